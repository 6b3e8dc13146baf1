"""The study's table: one row per run and mode, as CSV, Markdown (the paper's Tables IV-V) and a figure.

Columns (units in the names): ``name``, ``mode``, ``status`` (``ok`` | ``failed``), ``error`` (its
first line), ``norm_transl_rmse_percent`` (APE translation RMSE / distance travelled, %; Table IV),
``ape_rmse_m`` (after SE(3) alignment, Sim(3) for mono), ``joint_K_rmse_rad`` (dcc only; Table V),
``real_time_factor`` (processing time / data duration), ``wall_s`` (run + evaluation, s), ``reused``
(finished in an earlier invocation), ``folder``. The CSV keeps every number at full precision (the
values of the run's ``summary.json`` and ``evaluation.json``); the Markdown rounds them.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dcc_fg.plots.common import new_figure, save_figure

CSV_NAME = "results.csv"
MARKDOWN_NAME = "results.md"
FIGURE_NAME = "results_rmse.png"
MODE_COLORS = {"dcc": "tab:blue", "scc": "tab:orange", "mono": "tab:green"}


def joint_count(rows: Sequence[dict[str, Any]]) -> int:
    """The largest number of joints with an RMSE in any row."""
    return max((len(r.get("joint_rmse_rad") or []) for r in rows), default=0)


def columns(rows: Sequence[dict[str, Any]]) -> list[str]:
    joints = [f"joint_{j + 1}_rmse_rad" for j in range(joint_count(rows))]
    return ["name", "mode", "status", "error", "norm_transl_rmse_percent", "ape_rmse_m", *joints,
            "real_time_factor", "wall_s", "reused", "folder"]  # fmt: skip


def flat(row: dict[str, Any], n_joints: int) -> dict[str, Any]:
    """A row with the table's column names (joint RMSEs in their own columns; None where absent)."""
    joints = list(row.get("joint_rmse_rad") or [])
    out = {
        "name": row["name"],
        "mode": row["mode"],
        "status": row["status"],
        "error": row.get("error"),
        "norm_transl_rmse_percent": row.get("normalized_translation_rmse_percent"),
        "ape_rmse_m": row.get("ape_rmse_m"),
        **{f"joint_{j + 1}_rmse_rad": joints[j] if j < len(joints) else None for j in range(n_joints)},
        "real_time_factor": row.get("real_time_factor"),
        "wall_s": row.get("wall_s"),
        "reused": bool(row.get("reused")),
        "folder": row.get("folder"),
    }
    return out


