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

#: Standard gravity, m/s^2 (the unit of accelerometer full scales, "16 g").
STANDARD_GRAVITY = 9.80665
#: 2000 deg/s in rad/s: the largest full scale of common MEMS gyroscopes.
GYRO_RANGE_RAD_S = float(np.deg2rad(2000.0))
#: Fields of :class:`ImuConfig` that must be positive and finite, with their units.
POSITIVE_FIELDS = {
    "accelerometer_noise_density": "m/s^2/sqrt(Hz)",
    "accelerometer_random_walk": "m/s^3/sqrt(Hz)",
    "gyroscope_noise_density": "rad/s/sqrt(Hz)",
    "gyroscope_random_walk": "rad/s^2/sqrt(Hz)",
    "rate_hz": "Hz",
    "gravity": "m/s^2",
    "acc_range": "m/s^2",
    "gyro_range": "rad/s",
}
#: Largest deviation of R^T R from the identity accepted for a rotation read from a file (the
#: 8-12 printed digits of Kalibr / EuRoC YAML files are well inside it).
ROTATION_TOLERANCE = 1e-5


def check_rigid_transform(T: Any, name: str) -> None:
    """ValueError naming ``name`` unless ``T`` is a finite 4x4 rigid transform (rotation orthonormal
    within :data:`ROTATION_TOLERANCE` with determinant +1, last row ``0 0 0 1``)."""
    A = np.asarray(T, dtype=float)
    if A.shape != (4, 4) or not np.all(np.isfinite(A)):
        raise ValueError(f"'{name}' must be a finite 4x4 matrix, got shape {A.shape}")
    if not np.allclose(A[3], [0.0, 0.0, 0.0, 1.0], atol=ROTATION_TOLERANCE):
        raise ValueError(f"'{name}': the last row must be 0 0 0 1, got {A[3].tolist()}")
    R = A[:3, :3]
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if err > ROTATION_TOLERANCE or det < 0:
        raise ValueError(
            f"'{name}': the upper-left 3x3 block is not a rotation (max |R^T R - I| = {err:.2e}, det = {det:.4f}; "
            "expected an orthonormal matrix with determinant +1)"
        )


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
class CameraTracks:
    """Observations of one further camera of an N-camera run in one frame.

    ``camera`` is the camera's run index (>= 2, :class:`dcc_fg.data.cameras.RunCamera`); ``ids`` share
    the landmark id space of :class:`TrackFrame`; ``xy`` are undistorted normalized coordinates in that
    camera's frame. The image is taken as exposed with the frame's static image (cameras of a cluster
    are triggered together; its stamp was paired with the static stamp within the pairing tolerance).
    """

    camera: int
    ids: IntArray
    xy: FloatArray


@dataclass(frozen=True)
class TrackFrame:
    """Feature observations of one synchronized camera frame.

    ``static_xy`` / ``dynamic_xy`` are *undistorted normalized* image coordinates
    (x/z, y/z) in the static camera frame s and the dynamic camera frame d.
    ``static_ids`` / ``dynamic_ids`` index one landmark id space: an id seen by both
    cameras is the same world point (this is what makes the joint angles observable).
    ``dynamic_*`` is empty in ``mono`` mode or when the gimbal camera saw nothing. ``extra`` holds the
    tracks of further cameras of an N-camera cluster (run index >= 2), in the same id space.
    ``timestamp_ns`` is the static image's header stamp; ``dynamic_timestamp_ns`` the gimbal image's
    (None: the same stamp, a synchronized pair). Stamps are on the cameras' clocks: the smoother
    relates them to the IMU clock with its time offsets.
    """

    timestamp_ns: int
    static_ids: IntArray
    static_xy: FloatArray
    dynamic_ids: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    dynamic_xy: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))
    dynamic_timestamp_ns: int | None = None
    extra: tuple[CameraTracks, ...] = ()

    @property
    def dynamic_gap_s(self) -> float:
        """Gimbal stamp minus static stamp, s (0 for a synchronized pair)."""
        if self.dynamic_timestamp_ns is None:
            return 0.0
        return (int(self.dynamic_timestamp_ns) - int(self.timestamp_ns)) / 1e9


