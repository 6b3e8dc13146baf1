"""yac detection CSV files (one per camera frame), as raw tables.

Layout of a detection folder: ``cam0/<timestamp_ns>.csv`` (static camera),
``cam1/<timestamp_ns>.csv`` (dynamic camera), optional ``joints.csv``
(``timestamp_ns,theta_1,...,theta_L``, radians).  Each CSV has the header
``#ts,tag_rows,tag_cols,tag_size,tag_spacing,kp_x,kp_y,p_x,p_y,p_z,tag_id,corner_idx`` and one row
per detected AprilGrid corner: ``kp`` is the pixel (u, v) in the distorted image, ``p`` the corner
in the target frame (metres), point id = 4 * tag_id + corner_idx (Kalibr order).  A file with only
the header is a frame without detections.  :mod:`dcc_fg.sources.detections` turns the tables into
observations and snapshots.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

COLUMNS = (
    "ts",
    "tag_rows",
    "tag_cols",
    "tag_size",
    "tag_spacing",
    "kp_x",
    "kp_y",
    "p_x",
    "p_y",
    "p_z",
    "tag_id",
    "corner_idx",
)
HEADER = "#" + ",".join(COLUMNS)


@dataclass(frozen=True)
class DetectionTable:
    """The rows of one yac detection file.

    Attributes:
        timestamp_ns: the ``ts`` column (the same on every row), or None for a file without rows.
        grid: ``(tag_rows, tag_cols, tag_size, tag_spacing)`` of the AprilGrid (the same on every
            row; tag size in metres, spacing as a ratio), or None without rows.
        pixels: (N, 2) ``kp_x, kp_y`` in the distorted image, pixels.
        points: (N, 3) ``p_x, p_y, p_z``, target frame, metres.
        tag_id, corner_idx: (N,) int64; ``corner_idx`` is checked to be 0..3.
    """

    timestamp_ns: int | None
    grid: tuple[int, int, float, float] | None
    pixels: NDArray[np.float64]
    points: NDArray[np.float64]
    tag_id: NDArray[np.int64]
    corner_idx: NDArray[np.int64]


def is_detection_csv(path: Path) -> bool:
    """True if the file's first line is yac's detection header."""
    try:
        with path.open() as f:
            first = f.readline()
    except (OSError, UnicodeDecodeError):
        return False
    return first.strip().replace(" ", "") == HEADER


def read_detection_table(path: str | Path) -> DetectionTable:
    """Parse one yac detection file.

    Raises:
        ValueError: naming the file for a wrong header, unparsable numbers, a wrong column
            count, rows with different timestamps or grid parameters, or a corner index outside 0..3.
    """
    path = Path(path)
    with path.open() as f:
        header = f.readline().strip().replace(" ", "")
        if header != HEADER:
            raise ValueError(f"{path}: header must be '{HEADER}', got '{header}'")
        body = f.read()
    if not body.strip():
        empty_i = np.zeros(0, dtype=np.int64)
        return DetectionTable(None, None, np.zeros((0, 2)), np.zeros((0, 3)), empty_i, empty_i)
    try:
        data = np.loadtxt(body.splitlines(), delimiter=",", ndmin=2, dtype=np.float64)
    except ValueError as exc:
        raise ValueError(f"{path}: not a numeric table ({exc})") from None
    if data.shape[1] != len(COLUMNS):
        raise ValueError(f"{path}: expected {len(COLUMNS)} columns, got {data.shape[1]}")
    # ts is a 19-digit integer that float64 cannot hold exactly: read it as text.
    stamps = {int(line.split(",", 1)[0]) for line in body.splitlines() if line.strip()}
    if len(stamps) != 1:
        raise ValueError(f"{path}: rows have {len(stamps)} different timestamps in column 'ts'")
    params = np.unique(data[:, 1:5], axis=0)
    if params.shape[0] != 1:
        raise ValueError(f"{path}: rows disagree on tag_rows, tag_cols, tag_size, tag_spacing")
    rows, cols, size, spacing = params[0]
    corner = data[:, 11].astype(np.int64)
    if ((corner < 0) | (corner > 3)).any():
        raise ValueError(f"{path}: corner_idx must be 0..3")
    return DetectionTable(
        timestamp_ns=stamps.pop(),
        grid=(int(rows), int(cols), float(size), float(spacing)),
        pixels=data[:, 5:7],
        points=data[:, 7:10],
        tag_id=data[:, 10].astype(np.int64),
        corner_idx=corner,
    )


def write_detection_table(
    path: str | Path,
    timestamp_ns: int,
    grid: tuple[int, int, float, float],
    ids: NDArray[np.int64],
    pixels: NDArray[np.float64],
    points: NDArray[np.float64],
) -> None:
    """Write one frame's corners in yac's layout: point ``ids`` (4 * tag_id + corner_idx), their
    ``pixels`` (N, 2) and target-frame ``points`` (N, 3, metres) on the AprilGrid ``grid``
    ``(tag_rows, tag_cols, tag_size, tag_spacing)``."""
    rows, cols, size, spacing = grid
    with Path(path).open("w") as f:
        f.write(HEADER + "\n")
        for pid, (u, v), p in zip(ids, pixels, points, strict=True):
            f.write(
                f"{timestamp_ns},{rows},{cols},{size:.6f},{spacing:.6f},"
                f"{u:.10f},{v:.10f},{p[0]:.6f},{p[1]:.6f},{p[2]:.6f},{pid // 4},{pid % 4}\n"
            )