def csv_text(rows: Sequence[dict[str, Any]]) -> str:
    """The CSV table (``repr`` of floats: they read back exactly; empty cells for missing values)."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, columns(rows), lineterminator="\n")
    writer.writeheader()
    n = joint_count(rows)
    for row in rows:
        writer.writerow({k: ("" if v is None else repr(v) if isinstance(v, float) else v)
                         for k, v in flat(row, n).items()})  # fmt: skip
    return buf.getvalue()


def read_csv(path: str | Path) -> list[dict[str, str]]:
    """The CSV table back as strings per column."""
    with Path(path).open(newline="") as f:
        return list(csv.DictReader(f))


def _num(value: Any, fmt: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return format(value, fmt)


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def status_text(row: dict[str, Any], width: int = 100) -> str:
    """``ok`` or ``failed: FIRST LINE OF THE ERROR`` (shortened to ``width`` characters)."""
    if row["status"] == "ok":
        return "ok"
    error = str(row.get("error") or "").splitlines()[0] if row.get("error") else "unknown error"
    text = f"failed: {error}"
    return text if len(text) <= width else text[: width - 3] + "..."


def markdown_runs(rows: Sequence[dict[str, Any]]) -> str:
    """Every run and mode in one Markdown table."""
    n = joint_count(rows)
    head = ["run", "mode", "status", "norm. transl. RMSE (%)", "APE RMSE (m)",
            *[f"joint {j + 1} RMSE (rad)" for j in range(n)], "real-time factor", "wall (s)"]  # fmt: skip
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in rows:
        f = flat(row, n)
        status = status_text(row) + (" (reused)" if f["reused"] else "")
        cells = [f["name"], f["mode"], status, _num(f["norm_transl_rmse_percent"], ".4f"), _num(f["ape_rmse_m"], ".4f"),
                 *[_num(f[f"joint_{j + 1}_rmse_rad"], ".2e") for j in range(n)], _num(f["real_time_factor"], ".3f"),
                 _num(f["wall_s"], ".1f")]  # fmt: skip
        lines.append("| " + " | ".join(_cell(str(c)) for c in cells) + " |")
    return "\n".join(lines)


def markdown_by_mode(rows: Sequence[dict[str, Any]]) -> str:
    """The paper's Table IV layout: normalized translation RMSE (%) per run (rows) and mode (columns),
    with the dcc joint RMSEs (Table V) in the last column."""
    names = list(dict.fromkeys(r["name"] for r in rows))
    modes = [m for m in MODE_COLORS if any(r["mode"] == m for r in rows)]
    by = {(r["name"], r["mode"]): r for r in rows}
    head = ["run", *[f"{m} (%)" for m in modes], "dcc joint RMSE (rad)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name in names:
        cells = [name]
        for m in modes:
            r = by.get((name, m))
            cells.append("" if r is None else "failed" if r["status"] != "ok"
                         else _num(r.get("normalized_translation_rmse_percent"), ".4f"))  # fmt: skip
        dcc = by.get((name, "dcc"))
        joints = (dcc or {}).get("joint_rmse_rad") or []
        cells.append(", ".join(f"{x:.2e}" for x in joints) or "-")
        lines.append("| " + " | ".join(_cell(c) for c in cells) + " |")
    return "\n".join(lines)


def markdown_text(rows: Sequence[dict[str, Any]], timing: str = "") -> str:
    """``results.md``: the run table, the per-mode table, and the timing line."""
    parts = ["# dcc-fg batch results", "", "## Every run and mode", "", markdown_runs(rows), "",
             "## Normalized translation RMSE by mode (Table IV) and dcc joint RMSE (Table V)", "",
             markdown_by_mode(rows), ""]  # fmt: skip
    if timing:
        parts += [timing, ""]
    return "\n".join(parts)


def write_figure(rows: Sequence[dict[str, Any]], path: Path) -> Path:
    """Grouped bars of the normalized translation RMSE (%) per run (groups) and mode (colours); a failed
    run is marked with an x at the bottom of its slot."""
    names = list(dict.fromkeys(r["name"] for r in rows))
    modes = [m for m in MODE_COLORS if any(r["mode"] == m for r in rows)]
    by = {(r["name"], r["mode"]): r for r in rows}
    fig = new_figure(max(6.0, 1.5 + 0.45 * len(names) * max(len(modes), 1)), 3.8)
    ax = fig.add_subplot(1, 1, 1)
    width = 0.8 / max(len(modes), 1)
    x = np.arange(len(names), dtype=float)
    failed_label = True
    for k, mode in enumerate(modes):
        pos = x - 0.4 + width * (k + 0.5)
        values = []
        for i, name in enumerate(names):
            r = by.get((name, mode))
            ok = r is not None and r["status"] == "ok" and r.get("normalized_translation_rmse_percent") is not None
            values.append(float(r["normalized_translation_rmse_percent"]) if ok else np.nan)  # type: ignore[index]
            if r is not None and r["status"] != "ok":
                ax.plot(pos[i], 0.0, "x", color="tab:red", label="failed" if failed_label else None, clip_on=False)
                failed_label = False
        ax.bar(pos, np.nan_to_num(values), width, color=MODE_COLORS[mode], label=mode)
    ax.set_xticks(x, names, rotation=20 if len(names) > 3 else 0, ha="right" if len(names) > 3 else "center")
    ax.set_ylabel("normalized translation RMSE (%)")
    ax.set_title("APE translation RMSE / distance travelled, per run and mode", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    return save_figure(fig, path)
