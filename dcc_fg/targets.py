"""Calibration targets: Kalibr target YAML and the target-frame corner geometry.

Target frame t: origin at the first corner, x along the columns, y along the rows, z = 0 on the
board (points on the board have z = 0), metres.

* ``checkerboard``: ``targetCols`` x ``targetRows`` inner corners; corner id = row * cols + col,
  the order of OpenCV's ``findChessboardCorners`` with pattern size (cols, rows).
* ``aprilgrid``: ``tagCols`` x ``tagRows`` tag36h11 tags of side ``tagSize`` with gaps of
  ``tagSpacing * tagSize``; tag ``k`` sits at row ``k // tagCols``, column ``k % tagCols``;
  point id = 4 * tag_id + corner with corners numbered as Kalibr and yac do (0 bottom-left,
  1 bottom-right, 2 top-right, 3 top-left, in the target frame).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class TargetGeometry:
    """A planar fiducial target (Kalibr's parameters).

    Attributes:
        target_type: ``checkerboard`` or ``aprilgrid``.
        cols, rows: inner corners (checkerboard) or tags (aprilgrid) per row / column.
        col_spacing, row_spacing: checkerboard square size along x and y, metres.
        tag_size: aprilgrid tag side, metres; tag_spacing: gap / tag_size (ratio).
    """

    target_type: str
    cols: int
    rows: int
    col_spacing: float = 0.0
    row_spacing: float = 0.0
    tag_size: float = 0.0
    tag_spacing: float = 0.0

    @staticmethod
    def checkerboard(cols: int, rows: int, spacing: float, row_spacing: float | None = None) -> TargetGeometry:
        """Checkerboard with ``cols`` x ``rows`` inner corners and square size ``spacing`` metres."""
        return TargetGeometry("checkerboard", cols, rows, spacing, spacing if row_spacing is None else row_spacing)

    @staticmethod
    def aprilgrid(cols: int, rows: int, tag_size: float, tag_spacing: float) -> TargetGeometry:
        """Kalibr AprilGrid of ``cols`` x ``rows`` tag36h11 tags."""
        return TargetGeometry("aprilgrid", cols, rows, tag_size=tag_size, tag_spacing=tag_spacing)

    @property
    def points(self) -> FloatArray:
        """(M, 3) corner positions in the target frame; row index = point id."""
        if self.target_type == "checkerboard":
            r, c = np.meshgrid(np.arange(self.rows), np.arange(self.cols), indexing="ij")
            xyz = np.stack([c.ravel() * self.col_spacing, r.ravel() * self.row_spacing, np.zeros(r.size)], axis=1)
            return xyz.astype(float)
        pitch = self.tag_size * (1.0 + self.tag_spacing)
        out = np.zeros((4 * self.cols * self.rows, 3))
        offsets = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]) * self.tag_size
        for tag in range(self.cols * self.rows):
            origin = np.array([(tag % self.cols) * pitch, (tag // self.cols) * pitch])
            out[4 * tag : 4 * tag + 4, :2] = origin + offsets
        return out

    @property
    def size(self) -> tuple[float, float]:
        """Extent (x, y) of the corner set in metres."""
        p = self.points
        return float(np.ptp(p[:, 0])), float(np.ptp(p[:, 1]))

    def to_kalibr(self) -> dict[str, object]:
        """Kalibr target YAML dictionary."""
        if self.target_type == "checkerboard":
            return {
                "target_type": "checkerboard",
                "targetCols": self.cols,
                "targetRows": self.rows,
                "rowSpacingMeters": self.row_spacing,
                "colSpacingMeters": self.col_spacing,
            }
        return {
            "target_type": "aprilgrid",
            "tagCols": self.cols,
            "tagRows": self.rows,
            "tagSize": self.tag_size,
            "tagSpacing": self.tag_spacing,
        }


def _require(d: dict[str, object], key: str, source: str) -> object:
    if key not in d:
        raise ValueError(f"{source}: target YAML is missing the field '{key}'")
    return d[key]


def target_from_dict(d: dict[str, object], source: str = "<target>") -> TargetGeometry:
    """Parse a Kalibr target dictionary; errors name ``source`` and the missing field."""
    kind = _require(d, "target_type", source)
    if kind == "checkerboard":
        return TargetGeometry(
            "checkerboard",
            int(_require(d, "targetCols", source)),  # type: ignore[arg-type]
            int(_require(d, "targetRows", source)),  # type: ignore[arg-type]
            col_spacing=float(_require(d, "colSpacingMeters", source)),  # type: ignore[arg-type]
            row_spacing=float(_require(d, "rowSpacingMeters", source)),  # type: ignore[arg-type]
        )
    if kind == "aprilgrid":
        return TargetGeometry.aprilgrid(
            int(_require(d, "tagCols", source)),  # type: ignore[arg-type]
            int(_require(d, "tagRows", source)),  # type: ignore[arg-type]
            float(_require(d, "tagSize", source)),  # type: ignore[arg-type]
            float(_require(d, "tagSpacing", source)),  # type: ignore[arg-type]
        )
    raise ValueError(f"{source}: target_type '{kind}' is not supported (checkerboard, aprilgrid)")


def load_target(path: str | Path) -> TargetGeometry:
    """Read a Kalibr target YAML file."""
    path = Path(path)
    with path.open() as f:
        d = yaml.safe_load(f)
    if not isinstance(d, dict):
        raise ValueError(f"{path}: not a YAML mapping")
    return target_from_dict(d, str(path))
