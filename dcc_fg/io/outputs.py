"""Writers for result files (atomic: a temporary file renamed over the target) and their readers.

Timestamps are integers in ns end to end: they are parsed as ``int`` from the text, never through
a float (a float64 holds ns stamps near 1.4e18 only to within 256 ns).
"""

from __future__ import annotations

import io
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dcc_fg.util.config import to_plain


def _umask() -> int:
    """The process's file-creation mask (read from /proc where possible: setting it is not thread-safe)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file and an atomic rename (the file gets the
    permissions of a normally created file, not the temporary file's 0600)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def plain(obj: Any) -> Any:
    """``obj`` as plain Python for YAML/JSON: numpy values, tuples, dataclasses converted, non-finite -> None."""
    return to_plain(obj, nonfinite_as_none=True)


def _write_stamped_csv(
    path: Path, column: str, stamps_ns: NDArray[np.int64], rows: NDArray[np.float64], fmt: str
) -> None:
    """``timestamp_ns,<column>_1,...,<column>_L``: one row per stamp (exact integer ns), values as ``fmt``."""
    L = rows.shape[1] if rows.ndim == 2 else 0
    buf = io.StringIO()
    buf.write(",".join(["timestamp_ns"] + [f"{column}_{j + 1}" for j in range(L)]) + "\n")
    for t, row in zip(stamps_ns, rows, strict=True):
        buf.write(",".join([str(int(t))] + [format(x, fmt) for x in row]) + "\n")
    write_text_atomic(Path(path), buf.getvalue())


def write_joint_angles_csv(path: Path, timestamps_ns: NDArray[np.int64], thetas: NDArray[np.float64]) -> None:
    """``timestamp_ns,theta_1,...,theta_L`` (radians), one row per snapshot / keyframe."""
    _write_stamped_csv(path, "theta", timestamps_ns, thetas, ".12g")


def write_joint_sigmas_csv(path: Path, timestamps_ns: NDArray[np.int64], sigmas: NDArray[np.float64]) -> None:
    """``timestamp_ns,sigma_theta_1,...,sigma_theta_L`` (1-sigma in radians, ``nan`` where unknown), one
    row per keyframe, beside ``joint_angles.csv``."""
    _write_stamped_csv(path, "sigma_theta", timestamps_ns, sigmas, ".6g")


def read_joint_angles_csv(path: Path) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Inverse of :func:`write_joint_angles_csv`: (N,) int64 stamps (ns, exact) and (N, L) angles (rad)."""
    path = Path(path)
    lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
    if not lines or not lines[0].startswith("timestamp_ns"):
        raise ValueError(f"{path}: expected a header 'timestamp_ns,theta_1,...'")
    stamps: list[int] = []
    rows: list[list[float]] = []
    for k, ln in enumerate(lines[1:], start=2):
        first, *rest = ln.split(",")
        try:
            stamps.append(int(first))
            rows.append([float(x) for x in rest])
        except ValueError:
            raise ValueError(f"{path}:{k}: not a number in '{ln}'") from None
    return np.array(stamps, dtype=np.int64), np.array(rows, dtype=float).reshape(len(rows), -1)


def write_json(path: Path, data: dict[str, Any]) -> None:
    """Pretty JSON with numpy values converted (NaN -> null)."""
    write_text_atomic(Path(path), json.dumps(plain(data), indent=2) + "\n")
