"""TUM trajectory files: one pose per line, ``t[s] tx ty tz qx qy qz qw`` (``#`` comments allowed).

A pose ``T_WI`` maps body/IMU points into the world frame (translation in metres, Hamilton
quaternion x, y, z, w). Timestamps are written with nanosecond resolution and read back as
integer ns (never through a float).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from dcc_fg.io import validate
from dcc_fg.io.outputs import write_text_atomic

NS = 1_000_000_000
DEFAULT_COMMENT = "timestamp tx ty tz qx qy qz qw"


def ns_to_text(t_ns: int) -> str:
    """Seconds with exactly nine decimals from integer ns (``1.000000001`` for 1_000_000_001)."""
    return f"{int(t_ns) // NS}.{int(t_ns) % NS:09d}"


def tum_text(
    t_ns: NDArray[np.int64],
    T: NDArray[np.float64],
    comment: str = DEFAULT_COMMENT,
    quaternion_decimals: int = 9,
    w_nonnegative: bool = False,
) -> str:
    """TUM lines for poses ``T`` (N, 4, 4) at times ``t_ns`` (N,) ns, after one ``# comment`` line.

    Positions get 9 decimals, quaternions ``quaternion_decimals``; ``w_nonnegative`` picks the
    sign of each quaternion with ``w >= 0`` (else scipy's choice).
    """
    T = np.asarray(T, float).reshape(-1, 4, 4)
    q = Rotation.from_matrix(T[:, :3, :3]).as_quat(canonical=w_nonnegative)  # x, y, z, w
    buf = io.StringIO()
    buf.write(f"# {comment}\n")
    for t, p, qq in zip(np.asarray(t_ns, dtype=np.int64), T[:, :3, 3], q, strict=True):
        pos = " ".join(f"{x:.9f}" for x in p)
        quat = " ".join(f"{x:.{quaternion_decimals}f}" for x in qq)
        buf.write(f"{ns_to_text(int(t))} {pos} {quat}\n")
    return buf.getvalue()


def write_tum(
    path: str | Path,
    t_ns: NDArray[np.int64],
    T: NDArray[np.float64],
    comment: str = DEFAULT_COMMENT,
    quaternion_decimals: int = 9,
    w_nonnegative: bool = False,
) -> None:
    """Write poses ``T`` (N, 4, 4) at times ``t_ns`` atomically (format of :func:`tum_text`)."""
    write_text_atomic(Path(path), tum_text(t_ns, T, comment, quaternion_decimals, w_nonnegative))


def text_to_ns(text: str) -> int:
    """Integer ns of a decimal seconds string (``"-1.5"`` -> -1_500_000_000); digits past 9 decimals are cut."""
    whole, _, frac = text.partition(".")
    sign = -1 if whole.startswith("-") else 1
    return sign * (abs(int(whole)) * NS + int((frac + "000000000")[:9]))


#: Largest accepted | ||q|| - 1 | of a TUM quaternion (files written with 6 decimals are off by ~1e-6;
#: columns in the wrong order or a non-quaternion are off by far more).
QUATERNION_NORM_TOLERANCE = 1e-2


def read_tum(path: str | Path) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Read a TUM file: times (N,) int64 ns and poses (N, 4, 4).

    Quaternions are normalized after the check below.

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file and line for: a folder, bytes that are not UTF-8, an empty
            file or one without poses, a line without 8 columns, text that is not a number, a
            non-finite value, a quaternion whose norm is not 1 (within 1e-2), or a timestamp
            that does not increase.
    """
    path = Path(path)
    form = "one pose per line: t[s] tx ty tz qx qy qz qw"
    text = validate.read_text(path, "TUM trajectory", form)
    times: list[int] = []
    rows: list[list[float]] = []
    for k, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise ValueError(f"{path}:{k}: expected 8 columns 't tx ty tz qx qy qz qw', got {len(parts)}")
        try:
            t_ns = text_to_ns(parts[0])
            values = [float(x) for x in parts[1:]]
        except ValueError:
            raise ValueError(f"{path}:{k}: not a number in '{line}' ({form})") from None
        bad = [
            name
            for name, x in zip(("tx", "ty", "tz", "qx", "qy", "qz", "qw"), values, strict=True)
            if not np.isfinite(x)
        ]
        if bad:
            raise ValueError(f"{path}:{k}: {bad[0]} must be a finite number, got '{line}'")
        norm = float(np.linalg.norm(values[3:7]))
        if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
            raise ValueError(
                f"{path}:{k}: quaternion qx qy qz qw has norm {norm:.4g}, expected a unit quaternion ({form})"
            )
        if times and t_ns <= times[-1]:
            raise ValueError(
                f"{path}:{k}: timestamp {parts[0]} s does not increase (previous pose at {ns_to_text(times[-1])} s); "
                "poses must be in time order, one per stamp"
            )
        times.append(t_ns)
        rows.append(values)
    if not rows:
        raise ValueError(f"{path}: no poses ({form})")
    arr = np.array(rows)
    T = np.tile(np.eye(4), (arr.shape[0], 1, 1))
    T[:, :3, :3] = Rotation.from_quat(arr[:, 3:7]).as_matrix()
    T[:, :3, 3] = arr[:, :3]
    return np.array(times, dtype=np.int64), T
