"""Parse the operating range (``--range``) and the accuracy tolerance (``--tolerance``) of ``dcc-fg plan``.

* ``--range "-30:30,-20:45"``: one ``lo:hi`` pair per joint, in degrees, in the joint-angle
  convention of the calibration (the angles of its ``joint_angles.csv``: the calibration fixes the
  constant offsets of joints 1 and L, docs/architecture.md). Returned as an (L, 2) array in radians.
* ``--tolerance 1mrad,1mm``: the largest acceptable 1-sigma of ``T_ds`` over the range, rotation
  then translation, each with its unit (rotation: ``urad``, ``mrad``, ``rad``, ``deg``; translation:
  ``um``, ``mm``, ``cm``, ``m``). Returned as ``(rad, m)``.

Errors are ``ValueError`` whose message names the option and says what a valid value looks like.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

ROTATION_UNITS = {"urad": 1e-6, "mrad": 1e-3, "rad": 1.0, "deg": np.pi / 180.0}
TRANSLATION_UNITS = {"um": 1e-6, "mm": 1e-3, "cm": 1e-2, "m": 1.0}
RANGE_EXAMPLE = '--range "-30:30,-20:45" (degrees, lo:hi per joint)'
TOLERANCE_EXAMPLE = "--tolerance 1mrad,1mm (rotation with urad|mrad|rad|deg, translation with um|mm|cm|m)"
#: Default margin added on each side of the joint angles the data covered, as a fraction of the span
#: (at least ``DEFAULT_MARGIN_MIN_DEG``).
DEFAULT_MARGIN_FRACTION = 0.1
DEFAULT_MARGIN_MIN_DEG = 2.0
_NUMBER = r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?"


@dataclass(frozen=True)
class Tolerance:
    """Largest acceptable 1-sigma of ``T_ds``: rotation (rad, root of the trace of the rotation block,
    i.e. the RMS rotation-error angle) and translation (m, likewise)."""

    rotation: float
    translation: float

    def describe(self) -> str:
        return f"{self.rotation * 1e3:.4g} mrad, {self.translation * 1e3:.4g} mm"


def parse_range(text: str, n_joints: int) -> FloatArray:
    """``"lo:hi,lo:hi,..."`` (degrees, one pair per joint) -> (L, 2) radians.

    Raises ValueError naming ``--range`` for a wrong count of joints, a pair that is not two numbers,
    ``lo >= hi``, non-finite values or a span beyond one turn.
    """
    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"--range: empty; expected {RANGE_EXAMPLE}")
    parts = [p.strip() for p in text.split(",")]
    if len(parts) != n_joints:
        raise ValueError(
            f"--range {text!r}: {len(parts)} joint range(s) given, but the calibration has {n_joints} joint(s); "
            f"expected {RANGE_EXAMPLE}"
        )
    out = np.zeros((n_joints, 2))
    for j, part in enumerate(parts):
        m = re.fullmatch(rf"\s*({_NUMBER})\s*:\s*({_NUMBER})\s*(?:deg)?\s*", part)
        if m is None:
            raise ValueError(
                f"--range {text!r}: joint {j + 1} '{part}' is not lo:hi in degrees; expected {RANGE_EXAMPLE}"
            )
        lo, hi = float(m.group(1)), float(m.group(2))
        if not (np.isfinite(lo) and np.isfinite(hi)):
            raise ValueError(f"--range {text!r}: joint {j + 1} has a non-finite limit")
        if lo >= hi:
            raise ValueError(f"--range {text!r}: joint {j + 1} needs lo < hi, got {lo:g}:{hi:g} deg")
        if hi - lo > 360.0:
            raise ValueError(f"--range {text!r}: joint {j + 1} spans {hi - lo:g} deg, more than one turn")
        out[j] = np.deg2rad([lo, hi])
    return out


def format_range(ranges: FloatArray) -> str:
    """(L, 2) radians -> the ``--range`` text (degrees)."""
    return ",".join(f"{np.rad2deg(lo):.6g}:{np.rad2deg(hi):.6g}" for lo, hi in np.asarray(ranges, float))


def _quantity(text: str, part: str, units: dict[str, float], what: str) -> float:
    m = re.fullmatch(rf"\s*({_NUMBER})\s*([a-zA-Z]+)\s*", part)
    if m is None:
        raise ValueError(
            f"--tolerance {text!r}: {what} '{part}' is not a number with a unit; expected {TOLERANCE_EXAMPLE}"
        )
    value, unit = float(m.group(1)), m.group(2).lower()
    if unit not in units:
        raise ValueError(
            f"--tolerance {text!r}: {what} unit '{m.group(2)}' is not one of {', '.join(units)}; "
            f"expected {TOLERANCE_EXAMPLE}"
        )
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"--tolerance {text!r}: {what} must be a positive number, got {value:g}")
    return value * units[unit]


def parse_tolerance(text: str) -> Tolerance:
    """``"1mrad,1mm"`` -> :class:`Tolerance` (rad, m). Either order is accepted; the units tell which
    is which. Raises ValueError naming ``--tolerance``."""
    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"--tolerance: empty; expected {TOLERANCE_EXAMPLE}")
    parts = [p.strip() for p in text.split(",")]
    if len(parts) != 2:
        raise ValueError(f"--tolerance {text!r}: expected two values (rotation,translation), e.g. {TOLERANCE_EXAMPLE}")
    kinds = []
    for p in parts:
        m = re.fullmatch(rf"\s*{_NUMBER}\s*([a-zA-Z]+)\s*", p)
        unit = m.group(1).lower() if m else ""
        kinds.append("rotation" if unit in ROTATION_UNITS else "translation" if unit in TRANSLATION_UNITS else "?")
    if sorted(kinds) != ["rotation", "translation"]:
        if "?" not in kinds:
            raise ValueError(
                f"--tolerance {text!r}: needs one rotation and one translation; expected {TOLERANCE_EXAMPLE}"
            )
        bad = parts[kinds.index("?")]
        units = {**ROTATION_UNITS, **TRANSLATION_UNITS}
        _quantity(text, bad, units, "value")  # raises with the precise reason
        raise ValueError(f"--tolerance {text!r}: expected {TOLERANCE_EXAMPLE}")
    rot = parts[kinds.index("rotation")]
    tra = parts[kinds.index("translation")]
    return Tolerance(
        _quantity(text, rot, ROTATION_UNITS, "rotation"), _quantity(text, tra, TRANSLATION_UNITS, "translation")
    )


def default_range(joint_angles: FloatArray) -> FloatArray:
    """The range the data covered (min, max per joint of the estimated angles, rad) plus a margin of
    ``DEFAULT_MARGIN_FRACTION`` of the span on each side (at least ``DEFAULT_MARGIN_MIN_DEG``); (L, 2) rad."""
    th = np.asarray(joint_angles, dtype=float)
    if th.ndim != 2 or th.shape[0] == 0:
        raise ValueError("the default operating range needs the calibration's joint angles (none given)")
    lo, hi = th.min(axis=0), th.max(axis=0)
    margin = np.maximum(DEFAULT_MARGIN_FRACTION * (hi - lo), np.deg2rad(DEFAULT_MARGIN_MIN_DEG))
    return np.column_stack([lo - margin, hi + margin])
