"""Settings, initial state and result of the keyframe smoother (plain dataclasses, loadable from YAML).

Frames: ``T_WI`` maps points from the body/IMU frame I into the world W (gravity along -z);
velocities ``v_W`` in W (m/s); accelerometer biases in m/s^2, gyroscope biases in rad/s; joint
angles in rad; times in ns (:data:`NS` per second). See ``docs/architecture.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
NS = 1_000_000_000
MODES = ("dcc", "scc", "mono")
INITIALIZATIONS = ("auto", "standstill", "motion")
LANDMARKS = ("explicit", "smart")
PERSISTENT_LANDMARKS = ("auto", "all", "gimbal", "none")
#: Window (s) when landmarks persist (``persistent_landmarks`` all or gimbal) and ``lag`` is not given.
PERSISTENT_LAG_S = 1.5
#: Window (s) with no persistent landmark and ``lag`` not given: as accurate as every landmark
#: persistent with 1.5 s on synchronized cameras, at 0.64x the wall time (README, VIO throughput).
NON_PERSISTENT_LAG_S = 2.5
#: Largest static <-> gimbal stamp gap (ms) of cameras that count as synchronized (:meth:`VioOptions.resolved`).
SYNCHRONIZED_GAP_MS = 1.0
#: Largest |time offset| accepted as a start value, s.
MAX_TIME_OFFSET_S = 0.5


@dataclass(frozen=True)
class VioOptions:
    """Smoother settings.

    ``sigma`` is the standard deviation of a normalized image coordinate (pixel sigma / focal
    length); ``robust_k`` the Huber threshold in sigmas; ``theta_random_walk`` the joint-angle
    random walk in rad/sqrt(s); ``theta_fixed`` the locked joint angles of ``scc`` mode;
    ``theta_initial`` the joint-angle guess of a ``dcc`` run initialized from standstill;
    ``min_gimbal_landmarks`` and ``theta_measurement_inflation``: when and how strongly a direct
    joint-angle measurement is used (:meth:`~dcc_fg.vio.backend.smoother.VioSmoother.add_frame`).

    Divergence and recovery (:mod:`~dcc_fg.vio.backend.divergence`): ``max_speed`` (m/s) is the
    platform's top speed; ``max_velocity_sigma`` (m/s) the largest velocity 1-sigma of a
    constrained estimate; an interval between IMU samples longer than ``imu_gap_periods`` median
    sample periods is an IMU gap. After a gap or a divergence the smoother starts a new trajectory
    segment anchored with ``restart_rotation_sigma`` (rad), ``restart_velocity_sigma`` (m/s) and
    ``restart_theta_sigma`` (rad) priors.

    Camera timing (:mod:`~dcc_fg.vio.backend.exposure`): ``time_offsets`` = ``(t_s, t_d)`` (s; None:
    zeros, or the calibration's for ``dcc-fg vio``) are the start values of the static and the gimbal
    camera's offsets from the IMU clock, convention ``t_imu = t_cam_stamp + t_offset`` (OpenVINS
    ``calib_camimu_dt``, Kalibr ``timeshift_cam_imu``);
    ``estimate_time_offsets`` makes them a state of the smoother with a prior of
    ``time_offset_prior_sigma`` (s) around the start values (False: held at the start values).
    ``time_offset_freeze_sigma`` (s): once every estimated offset's 1-sigma is below it, the offsets
    are held at their estimate, which saves the auxiliary static pose (None, the default: estimated to
    the end; holding them at 0.25 ms cost 20 % translation accuracy over 12 simulated flights, the
    offsets' remaining error acting as a bias, ``benchmarks/bench_time_offsets.py --freeze``).
    ``stamp_jitter`` = 1-sigma (s) of each
    camera's header stamps around its exposure times (None: measured from the stamps by
    :func:`~dcc_fg.vio.backend.runner.run_vio` and ``dcc-fg vio``).

    Start (:mod:`~dcc_fg.vio.backend.motion_init`, without a given initial state): ``initialization``
    ``standstill`` (gravity from the first ``standstill_window`` s of IMU, the body must be still),
    ``motion`` (visual-inertial alignment over the first ``motion_init_window`` s, retried up to
    ``motion_init_max_window`` s) or ``auto`` (standstill when the IMU and the static tracks are at rest
    over the first ``standstill_window`` s, else motion).

    ``joint_sigmas`` (``dcc``): every keyframe's joint-angle 1-sigma (rad) from the window's marginal
    covariance of ``t(k)`` at the last update before the keyframe leaves the window (the estimate the
    result keeps is from the same update), in ``VioResult.theta_sigma`` and ``joint_angles_sigma.csv``;
    one marginal covariance per keyframe costs about as much as the update itself (off by default).

    ``landmarks``: ``explicit`` (a Point3 variable per landmark with Huber-robust reprojection factors) or
    ``smart`` (structureless, experimental: one GTSAM smart projection factor per landmark, the point
    eliminated inside it, :mod:`~dcc_fg.vio.backend.structureless`). A smart factor has isotropic noise and
    no robust loss, so observations are gated at ``smart_observation_gate`` sigmas instead of
    ``observation_gate`` (on the 60 s rendered flight a gate of 8 sigmas let outliers in and the run
    diverged), and a landmark whose triangulation leaves an observation beyond ``smart_outlier_sigmas``
    sigmas contributes nothing at that linearization (gtsam's dynamic outlier rejection; None: never).
    Without it 2 of 3 runs of that flight drifted or diverged; at 4 sigmas a 20 s tracks-level flight had
    3 failed updates. Measured on that flight (``benchmarks/bench_vio.py --smart``, which runs it with a
    2.5 s ``lag``: its factors restart when their oldest keyframe leaves the window): 0.69x the main
    process's CPU time and 0.90x the translation RMSE of ``explicit`` at the former defaults (every landmark
    persistent, 1.5 s lag), but 1.4x the first joint's
    RMSE (with a 1.5 s lag: 0.56x the CPU, 1.2-1.45x the translation RMSE).
    ``persistent_landmarks`` (``explicit`` landmarks): which landmarks stay in the window while they are
    tracked: ``all``; ``gimbal``, those a camera on a gimbal saw; ``none``; ``auto`` (default), ``none``
    when the cameras are synchronized, else ``all`` (:meth:`resolved`, which also picks the window
    ``lag`` when it is None: 2.5 s with ``none``, 1.5 s otherwise). The others leave with the oldest
    keyframe that saw them when they were made (:meth:`~.landmarks.LandmarkMap.stamp_ns`): their
    observations become a prior on the keyframe states and a track that goes on is triangulated afresh.
    A persistent landmark the leaving keyframe saw stays in that keyframe's marginal, so every one of them
    is tied into one dense prior: the main cost of the smoother (the README's VIO throughput section has
    the measured speed and accuracy of each choice: ``none`` with a 2.5 s ``lag`` matches ``all``'s accuracy
    at 0.64-0.69x the wall time on synchronized cameras, but not on a gimbal camera with its own clock,
    :func:`~dcc_fg.vio.pipeline.warn_persistence_on_unsynchronized`).
    ``smart`` needs every observation on an identity-mount camera pose: the incremental smoother,
    estimated time offsets that stay estimated (``time_offset_freeze_sigma`` None),
    ``gimbal_factor='camera_pose'`` and no further cameras.
    """

    mode: str = "dcc"
    keyframe_every: int = 2
    lag: float | None = None
    sigma: float = 1.0 / 460.0
    robust_k: float = 2.0
    theta_random_walk: float = 1.0
    theta_prior_sigma: float = 0.1
    theta_fixed: tuple[float, ...] | None = None
    theta_initial: tuple[float, ...] | None = None
    min_track_keyframes: int = 3
    min_parallax_deg: float = 1.0
    max_depth: float = 60.0
    triangulation_gate: float = 4.0
    observation_gate: float = 30.0
    max_new_landmarks: int = 150
    persistent_landmarks: str = "auto"
    standstill_window: float = 0.5
    prior_position_sigma: float = 1e-3
    prior_rotation_sigma: float = 1e-3
    prior_velocity_sigma: float = 0.05
    prior_acc_bias_sigma: float = 0.1
    prior_gyro_bias_sigma: float = 0.01
    smoother: str = "incremental"
    gimbal_factor: str = "camera_pose"
    landmark_prior_sigma: float = 100.0
    zupt_threshold: float = 0.5 / 460.0
    zupt_min_tracks: int = 8
    zupt_velocity_sigma: float = 0.01
    zupt_pose_sigma: float = 1e-3
    recovery_position_sigma: float = 0.01
    recovery_rotation_sigma: float = 0.01
    camera_pose_sigma: float = 1e-4
    relinearize_threshold: float = 0.01
    extra_iterations: int = 0
    min_gimbal_landmarks: int = 10
    theta_measurement_inflation: float = 3.0
    max_speed: float = 30.0
    max_velocity_sigma: float = 2.0
    imu_gap_periods: float = 5.0
    restart_rotation_sigma: float = 0.05
    restart_velocity_sigma: float = 1.0
    restart_theta_sigma: float = 0.1
    time_offsets: tuple[float, float] | None = None
    estimate_time_offsets: bool = True
    time_offset_prior_sigma: float = 0.01
    stamp_jitter: tuple[float, float] | None = None
    time_offset_freeze_sigma: float | None = None
    joint_sigmas: bool = False
    initialization: str = "auto"
    motion_init_window: float = 1.0
    motion_init_max_window: float = 3.0
    landmarks: str = "explicit"
    smart_observation_gate: float = 5.0
    smart_outlier_sigmas: float | None = 6.0

    def __post_init__(self) -> None:
        if self.initialization not in INITIALIZATIONS:
            raise ValueError(f"initialization '{self.initialization}' is not one of {', '.join(INITIALIZATIONS)}")
        if self.mode not in MODES:
            raise ValueError(f"mode '{self.mode}' is not one of {', '.join(MODES)}")
        if self.smoother not in ("incremental", "batch"):
            raise ValueError(f"smoother '{self.smoother}' is not one of incremental, batch")
        if self.landmarks not in LANDMARKS:
            raise ValueError(f"landmarks '{self.landmarks}' is not one of {', '.join(LANDMARKS)}")
        if self.persistent_landmarks not in PERSISTENT_LANDMARKS:
            raise ValueError(
                f"persistent_landmarks '{self.persistent_landmarks}' is not one of {', '.join(PERSISTENT_LANDMARKS)}"
            )
        if self.landmarks == "smart" and (
            self.smoother != "incremental"
            or not self.estimate_time_offsets
            or self.time_offset_freeze_sigma is not None
            or self.gimbal_factor != "camera_pose"
        ):
            raise ValueError(
                "landmarks 'smart' needs smoother 'incremental', estimate_time_offsets, no "
                "time_offset_freeze_sigma and gimbal_factor 'camera_pose' (every observation on a camera pose); "
                "use landmarks 'explicit' with these settings"
            )
        if self.keyframe_every < 1 or (self.lag is not None and self.lag <= 0) or self.sigma <= 0:
            raise ValueError("keyframe_every >= 1, lag > 0 and sigma > 0 are required")
        for name in (
            "max_speed",
            "max_velocity_sigma",
            "imu_gap_periods",
            "restart_rotation_sigma",
            "restart_velocity_sigma",
            "restart_theta_sigma",
            "time_offset_prior_sigma",
            "motion_init_window",
            "motion_init_max_window",
            "smart_observation_gate",
        ):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"smoother option '{name}' must be a positive number, got {value!r}")
        if self.smart_outlier_sigmas is not None and not self.smart_outlier_sigmas > 0:
            raise ValueError(f"smart_outlier_sigmas must be > 0 or None, got {self.smart_outlier_sigmas!r}")
        if self.time_offset_freeze_sigma is not None and not self.time_offset_freeze_sigma > 0:
            raise ValueError(f"time_offset_freeze_sigma must be > 0 s or None, got {self.time_offset_freeze_sigma!r}")
        if self.stamp_jitter is not None and (
            len(self.stamp_jitter) != 2 or not all(np.isfinite(x) and x >= 0 for x in self.stamp_jitter)
        ):
            raise ValueError(f"stamp_jitter must be two numbers >= 0 (s), got {self.stamp_jitter!r}")
        t = self.offsets
        if len(t) != 2 or not all(np.isfinite(x) for x in t):
            raise ValueError(f"time_offsets must be two finite numbers (t_s, t_d in s), got {self.time_offsets!r}")
        if max(abs(x) for x in t) > MAX_TIME_OFFSET_S:
            raise ValueError(
                f"time_offsets {self.time_offsets!r} s: larger than {MAX_TIME_OFFSET_S} s in magnitude; an offset "
                "that large is a clock problem (different time bases), not a camera delay: fix the stamps"
            )

    @property
    def is_resolved(self) -> bool:
        """Whether ``persistent_landmarks`` and ``lag`` are concrete (:meth:`resolved`)."""
        return self.persistent_landmarks != "auto" and self.lag is not None

    def resolved(self, synchronized: bool) -> VioOptions:
        """These options with ``persistent_landmarks`` ``auto`` and ``lag`` None made concrete.

        ``auto``: ``none`` when ``synchronized`` (the run's cameras expose together: every gimbal image
        has a static partner on the same stamp, or there is no gimbal camera, and no further camera and
        explicit landmarks), else ``all``. ``lag`` None: :data:`NON_PERSISTENT_LAG_S` with ``none``,
        :data:`PERSISTENT_LAG_S` otherwise. Measured (README, VIO throughput): over eight synchronized
        60 s flights ``none`` with 2.5 s is as accurate as ``all`` with 1.5 s at 0.64x the wall time;
        on the unsynchronized benchmark flight (gimbal camera at 30 Hz on its own clock) it had 1.19x
        the translation error of ``all``, and with further cameras it is not measured."""
        persist = self.persistent_landmarks
        if persist == "auto":
            persist = "none" if synchronized and self.landmarks == "explicit" else "all"
        lag = self.lag
        if lag is None:
            lag = NON_PERSISTENT_LAG_S if persist == "none" else PERSISTENT_LAG_S
        return replace(self, persistent_landmarks=persist, lag=lag)

    @property
    def window_s(self) -> float:
        """The smoother window (s) of resolved options (:meth:`resolved`)."""
        if self.lag is None:
            raise ValueError("VioOptions.lag is not resolved: call VioOptions.resolved() first")
        return float(self.lag)

    @property
    def gate(self) -> float:
        """Largest predicted reprojection error (sigmas) of an observation the smoother uses."""
        return self.observation_gate if self.landmarks == "explicit" else self.smart_observation_gate

    @property
    def offsets(self) -> tuple[float, float]:
        """The start values ``(t_s, t_d)`` of the time offsets, s (zeros when not given)."""
        if self.time_offsets is None:
            return (0.0, 0.0)
        return (float(self.time_offsets[0]), float(self.time_offsets[1]))


@dataclass(frozen=True)
class InitialState:
    """State at time ``t_ns``: ``T_WI`` (4x4), ``v_W`` (m/s), biases, joint angles (rad)."""

    t_ns: int
    T_WI: FloatArray
    v_W: FloatArray
    acc_bias: FloatArray = field(default_factory=lambda: np.zeros(3))
    gyro_bias: FloatArray = field(default_factory=lambda: np.zeros(3))
    theta: FloatArray = field(default_factory=lambda: np.zeros(0))


@dataclass
class VioResult:
    """Per-keyframe estimates (the last estimate of each keyframe before it left the window)."""

    timestamps_ns: IntArray
    T_WI: FloatArray
    v_W: FloatArray
    acc_bias: FloatArray
    gyro_bias: FloatArray
    theta: FloatArray
    mode: str
    stats: dict[str, Any]
    #: (N, L) 1-sigma of the joint angles (rad) from the window's marginal covariance just before each
    #: keyframe left it (``joint_sigmas``; NaN where a keyframe left without one, e.g. at a restart), or None
    theta_sigma: FloatArray | None = None
    #: further gimbal chains of an N-camera run: chain name -> (N, L) joint angles (rad) per keyframe
    chain_theta: dict[str, FloatArray] = field(default_factory=dict)