@dataclass(frozen=True)
class ImuConfig:
    """IMU noise (Kalibr imu.yaml names and units) and the static-camera mount.

    ``T_sI`` maps points from the IMU frame I into the static camera frame s
    (Kalibr's ``T_cam_imu`` of cam0). Noise densities are continuous-time:
    accelerometer m/s^2/sqrt(Hz), gyroscope rad/s/sqrt(Hz); random walks are
    m/s^3/sqrt(Hz) and rad/s^2/sqrt(Hz). ``gravity`` is the magnitude in m/s^2.
    Defaults are EuRoC's ADIS16448 figures. ``acc_range`` (m/s^2) and ``gyro_range`` (rad/s) are
    the sensor's measurement range per axis (default 16 g and 2000 deg/s, the largest full scales
    of common MEMS IMUs): a sample beyond it cannot be a measurement and is dropped by the readers.
    ``time_offsets`` = ``(t_s, t_d)`` (s, optional) are the cameras' time offsets from the IMU clock,
    ``t_imu = t_cam_stamp + t_offset`` (Kalibr's ``timeshift_cam_imu``): the VIO's start values.

    Every number is checked on construction (finite; positive noise, rate, gravity and ranges;
    ``T_sI`` a rigid transform: orthonormal rotation with determinant +1, last row 0 0 0 1);
    :meth:`from_dict` names the source file in the error.
    """

    T_sI: FloatArray = field(default_factory=lambda: np.eye(4))
    accelerometer_noise_density: float = 2.0e-3
    accelerometer_random_walk: float = 3.0e-3
    gyroscope_noise_density: float = 1.6968e-4
    gyroscope_random_walk: float = 1.9393e-5
    rate_hz: float = 200.0
    gravity: float = 9.81
    acc_range: float = 16.0 * STANDARD_GRAVITY
    gyro_range: float = GYRO_RANGE_RAD_S
    time_offsets: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if self.time_offsets is not None:
            t = tuple(self.time_offsets)
            if len(t) != 2 or not all(isinstance(x, int | float) and np.isfinite(x) for x in t):
                raise ValueError(f"'time_offsets' must be two finite numbers [t_s, t_d] (s), got {self.time_offsets!r}")
        for name in POSITIVE_FIELDS:
            value = getattr(self, name)
            if not (isinstance(value, int | float | np.floating | np.integer) and np.isfinite(value) and value > 0):
                raise ValueError(f"'{name}' must be a positive finite number ({POSITIVE_FIELDS[name]}), got {value!r}")
        check_rigid_transform(self.T_sI, "T_sI")

    def to_dict(self) -> dict[str, Any]:
        return {
            "T_sI": np.asarray(self.T_sI, dtype=float).tolist(),
            "accelerometer_noise_density": float(self.accelerometer_noise_density),
            "accelerometer_random_walk": float(self.accelerometer_random_walk),
            "gyroscope_noise_density": float(self.gyroscope_noise_density),
            "gyroscope_random_walk": float(self.gyroscope_random_walk),
            "rate_hz": float(self.rate_hz),
            "gravity": float(self.gravity),
            "acc_range": float(self.acc_range),
            "gyro_range": float(self.gyro_range),
            **({} if self.time_offsets is None else {"time_offsets": [float(x) for x in self.time_offsets]}),
        }

    @staticmethod
    def from_dict(d: dict[str, Any], source: str = "<imu>") -> ImuConfig:
        if not isinstance(d, dict):
            raise ValueError(f"{source}: expected a mapping of IMU fields, got {type(d).__name__}")
        kwargs: dict[str, Any] = {}
        for key, value in d.items():
            if key == "T_sI":
                try:
                    T = np.asarray(value, dtype=float)
                except (TypeError, ValueError):
                    raise ValueError(f"{source}: 'T_sI' must be a 4x4 matrix of numbers") from None
                kwargs[key] = T
            elif key == "time_offsets":
                if not isinstance(value, list | tuple) or len(value) != 2:
                    raise ValueError(f"{source}: 'time_offsets' must be a list [t_s, t_d] of two numbers (s)")
                try:
                    kwargs[key] = (float(value[0]), float(value[1]))
                except (TypeError, ValueError):
                    raise ValueError(f"{source}: 'time_offsets' must be a list [t_s, t_d] of two numbers (s)") from None
            elif key in ImuConfig.__dataclass_fields__:
                try:
                    kwargs[key] = float(value)
                except (TypeError, ValueError):
                    raise ValueError(f"{source}: '{key}' must be a number, got {value!r}") from None
            else:
                raise ValueError(f"{source}: unknown field '{key}'")
        try:
            return ImuConfig(**kwargs)
        except ValueError as err:
            raise ValueError(f"{source}: {err}") from None


