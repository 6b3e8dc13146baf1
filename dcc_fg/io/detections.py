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

from dcc_fg.io import validate

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


def _bad_line(path: Path, lines: list[tuple[int, str]]) -> ValueError:
    """The error for the first line of ``lines`` that is not 12 comma-separated numbers."""
    for line_no, line in lines:
        fields = line.split(",")
        if len(fields) != len(COLUMNS):
            return ValueError(f"{path}:{line_no}: expected {len(COLUMNS)} columns ({HEADER[1:]}), got {len(fields)}")
        for name, field in zip(COLUMNS, fields, strict=True):
            try:
                float(field)
            except ValueError:
                return ValueError(f"{path}:{line_no}: column {name} is not a number: {field.strip()!r}")
    return ValueError(f"{path}: not a numeric table")


def read_detection_table(path: str | Path) -> DetectionTable:
    """Parse one yac detection file, checking every value.

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file (and line, column) for: a folder, bytes that are not UTF-8, an
            empty file, a wrong header, unparsable numbers, a wrong column count, non-finite
            values, a ``ts`` that is not a positive integer or differs between rows, grid
            parameters that differ between rows or are not positive (integer tag counts), a
            ``tag_id`` that is not a non-negative integer, or a ``corner_idx`` outside 0..3.
    """
    path = Path(path)
    text = validate.read_text(path, "yac detection CSV", f"header {HEADER}")
    header, _, body = text.partition("\n")
    header = header.strip().replace(" ", "")
    if header != HEADER:
        raise ValueError(f"{path}: header must be '{HEADER}', got '{header}'")
    lines = [(k, line) for k, line in enumerate(body.splitlines(), start=2) if line.strip()]
    if not lines:
        empty_i = np.zeros(0, dtype=np.int64)
        return DetectionTable(None, None, np.zeros((0, 2)), np.zeros((0, 3)), empty_i, empty_i)
    try:
        data = np.loadtxt([line for _, line in lines], delimiter=",", ndmin=2, dtype=np.float64)
    except ValueError:
        raise _bad_line(path, lines) from None
    if data.shape[1] != len(COLUMNS):
        raise ValueError(f"{path}: expected {len(COLUMNS)} columns ({HEADER[1:]}), got {data.shape[1]}")
    bad = ~np.isfinite(data)
    if bad.any():
        r, c = (int(x) for x in np.argwhere(bad)[0])
        raise ValueError(f"{path}:{lines[r][0]}: column {COLUMNS[c]} must be a finite number, got {data[r, c]:g}")
    # ts is a 19-digit integer that float64 cannot hold exactly: read it as text.
    stamps: set[int] = set()
    for line_no, line in lines:
        field = line.split(",", 1)[0].strip()
        try:
            ts = int(field)
        except ValueError:
            raise ValueError(f"{path}:{line_no}: column ts must be an integer timestamp in ns, got {field!r}") from None
        if ts <= 0:
            raise ValueError(f"{path}:{line_no}: column ts must be a positive timestamp in ns, got {ts}")
        stamps.add(ts)
    if len(stamps) != 1:
        raise ValueError(f"{path}: rows have {len(stamps)} different timestamps in column 'ts'")
    params = np.unique(data[:, 1:5], axis=0)
    if params.shape[0] != 1:
        raise ValueError(f"{path}: rows disagree on tag_rows, tag_cols, tag_size, tag_spacing")
    rows, cols, size, spacing = params[0]
    where = f"{path}:{lines[0][0]}: column"
    validate.integer(rows, f"{where} tag_rows", unit="tags", minimum=1)
    validate.integer(cols, f"{where} tag_cols", unit="tags", minimum=1)
    validate.number(size, f"{where} tag_size", unit="metres", positive=True)
    validate.number(spacing, f"{where} tag_spacing", unit="", positive=True)
    for c in (COLUMNS.index("tag_id"), COLUMNS.index("corner_idx")):
        frac = data[:, c] != np.round(data[:, c])
        if frac.any() or (data[:, c] < 0).any():
            r = int(np.flatnonzero(frac | (data[:, c] < 0))[0])
            raise ValueError(
                f"{path}:{lines[r][0]}: column {COLUMNS[c]} must be a non-negative integer, got {data[r, c]:g}"
            )
    corner = data[:, 11].astype(np.int64)
    if ((corner < 0) | (corner > 3)).any():
        r = int(np.flatnonzero((corner < 0) | (corner > 3))[0])
        raise ValueError(f"{path}:{lines[r][0]}: corner_idx must be 0..3, got {corner[r]}")
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
