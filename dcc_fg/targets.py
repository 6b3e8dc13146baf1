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

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from dcc_fg.io import validate

log = logging.getLogger(__name__)

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


#: Fewest inner corners per row / column of a checkerboard that OpenCV's detector accepts.
MIN_CHECKERBOARD_CORNERS = 3

#: A square or tag side beyond this (metres) was probably written in millimetres or centimetres.
MAX_PLAUSIBLE_SIZE_M = 2.0


def _count(d: dict[str, object], key: str, source: str, what: str, minimum: int) -> int:
    return validate.integer(_require(d, key, source), f"{source}: {key}", unit=what, minimum=minimum)


def _length(d: dict[str, object], key: str, source: str) -> float:
    x = validate.number(_require(d, key, source), f"{source}: {key}", unit="metres", positive=True)
    if x > MAX_PLAUSIBLE_SIZE_M:
        log.warning("%s: %s = %g m is larger than %g m; is it in millimetres? Kalibr expects metres", source, key, x,
                    MAX_PLAUSIBLE_SIZE_M)  # fmt: skip
    return x


def target_from_dict(d: dict[str, object], source: str = "<target>") -> TargetGeometry:
    """Parse a Kalibr target dictionary, checking every field.

    Raises:
        ValueError: naming ``source`` and the field: a missing field, an unknown ``target_type``,
            corner / tag counts that are not integers (checkerboard: >= 3 inner corners per row and
            column, OpenCV's minimum; aprilgrid: >= 1 tag), sizes that are not positive finite
            metres, a ``tagSpacing`` ratio that is not a positive finite number.
    """
    kind = _require(d, "target_type", source)
    if kind == "checkerboard":
        n = MIN_CHECKERBOARD_CORNERS
        return TargetGeometry(
            "checkerboard",
            _count(d, "targetCols", source, "inner corners", n),
            _count(d, "targetRows", source, "inner corners", n),
            col_spacing=_length(d, "colSpacingMeters", source),
            row_spacing=_length(d, "rowSpacingMeters", source),
        )
    if kind == "aprilgrid":
        return TargetGeometry.aprilgrid(
            _count(d, "tagCols", source, "tags", 1),
            _count(d, "tagRows", source, "tags", 1),
            _length(d, "tagSize", source),
            validate.number(
                _require(d, "tagSpacing", source), f"{source}: tagSpacing", unit="", positive=True
            ),  # fmt: skip
        )
    raise ValueError(f"{source}: target_type must be 'checkerboard' or 'aprilgrid', got {kind!r}")


def load_target(path: str | Path) -> TargetGeometry:
    """Read a Kalibr target YAML file (every field checked, see :func:`target_from_dict`)."""
    path = Path(path)
    d = validate.load_yaml(path, "Kalibr target", "target_type: checkerboard | aprilgrid and its fields")
    return target_from_dict(d, str(path))
