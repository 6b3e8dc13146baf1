"""dcc-fg: encoderless calibration and gimbal-aware VIO for dynamic camera clusters."""

from dcc_fg.model import GimbalCalibration, load_calibration

__all__ = ["GimbalCalibration", "load_calibration"]
__version__ = "0.1.0"
