"""Writers for result files (atomic: a temporary file renamed over the target)."""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dcc_fg.model import _plain, write_text_atomic


def write_joint_angles_csv(path: Path, timestamps_ns: NDArray[np.int64], thetas: NDArray[np.float64]) -> None:
    """``timestamp_ns,theta_1,...,theta_L`` (radians), one row per snapshot / keyframe."""
    L = thetas.shape[1] if thetas.ndim == 2 else 0
    buf = io.StringIO()
    buf.write(",".join(["timestamp_ns"] + [f"theta_{j + 1}" for j in range(L)]) + "\n")
    for t, th in zip(timestamps_ns, thetas, strict=True):
        buf.write(",".join([str(int(t))] + [f"{x:.12g}" for x in th]) + "\n")
    write_text_atomic(Path(path), buf.getvalue())


def read_joint_angles_csv(path: Path) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Inverse of :func:`write_joint_angles_csv`."""
    path = Path(path)
    lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
    if not lines or not lines[0].startswith("timestamp_ns"):
        raise ValueError(f"{path}: expected a header 'timestamp_ns,theta_1,...'")
    rows = []
    for k, ln in enumerate(lines[1:], start=2):
        try:
            rows.append([float(x) for x in ln.split(",")])
        except ValueError:
            raise ValueError(f"{path}:{k}: not a number in '{ln}'") from None
    arr = np.array(rows, dtype=float).reshape(len(rows), -1)
    return arr[:, 0].astype(np.int64), arr[:, 1:]


def write_json(path: Path, data: dict[str, Any]) -> None:
    """Pretty JSON with numpy values converted (NaN -> null)."""
    write_text_atomic(Path(path), json.dumps(_plain(data), indent=2) + "\n")
