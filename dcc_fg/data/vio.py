"""Data passed between the VIO front end, the back end and the readers.

The front end turns images into :class:`TrackFrame` objects; the back end consumes
``TrackFrame`` and :class:`ImuSamples` and never sees an image, so tracks from another
front end (e.g. the gtsam wheel's ``eqvio_processed_30s.csv``) can be fed in directly.

Frames: ``s`` static camera, ``d`` dynamic (gimbal) camera, ``I`` IMU/body, ``W`` world.
Units: nanoseconds, metres, radians, m/s^2, rad/s.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class ImuSamples:
    """IMU samples in the IMU frame I, sorted by time.

    ``t_ns`` (N,) int64 nanoseconds; ``acc`` (N, 3) specific force in m/s^2;
    ``gyro`` (N, 3) angular rate in rad/s.
    """

    t_ns: IntArray
    acc: FloatArray
    gyro: FloatArray

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])


@dataclass(frozen=True)
class TrackFrame:
    """Feature observations of one synchronized camera frame.

    ``static_xy`` / ``dynamic_xy`` are *undistorted normalized* image coordinates
    (x/z, y/z) in the static camera frame s and the dynamic camera frame d.
    ``static_ids`` / ``dynamic_ids`` index one landmark id space: an id seen by both
    cameras is the same world point (this is what makes the joint angles observable).
    ``dynamic_*`` is empty in ``mono`` mode or when the gimbal camera saw nothing.
    """

    timestamp_ns: int
    static_ids: IntArray
    static_xy: FloatArray
    dynamic_ids: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    dynamic_xy: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))


@dataclass(frozen=True)
class ImuConfig:
    """IMU noise (Kalibr imu.yaml names and units) and the static-camera mount.

    ``T_sI`` maps points from the IMU frame I into the static camera frame s
    (Kalibr's ``T_cam_imu`` of cam0). Noise densities are continuous-time:
    accelerometer m/s^2/sqrt(Hz), gyroscope rad/s/sqrt(Hz); random walks are
    m/s^3/sqrt(Hz) and rad/s^2/sqrt(Hz). ``gravity`` is the magnitude in m/s^2.
    Defaults are EuRoC's ADIS16448 figures.
    """

    T_sI: FloatArray = field(default_factory=lambda: np.eye(4))
    accelerometer_noise_density: float = 2.0e-3
    accelerometer_random_walk: float = 3.0e-3
    gyroscope_noise_density: float = 1.6968e-4
    gyroscope_random_walk: float = 1.9393e-5
    rate_hz: float = 200.0
    gravity: float = 9.81

    def to_dict(self) -> dict[str, Any]:
        return {
            "T_sI": np.asarray(self.T_sI, dtype=float).tolist(),
            "accelerometer_noise_density": float(self.accelerometer_noise_density),
            "accelerometer_random_walk": float(self.accelerometer_random_walk),
            "gyroscope_noise_density": float(self.gyroscope_noise_density),
            "gyroscope_random_walk": float(self.gyroscope_random_walk),
            "rate_hz": float(self.rate_hz),
            "gravity": float(self.gravity),
        }

    @staticmethod
    def from_dict(d: dict[str, Any], source: str = "<imu>") -> ImuConfig:
        kwargs: dict[str, Any] = {}
        for key, value in d.items():
            if key == "T_sI":
                T = np.asarray(value, dtype=float)
                if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                    raise ValueError(f"{source}: 'T_sI' must be a finite 4x4 matrix")
                kwargs[key] = T
            elif key in ImuConfig.__dataclass_fields__:
                kwargs[key] = float(value)
            else:
                raise ValueError(f"{source}: unknown field '{key}'")
        return ImuConfig(**kwargs)


def load_imu_config(path: str | Path) -> ImuConfig | None:
    """Read the optional ``imu:`` section of a calibration.yaml (None when absent)."""
    p = Path(path)
    with p.open() as f:
        d = yaml.safe_load(f) or {}
    if "imu" not in d:
        return None
    return ImuConfig.from_dict(d["imu"], f"{p}: imu")
