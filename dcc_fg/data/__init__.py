"""Measurement containers shared by the simulators, the readers and the estimators.

:mod:`dcc_fg.data.calibration` holds target observations and snapshots for the calibration,
:mod:`dcc_fg.data.vio` the IMU samples, feature-track frames and IMU configuration for the VIO.
The calibration names are re-exported here (``from dcc_fg.data import Snapshot``).
"""

from dcc_fg.data.calibration import CalibrationDataset, Observation, Snapshot, common_corners, with_joints

__all__ = ["CalibrationDataset", "Observation", "Snapshot", "common_corners", "with_joints"]
