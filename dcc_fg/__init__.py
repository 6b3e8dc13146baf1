"""dcc-fg: encoderless calibration and gimbal-aware VIO for dynamic camera clusters."""

from dcc_fg.model import GimbalCalibration, load_calibration
from dcc_fg.util.provenance import package_version

__all__ = ["GimbalCalibration", "load_calibration", "__version__"]
__version__ = package_version()
