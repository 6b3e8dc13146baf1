"""Global strategy of the encoderless calibration (issue 14): several starts, keep the best minimum.

Stub: one start from the automatic initialization (or from ``initial``). The full strategy
(multi-start over the auto-init's distinct minima, comparison of final costs, ambiguity report)
replaces this body; the signature stays.
"""

from __future__ import annotations

from dataclasses import replace

from dcc_fg.auto_init import auto_initialize
from dcc_fg.calibrate import CalibrationOptions, CalibrationResult, calibrate
from dcc_fg.data import CalibrationDataset
from dcc_fg.model import GimbalCalibration


def calibrate_global(
    data: CalibrationDataset,
    n_joints: int,
    options: CalibrationOptions | None = None,
    initial: GimbalCalibration | None = None,
) -> CalibrationResult:
    """Encoderless (or encoders) calibration that searches for the global minimum.

    Args:
        data: the snapshots (``joints`` are guesses in encoderless mode, readings with encoders).
        n_joints: L.
        options: solver options.
        initial: hand-measured kinematics (``--gimbal``), used as one more start; None: automatic only.

    Returns:
        the result of the start with the lowest final cost; ``extra["global"]`` describes the starts.
    """
    opt = options or CalibrationOptions()
    if initial is not None:
        return calibrate(data, initial, opt)
    cal0, thetas, _ = auto_initialize(data, n_joints)
    if opt.mode != "encoders":
        data = replace(data, snapshots=[replace(s, joints=t) for s, t in zip(data.snapshots, thetas, strict=True)])
    return calibrate(data, cal0, opt)