def load_imu_config(path: str | Path) -> ImuConfig | None:
    """Read the optional ``imu:`` section of a calibration.yaml (None when absent)."""
    p = Path(path)
    with p.open() as f:
        d = yaml.safe_load(f) or {}
    if "imu" not in d:
        return None
    return ImuConfig.from_dict(d["imu"], f"{p}: imu")


def imu_out_of_range(acc: FloatArray, gyro: FloatArray, acc_range: float, gyro_range: float) -> NDArray[np.bool_]:
    """Per sample: True where any axis is non-finite or beyond the range (m/s^2, rad/s)."""
    a = np.asarray(acc, float)
    g = np.asarray(gyro, float)
    with np.errstate(invalid="ignore"):
        ok = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(g), axis=1)
        ok &= np.all(np.abs(a) <= acc_range, axis=1) & np.all(np.abs(g) <= gyro_range, axis=1)
    return ~ok


#: Lowest IMU rate accepted, Hz: preintegration between keyframes (0.1-0.2 s apart) needs several
#: samples per interval to follow the motion (EuRoC and common drones: 200-400 Hz).
MIN_IMU_RATE_HZ = 50.0
#: The IMU must also be at least this many times faster than the camera.
MIN_IMU_CAMERA_RATIO = 2.0
#: Frames before the first or after the last IMU sample beyond this span (s) point to an IMU
#: clock offset (or an IMU recording started late), not a recorder start-up difference.
MAX_FRAMES_OUTSIDE_IMU_S = 1.0


def measured_rate_hz(t_ns: IntArray) -> float:
    """Rate (Hz) from the median interval of increasing stamps (nan for fewer than 2)."""
    t = np.asarray(t_ns, dtype=np.int64)
    if t.size < 2:
        return float("nan")
    return 1e9 / float(np.median(np.diff(t)))


def check_imu_against_frames(imu_t_ns: IntArray, frame_t_ns: IntArray, where: str) -> None:
    """Refuse, before any work, an IMU stream the smoother cannot use with these camera frames.

    * measured IMU rate below :data:`MIN_IMU_RATE_HZ` or below :data:`MIN_IMU_CAMERA_RATIO` times
      the camera rate (preintegration cannot follow the motion: vision ends up unused);
    * camera frames extending more than :data:`MAX_FRAMES_OUTSIDE_IMU_S` before the first or after
      the last IMU sample (an IMU clock offset; the measured offsets are in the message).

    Raises:
        ValueError: naming ``where`` (file and topic), with the measured numbers.
    """
    t = np.asarray(imu_t_ns, dtype=np.int64)
    f = np.sort(np.asarray(frame_t_ns, dtype=np.int64))
    rate = measured_rate_hz(t)
    cam_rate = measured_rate_hz(f)
    need = max(MIN_IMU_RATE_HZ, MIN_IMU_CAMERA_RATIO * cam_rate if np.isfinite(cam_rate) else 0.0)
    if not rate >= need:
        raise ValueError(
            f"{where}: the IMU rate is {rate:.1f} Hz (median sample interval), too low for preintegration: at least "
            f"{need:.0f} Hz is needed (>= {MIN_IMU_RATE_HZ:.0f} Hz and >= {MIN_IMU_CAMERA_RATIO:g}x the camera "
            f"rate {cam_rate:.1f} Hz); check the IMU topic and the driver's rate"
        )
    if f.size == 0:
        return
    before = (int(t[0]) - int(f[0])) / 1e9
    after = (int(f[-1]) - int(t[-1])) / 1e9
    if before > MAX_FRAMES_OUTSIDE_IMU_S or after > MAX_FRAMES_OUTSIDE_IMU_S:
        raise ValueError(
            f"{where}: the camera frames start {before:.2f} s before the first IMU sample and end {after:.2f} s "
            f"after the last (limit {MAX_FRAMES_OUTSIDE_IMU_S:g} s): the IMU clock is probably offset from the "
            "camera clock (or the IMU was not recorded over the whole bag); check the stamps of both topics"
        )
