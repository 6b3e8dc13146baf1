"""Keyframe fixed-lag smoother of the gimbal-aware VIO (paper section IV-C).

Input: :class:`~dcc_fg.data.vio.TrackFrame` lists (undistorted normalized coordinates, one landmark
id space across both cameras) and :class:`~dcc_fg.data.vio.ImuSamples`; no images.

State per keyframe k (gtsam keys): ``x(k)`` Pose3 ``T_WI``, ``v(k)`` velocity in W (m/s), ``b(k)``
``imuBias.ConstantBias`` (accelerometer m/s^2, gyroscope rad/s) and, in ``dcc`` mode, ``t(k)`` the
joint angles (Vector L, rad). Landmarks ``l(n)`` are Point3 in W. W has gravity along -z.

Factors:

* ``CombinedImuFactor`` between consecutive keyframes (``PreintegratedCombinedMeasurements`` with the
  Kalibr noise densities of :class:`~dcc_fg.data.vio.ImuConfig`, bias random walk included);
* static camera: gtsam's ``GenericProjectionFactorCal3_S2`` on normalized coordinates with
  ``body_P_sensor = T_Is`` and a Huber loss;
* gimbal camera: the paper's eq. 14 (:func:`factors.vio.gimbal_reprojection_factor`, keys pose,
  landmark, joint angles; Huber loss) in ``dcc`` mode, which estimates the joint angles; ``scc``
  holds them at the given fixed angles (gimbal locked: a projection factor with the fixed
  extrinsic ``T_dI``), ``mono`` ignores the gimbal camera;
* joint-angle random walk ``theta_k - theta_{k-1} ~ N(0, q^2 dt)`` between keyframes (``dcc``);
* priors on the first keyframe (pose, velocity, bias, joint angles).

Landmarks are triangulated (linear DLT over all buffered observations, both cameras) once a track
has ``min_track_keyframes`` keyframes, enough parallax, positive depths and small reprojection
errors; the smoother (gtsam ``IncrementalFixedLagSmoother`` or ``BatchFixedLagSmoother``) then
marginalizes every variable whose last keyframe left the window of ``lag`` seconds.

Gimbal camera outliers use the two-stage scheme the paper proposes as future work: the joint
angles of a new keyframe are first fitted (Huber, no rejection) to the gimbal observations of known
landmarks with the IMU-predicted pose, then observations are gated with the updated extrinsics.

Initialization: from standstill (gravity from the mean accelerometer reading, yaw 0, gyroscope bias
from the mean rate) or from a given :class:`InitialState` (e.g. ground truth in tests).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gtsam
import numpy as np
from numpy.typing import NDArray

from dcc_fg.model import GimbalCalibration
from dcc_fg.data.vio import ImuConfig, ImuSamples, TrackFrame
from factors import chain
from factors.calibration import RobustLoss
from factors.vio import (
    ChainCache,
    ProjectionFactory,
    gimbal_camera_pose_factor,
    gimbal_reprojection_factor,
    gimbal_residuals,
    joint_random_walk_factor,
)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
NS = 1_000_000_000
MODES = ("dcc", "scc", "mono")
log = logging.getLogger(__name__)


def X(k: int) -> int:
    return gtsam.symbol("x", k)


def V(k: int) -> int:
    return gtsam.symbol("v", k)


def B(k: int) -> int:
    return gtsam.symbol("b", k)


def TH(k: int) -> int:
    return gtsam.symbol("t", k)


def LM(n: int) -> int:
    return gtsam.symbol("l", n)


def CAM(k: int) -> int:
    return gtsam.symbol("c", k)


@dataclass(frozen=True)
class VioOptions:
    """Smoother settings.

    ``sigma`` is the standard deviation of a normalized image coordinate (pixel sigma / focal
    length); ``robust_k`` the Huber threshold in sigmas; ``theta_random_walk`` the joint-angle
    random walk in rad/sqrt(s); ``theta_fixed`` the locked joint angles of ``scc`` mode;
    ``theta_initial`` the joint-angle guess of a ``dcc`` run initialized from standstill;
    ``min_gimbal_landmarks`` and ``theta_measurement_inflation``: when and how strongly a direct
    joint-angle measurement is used (:meth:`VioSmoother.add_frame`).
    """

    mode: str = "dcc"
    keyframe_every: int = 2
    lag: float = 1.5
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

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode '{self.mode}' is not one of {', '.join(MODES)}")
        if self.smoother not in ("incremental", "batch"):
            raise ValueError(f"smoother '{self.smoother}' is not one of incremental, batch")
        if self.keyframe_every < 1 or self.lag <= 0 or self.sigma <= 0:
            raise ValueError("keyframe_every >= 1, lag > 0 and sigma > 0 are required")


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


def validate_imu(imu: ImuSamples, source: str = "imu") -> None:
    """Raise ValueError for IMU data the smoother cannot use (naming the field at fault)."""
    n = len(imu)
    if imu.acc.shape != (n, 3) or imu.gyro.shape != (n, 3):
        raise ValueError(f"{source}: acc and gyro must be (N, 3) arrays matching t_ns ({n} samples)")
    if n < 2:
        raise ValueError(f"{source}: at least two IMU samples are needed, got {n}")
    dt = np.diff(imu.t_ns)
    if np.any(dt <= 0):
        k = int(np.argmax(dt <= 0))
        raise ValueError(
            f"{source}: t_ns not strictly increasing at sample {k + 1} ({imu.t_ns[k]} -> {imu.t_ns[k + 1]})"
        )
    for name, arr in (("acc", imu.acc), ("gyro", imu.gyro)):
        bad = ~np.all(np.isfinite(arr), axis=1)
        if np.any(bad):
            k = int(np.argmax(bad))
            raise ValueError(f"{source}: {name} is not finite at sample {k} (t_ns {imu.t_ns[k]})")


def validate_frames(frames: list[TrackFrame], source: str = "tracks") -> None:
    """Frames must be time-ordered with matching id/coordinate counts and finite coordinates."""
    if not frames:
        raise ValueError(f"{source}: no camera frames")
    last = None
    for i, f in enumerate(frames):
        if last is not None and f.timestamp_ns <= last:
            raise ValueError(f"{source}: frame {i} timestamp {f.timestamp_ns} is not after {last}")
        last = f.timestamp_ns
        for cam, ids, xy in (("static", f.static_ids, f.static_xy), ("dynamic", f.dynamic_ids, f.dynamic_xy)):
            if xy.shape != (ids.shape[0], 2):
                raise ValueError(f"{source}: frame {i} {cam}: {ids.shape[0]} ids but xy has shape {xy.shape}")
            if not np.all(np.isfinite(xy)):
                raise ValueError(f"{source}: frame {i} {cam}: non-finite coordinates")


def preintegration_params(cfg: ImuConfig) -> gtsam.PreintegrationCombinedParams:
    """Combined preintegration parameters from Kalibr continuous-time noise densities, gravity -z."""
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(cfg.gravity)
    I3 = np.eye(3)
    p.setAccelerometerCovariance(I3 * cfg.accelerometer_noise_density**2)
    p.setGyroscopeCovariance(I3 * cfg.gyroscope_noise_density**2)
    p.setIntegrationCovariance(I3 * 1e-8)
    p.setBiasAccCovariance(I3 * cfg.accelerometer_random_walk**2)
    p.setBiasOmegaCovariance(I3 * cfg.gyroscope_random_walk**2)
    return p


def integrate_imu(pim: gtsam.PreintegratedCombinedMeasurements, imu: ImuSamples, t0_ns: int, t1_ns: int) -> None:
    """Integrate the IMU over [t0, t1]: each sample interval contributes its midpoint average,
    clipped to the interval (samples before t0 / after t1 are held)."""
    t = imu.t_ns
    i0 = max(int(np.searchsorted(t, t0_ns, side="right")) - 1, 0)
    i1 = min(int(np.searchsorted(t, t1_ns, side="left")), len(t) - 1)
    for i in range(i0, i1):
        a = max(t[i], t0_ns)
        b = min(t[i + 1], t1_ns)
        if b <= a:
            continue
        acc = 0.5 * (imu.acc[i] + imu.acc[i + 1])
        gyro = 0.5 * (imu.gyro[i] + imu.gyro[i + 1])
        pim.integrateMeasurement(acc, gyro, (b - a) / NS)
    if t1_ns > t[-1]:  # hold the last sample
        pim.integrateMeasurement(imu.acc[-1], imu.gyro[-1], (t1_ns - max(t[-1], t0_ns)) / NS)


def standstill_state(imu: ImuSamples, t0_ns: int, window: float, gravity: float, n_joints: int) -> InitialState:
    """Gravity-aligned initial state from IMU samples in [t0, t0 + window] (body assumed at rest).

    Roll and pitch rotate the mean specific force onto +z of W; yaw is 0; the gyroscope bias is
    the mean rate; raises ValueError if the body is clearly moving.
    """
    sel = (imu.t_ns >= t0_ns) & (imu.t_ns <= t0_ns + int(window * NS))
    if sel.sum() < 5:
        raise ValueError(f"standstill initialization needs IMU samples in the first {window} s after the first frame")
    f = imu.acc[sel].mean(axis=0)
    spread = np.linalg.norm(imu.acc[sel] - f, axis=1).max()
    if abs(np.linalg.norm(f) - gravity) > 0.5 or spread > 3.0:
        raise ValueError(
            f"standstill initialization: the IMU is not at rest at the start (|mean acc| = {np.linalg.norm(f):.2f} "
            f"m/s^2, spread {spread:.2f}); pass an initial state instead"
        )
    u = f / np.linalg.norm(f)
    ez = np.array([0.0, 0.0, 1.0])
    axis = np.cross(u, ez)
    s, c = np.linalg.norm(axis), float(np.dot(u, ez))
    rotvec = np.zeros(3) if s < 1e-12 else axis / s * np.arctan2(s, c)
    T = np.eye(4)
    T[:3, :3] = gtsam.Rot3.Expmap(rotvec).matrix()
    return InitialState(t0_ns, T, np.zeros(3), np.zeros(3), imu.gyro[sel].mean(axis=0), np.zeros(n_joints))


def triangulate(T_Wc: FloatArray, xy: FloatArray) -> FloatArray:
    """Linear (DLT) triangulation of one point from camera poses T_Wc (M, 4, 4) and normalized xy (M, 2)."""
    R_cW = np.transpose(T_Wc[:, :3, :3], (0, 2, 1))
    P = np.concatenate([R_cW, -R_cW @ T_Wc[:, :3, 3:4]], axis=2)  # (M, 3, 4) = [R_cW | t_cW]
    A = np.concatenate([xy[:, :1] * P[:, 2] - P[:, 0], xy[:, 1:2] * P[:, 2] - P[:, 1]], axis=0)
    _, _, vt = np.linalg.svd(A)
    h = vt[-1]
    if abs(h[3]) < 1e-12:
        return np.full(3, np.nan)
    return h[:3] / h[3]


@dataclass
class _Track:
    """Buffered observations of a not-yet-triangulated landmark: (keyframe, camera 0/1, xy)."""

    obs: list[tuple[int, int, FloatArray]] = field(default_factory=list)


class VioSmoother:
    """Incremental keyframe smoother; feed frames in time order with :meth:`add_frame`."""

    def __init__(
        self,
        imu: ImuSamples,
        imu_config: ImuConfig,
        calibration: GimbalCalibration | None,
        options: VioOptions,
    ) -> None:
        validate_imu(imu)
        self.imu = imu
        self.cfg = imu_config
        self.opt = options
        self.cal = calibration
        self.L = calibration.n_joints if calibration is not None else 0
        if options.mode != "mono" and calibration is None:
            raise ValueError(f"mode '{options.mode}' needs the gimbal calibration")
        if options.mode == "scc":
            if options.theta_fixed is None or len(options.theta_fixed) != self.L:
                raise ValueError(f"scc mode needs theta_fixed with {self.L} joint angles (the locked gimbal)")
        self.T_sI = np.asarray(imu_config.T_sI, float)
        self.params = preintegration_params(imu_config)
        self.robust = RobustLoss("huber", options.robust_k)
        self.chain_cache = ChainCache(calibration.kin, self.L) if calibration is not None else None
        self.project_static = ProjectionFactory(options.sigma, self.T_sI, options.robust_k)
        self.project_camera = ProjectionFactory(options.sigma, np.eye(4), options.robust_k)
        self.T_dI_fixed = np.eye(4)
        if options.mode == "scc":
            assert calibration is not None and options.theta_fixed is not None
            self.T_dI_fixed = calibration.T_ds(np.asarray(options.theta_fixed, float)) @ self.T_sI
        self.project_locked = ProjectionFactory(options.sigma, self.T_dI_fixed, options.robust_k)
        self.smoother = self._new_smoother()
        self.k = -1
        self.kf_times: dict[int, int] = {}
        self.estimates: dict[int, tuple[int, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]] = {}
        self.state: gtsam.NavState | None = None
        self.bias = gtsam.imuBias.ConstantBias()
        self.theta = np.zeros(self.L)
        self.tracks: dict[int, _Track] = {}
        self.active: dict[int, int] = {}  # track id -> landmark index
        self.landmark_last: dict[int, int] = {}  # landmark index -> last keyframe time (ns)
        self.landmark_pos: dict[int, FloatArray] = {}
        self.n_landmarks = 0
        self.frame_count = 0
        self.prev_static: dict[int, FloatArray] = {}
        self.stats: dict[str, Any] = {
            "keyframes": 0,
            "landmarks": 0,
            "static_obs": 0,
            "dynamic_obs": 0,
            "gated": 0,
            "failed_updates": 0,
        }

    # ------------------------------------------------------------------ helpers
    def _new_smoother(self) -> Any:
        o = self.opt
        if o.smoother == "incremental":
            p = gtsam.ISAM2Params()
            p.setRelinearizeThreshold(o.relinearize_threshold)
            p.relinearizeSkip = 1
            return gtsam.IncrementalFixedLagSmoother(o.lag, p)
        return gtsam.BatchFixedLagSmoother(o.lag)

    def _theta_at(self, k: int, values: gtsam.Values | None = None) -> FloatArray:
        if self.opt.mode == "scc":
            return np.asarray(self.opt.theta_fixed, float)
        if self.opt.mode == "mono":
            return np.zeros(self.L)
        if values is not None and values.exists(TH(k)):
            return values.atVector(TH(k))
        return self.estimates[k][5] if k in self.estimates else self.theta

    def _T_WI(self, k: int) -> FloatArray:
        return self.estimates[k][1]

    def _T_Wc(self, k: int, cam: int, theta: FloatArray | None = None) -> FloatArray:
        T_WI = self._T_WI(k)
        if cam == 0:
            return T_WI @ chain.inv_se3(self.T_sI)
        assert self.cal is not None
        th = self._theta_at(k) if theta is None else theta
        return T_WI @ chain.inv_se3(self.cal.T_ds(th) @ self.T_sI)

    def _in_window(self, t_ns: int, now_ns: int) -> bool:
        """True if a keyframe at t_ns survives the next update (not marginalized)."""
        dt_kf = now_ns - self.kf_times[self.k - 1] if self.k >= 1 else 0
        return t_ns >= now_ns - int(self.opt.lag * NS) + dt_kf

    # ------------------------------------------------------------------ main loop
    def initialize(self, frame: TrackFrame, initial: InitialState | None) -> None:
        if initial is None:
            initial = standstill_state(
                self.imu, frame.timestamp_ns, self.opt.standstill_window, self.cfg.gravity, self.L
            )
            if self.opt.mode == "dcc":
                if self.opt.theta_initial is None or len(self.opt.theta_initial) != self.L:
                    raise ValueError(f"dcc mode from standstill needs theta_initial ({self.L} joint angles, rad)")
                initial = InitialState(
                    initial.t_ns,
                    initial.T_WI,
                    initial.v_W,
                    initial.acc_bias,
                    initial.gyro_bias,
                    np.asarray(self.opt.theta_initial, float),
                )
        theta0 = np.asarray(initial.theta, float).reshape(-1)
        if self.opt.mode == "dcc" and theta0.shape[0] != self.L:
            raise ValueError(f"initial theta must have {self.L} joint angles")
        if self.opt.mode == "scc":
            theta0 = np.asarray(self.opt.theta_fixed, float)
        if initial.t_ns != frame.timestamp_ns:
            raise ValueError("the initial state must be at the time of the first frame")
        self.k = 0
        t = frame.timestamp_ns
        self.kf_times[0] = t
        pose = gtsam.Pose3(np.asarray(initial.T_WI, float))
        v = np.asarray(initial.v_W, float)
        self.bias = gtsam.imuBias.ConstantBias(
            np.asarray(initial.acc_bias, float), np.asarray(initial.gyro_bias, float)
        )
        self.theta = theta0 if self.L else np.zeros(0)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        o = self.opt
        graph.add(
            gtsam.PriorFactorPose3(
                X(0),
                pose,
                gtsam.noiseModel.Diagonal.Sigmas(
                    np.r_[np.full(3, o.prior_rotation_sigma), np.full(3, o.prior_position_sigma)]
                ),
            )
        )
        graph.add(gtsam.PriorFactorVector(V(0), v, gtsam.noiseModel.Isotropic.Sigma(3, o.prior_velocity_sigma)))
        graph.add(
            gtsam.PriorFactorConstantBias(
                B(0),
                self.bias,
                gtsam.noiseModel.Diagonal.Sigmas(
                    np.r_[np.full(3, o.prior_acc_bias_sigma), np.full(3, o.prior_gyro_bias_sigma)]
                ),
            )
        )
        values.insert(X(0), pose)
        values.insert(V(0), v)
        values.insert(B(0), self.bias)
        stamps = {X(0): t, V(0): t, B(0): t}
        if o.mode == "dcc":
            graph.add(
                gtsam.PriorFactorVector(
                    TH(0), self.theta, gtsam.noiseModel.Isotropic.Sigma(self.L, o.theta_prior_sigma)
                )
            )
            values.insert(TH(0), self.theta)
            stamps[TH(0)] = t
            self._add_camera_pose(0, pose, self.theta, graph, values, stamps)
        self.kf_times[0] = t
        self.state = gtsam.NavState(pose, v)
        self.estimates[0] = (t, pose.matrix(), v, self.bias.accelerometer(), self.bias.gyroscope(), self.theta.copy())
        self._observe(0, frame, graph, values, stamps)
        self.prev_static = dict(zip(frame.static_ids.tolist(), frame.static_xy, strict=True))
        self._update(graph, values, stamps)

    def next_is_keyframe(self) -> bool:
        """True if the next :meth:`add_frame` call will make a keyframe."""
        return self.frame_count % self.opt.keyframe_every == 0

    def gimbal_landmarks(self, frame: TrackFrame) -> int:
        """How many of the frame's gimbal-camera tracks are mapped landmarks."""
        return sum(int(tid) in self.active for tid in frame.dynamic_ids)

    def add_frame(self, frame: TrackFrame, theta_measurement: tuple[FloatArray, FloatArray] | None = None) -> bool:
        """Process one frame; returns True if it became a keyframe.

        ``theta_measurement`` = (theta (L,) rad, covariance (L, L) rad^2): a direct measurement of
        the joint angles, e.g. from the frame's static <-> gimbal epipolar geometry
        (:func:`dcc_fg.vio.joint_init.fit_joint_angles`). It is used (``dcc`` mode) only while the
        gimbal camera sees fewer than ``min_gimbal_landmarks`` mapped landmarks, i.e. when the
        reprojection factors cannot determine the angles yet (start-up at standstill, after a gap),
        as the starting value and a prior with the covariance inflated by ``theta_measurement_inflation``.
        """
        self.frame_count += 1
        if (self.frame_count - 1) % self.opt.keyframe_every:
            return False
        k_prev, k = self.k, self.k + 1
        t_prev, t = self.kf_times[k_prev], frame.timestamp_ns
        if t - t_prev > 2 * NS:
            log.warning(
                "gap of %.2f s between keyframes at t_ns %d: IMU-only propagation across it", (t - t_prev) / NS, t
            )
        pim = gtsam.PreintegratedCombinedMeasurements(self.params, self.bias)
        integrate_imu(pim, self.imu, t_prev, t)
        assert self.state is not None
        pred = pim.predict(self.state, self.bias)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        graph.add(gtsam.CombinedImuFactor(X(k_prev), V(k_prev), X(k), V(k), B(k_prev), B(k), pim))
        values.insert(X(k), pred.pose())
        values.insert(V(k), pred.velocity())
        values.insert(B(k), self.bias)
        stamps = {X(k): t, V(k): t, B(k): t}
        self.k = k
        self.kf_times[k] = t
        self.estimates[k] = (
            t,
            pred.pose().matrix(),
            pred.velocity(),
            self.bias.accelerometer(),
            self.bias.gyroscope(),
            self.theta.copy(),
        )
        if self.opt.mode == "dcc":
            dt = (t - t_prev) / NS
            theta0 = self._fit_theta(frame, pred.pose().matrix(), self.theta, self.opt.theta_random_walk * np.sqrt(dt))
            if theta_measurement is not None and self.gimbal_landmarks(frame) < self.opt.min_gimbal_landmarks:
                th_m, cov_m = (np.asarray(x, float) for x in theta_measurement)
                if th_m.shape == (self.L,) and cov_m.shape == (self.L, self.L) and np.all(np.isfinite(cov_m)):
                    theta0 = th_m.copy()
                    cov = cov_m * self.opt.theta_measurement_inflation**2 + np.eye(self.L) * 1e-10
                    graph.add(gtsam.PriorFactorVector(TH(k), th_m, gtsam.noiseModel.Gaussian.Covariance(cov)))
                    self.stats["theta_measurements"] = self.stats.get("theta_measurements", 0) + 1
            values.insert(TH(k), theta0)
            stamps[TH(k)] = t
            graph.add(
                joint_random_walk_factor(TH(k_prev), TH(k), self.L, max(self.opt.theta_random_walk * np.sqrt(dt), 1e-6))
            )
            self.estimates[k] = self.estimates[k][:5] + (theta0,)
            self._add_camera_pose(k, pred.pose(), theta0, graph, values, stamps)
        self._zero_velocity(k_prev, k, frame, graph)
        self._observe(k, frame, graph, values, stamps)
        self._update(graph, values, stamps)
        return True

    def _zero_velocity(self, k_prev: int, k: int, frame: TrackFrame, graph: gtsam.NonlinearFactorGraph) -> None:
        """Standstill detection: if the static-camera tracks did not move between the keyframes
        (median displacement below ``zupt_threshold``), add zero-velocity and no-motion factors.
        Without parallax nothing can be triangulated, so this is what keeps a resting body fixed."""
        o = self.opt
        prev = self.prev_static
        cur = dict(zip(frame.static_ids.tolist(), frame.static_xy, strict=True))
        self.prev_static = cur
        common = [tid for tid in cur if tid in prev]
        if len(common) < o.zupt_min_tracks:
            return
        disp = float(np.median([np.linalg.norm(cur[tid] - prev[tid]) for tid in common]))
        if disp >= o.zupt_threshold:
            return
        self.stats["zero_velocity"] = self.stats.get("zero_velocity", 0) + 1
        graph.add(
            gtsam.PriorFactorVector(V(k), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, o.zupt_velocity_sigma))
        )
        graph.add(
            gtsam.BetweenFactorPose3(
                X(k_prev), X(k), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, o.zupt_pose_sigma)
            )
        )

    def _add_camera_pose(
        self,
        k: int,
        pose: gtsam.Pose3,
        theta: FloatArray,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        stamps: dict[int, int],
    ) -> None:
        """dcc with ``gimbal_factor='camera_pose'``: the auxiliary gimbal-camera pose of keyframe k."""
        if self.opt.gimbal_factor != "camera_pose":
            return
        assert self.cal is not None and self.chain_cache is not None
        T_Wd = pose.compose(gtsam.Pose3(self.cal.T_ds(theta) @ self.T_sI).inverse())
        values.insert(CAM(k), T_Wd)
        stamps[CAM(k)] = self.kf_times[k]
        sig = self.opt.camera_pose_sigma
        graph.add(gimbal_camera_pose_factor(X(k), TH(k), CAM(k), self.chain_cache, self.T_sI, sig, sig))

    def _fit_theta(self, frame: TrackFrame, T_WI: FloatArray, theta0: FloatArray, prior_sigma: float) -> FloatArray:
        """Stage one of the gimbal outlier handling: Gauss-Newton on the joint angles alone (Huber,
        no rejection) against gimbal observations of known landmarks, pose from the IMU."""
        assert self.cal is not None
        idx = [i for i, tid in enumerate(frame.dynamic_ids) if int(tid) in self.active]
        if len(idx) < 3:
            return theta0.copy()
        p_W = np.array([self.landmark_pos[self.active[int(frame.dynamic_ids[i])]] for i in idx])
        z = frame.dynamic_xy[idx]
        theta = theta0.copy()
        for _ in range(10):  # iteratively reweighted least squares with Huber weights
            res = gimbal_residuals(T_WI, p_W, theta, self.cal.kin, self.L, self.T_sI, z)
            assert res.d_theta is not None
            r = res.r / self.opt.sigma
            _, w = self.robust.rho(np.sum(r * r, axis=1))
            sw = np.sqrt(w)[:, None]
            A = (res.d_theta / self.opt.sigma * sw[:, :, None]).reshape(-1, self.L)
            b = (r * sw).reshape(-1)
            H = A.T @ A + np.eye(self.L) / prior_sigma**2
            g = A.T @ b + (theta - theta0) / prior_sigma**2
            step = -np.linalg.solve(H, g)
            theta = theta + step
            if np.max(np.abs(step)) < 1e-7:
                break
        return theta

    def _observe(
        self, k: int, frame: TrackFrame, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict[int, int]
    ) -> None:
        """Add factors of known landmarks, buffer the rest, triangulate ready tracks."""
        t = frame.timestamp_ns
        o = self.opt
        theta_k = self._theta_at(k, values)
        cams = [(0, frame.static_ids, frame.static_xy)]
        if o.mode != "mono":
            cams.append((1, frame.dynamic_ids, frame.dynamic_xy))
        for cam, ids, xy in cams:
            if ids.size == 0:
                continue
            T_cW = chain.inv_se3(self._T_Wc(k, cam, theta_k))
            for tid, z in zip(ids.tolist(), xy, strict=True):
                lm = self.active.get(tid)
                if lm is None:
                    self.tracks.setdefault(tid, _Track()).obs.append((k, cam, z))
                    continue
                p_c = T_cW[:3, :3] @ self.landmark_pos[lm] + T_cW[:3, 3]
                if p_c[2] <= 0 or np.linalg.norm(p_c[:2] / p_c[2] - z) > o.observation_gate * o.sigma:
                    self.stats["gated"] += 1
                    continue
                graph.add(self._factor(k, cam, lm, z))
                self.landmark_last[lm] = t
                stamps[LM(lm)] = t
        self._triangulate_ready(k, t, graph, values, stamps)

    def _factor(self, k: int, cam: int, lm: int, z: FloatArray) -> gtsam.NonlinearFactor:
        """Reprojection factor of landmark ``lm`` seen by camera ``cam`` (0 static, 1 gimbal) at keyframe k."""
        o = self.opt
        if cam == 0:
            self.stats["static_obs"] += 1
            return self.project_static(z, X(k), LM(lm))
        self.stats["dynamic_obs"] += 1
        if o.mode == "dcc" and o.gimbal_factor == "camera_pose":
            return self.project_camera(z, CAM(k), LM(lm))
        if o.mode == "dcc":
            assert self.chain_cache is not None
            return gimbal_reprojection_factor(z, o.sigma, X(k), LM(lm), TH(k), self.chain_cache, self.T_sI, o.robust_k)
        return self.project_locked(z, X(k), LM(lm))

    def _triangulate_ready(
        self, k: int, t: int, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict[int, int]
    ) -> None:
        o = self.opt
        added = 0
        memo: dict[tuple[int, int], FloatArray] = {}  # camera poses of the window's keyframes
        for tid in list(self.tracks):
            tr = self.tracks[tid]
            tr.obs = [ob for ob in tr.obs if self._in_window(self.kf_times[ob[0]], t)]
            if not tr.obs:
                del self.tracks[tid]
                continue
            if tr.obs[-1][0] != k:
                # not seen in this keyframe: the track ended; drop it if it can never become ready
                if len({ob[0] for ob in tr.obs}) < o.min_track_keyframes:
                    del self.tracks[tid]
                continue
            kfs = {ob[0] for ob in tr.obs}
            if len(kfs) < o.min_track_keyframes or added >= o.max_new_landmarks:
                continue
            # static observations do not depend on the (uncertain) joint angles: prefer them; fall back
            # on both cameras (a stereo baseline: what gives landmarks while the body stands still)
            p, ok = np.full(3, np.nan), False
            static_obs = [ob for ob in tr.obs if ob[1] == 0]
            for use in (static_obs, tr.obs):
                if len({(ob[0], ob[1]) for ob in use}) < 2 or (use is tr.obs and len(use) == len(static_obs)):
                    continue
                T_Wc = np.array(
                    [
                        memo[(kk, cam)] if (kk, cam) in memo else memo.setdefault((kk, cam), self._T_Wc(kk, cam))
                        for kk, cam, _ in use
                    ]
                )
                xy = np.array([z for _, _, z in use])
                p = triangulate(T_Wc, xy)
                ok = self._good_landmark(p, T_Wc, xy)
                if ok:
                    break
            if not ok:
                if len(kfs) > 3 * o.min_track_keyframes:
                    del self.tracks[tid]  # never converges: give up on this track
                continue
            lm = self.n_landmarks
            self.n_landmarks += 1
            self.stats["landmarks"] += 1
            self.active[tid] = lm
            self.landmark_pos[lm] = p
            self.landmark_last[lm] = t
            values.insert(LM(lm), p)
            # a very weak prior keeps a landmark determined if all its projections fail cheirality
            graph.add(gtsam.PriorFactorPoint3(LM(lm), p, gtsam.noiseModel.Isotropic.Sigma(3, o.landmark_prior_sigma)))
            stamps[LM(lm)] = t
            for kk, cam, z in tr.obs:
                graph.add(self._factor(kk, cam, lm, z))
            del self.tracks[tid]
            added += 1

    def _good_landmark(self, p: FloatArray, T_Wc: FloatArray, xy: FloatArray) -> bool:
        o = self.opt
        if not np.all(np.isfinite(p)):
            return False
        centres = T_Wc[:, :3, 3]
        rays = p - centres
        dist = np.linalg.norm(rays, axis=1)
        if np.any(dist > o.max_depth) or np.any(dist < 0.2):
            return False
        p_c = np.einsum("nji,nj->ni", T_Wc[:, :3, :3], rays)
        if np.any(p_c[:, 2] <= 0.1):
            return False
        if np.max(np.linalg.norm(p_c[:, :2] / p_c[:, 2:3] - xy, axis=1)) > o.triangulation_gate * o.sigma:
            return False
        u = rays / dist[:, None]
        cosang = np.clip(u @ u.T, -1.0, 1.0)
        return bool(np.degrees(np.arccos(cosang.min())) >= o.min_parallax_deg)

    def _update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict[int, int]) -> None:
        ts = gtsam.FixedLagSmootherKeyTimestampMap()
        for key, t in stamps.items():
            ts.insert((key, t / NS))
        try:
            self.smoother.update(graph, values, ts)
            for _ in range(self.opt.extra_iterations):
                self.smoother.update()
        except RuntimeError as err:  # indeterminant system etc.: log, restart from the IMU prediction
            self.stats["failed_updates"] += 1
            log.warning(
                "smoother update failed at keyframe %d (%s); restarting the window from the IMU prediction",
                self.k,
                str(err).strip().splitlines()[0],
            )
            self._restart(values)
        est = self.smoother.calculateEstimate()
        for kk, t in self.kf_times.items():
            if est.exists(X(kk)):
                th = est.atVector(TH(kk)) if est.exists(TH(kk)) else self._theta_at(kk)
                b = est.atConstantBias(B(kk))
                self.estimates[kk] = (
                    t,
                    est.atPose3(X(kk)).matrix(),
                    est.atVector(V(kk)),
                    b.accelerometer(),
                    b.gyroscope(),
                    np.asarray(th, float).copy(),
                )
        k = self.k
        self.state = gtsam.NavState(est.atPose3(X(k)), est.atVector(V(k)))
        self.bias = est.atConstantBias(B(k))
        if self.opt.mode == "dcc":
            self.theta = est.atVector(TH(k))
        # landmarks: refresh positions, forget the marginalized ones
        cutoff = self.kf_times[k] - int(self.opt.lag * NS)
        for tid, lm in list(self.active.items()):
            if est.exists(LM(lm)):
                self.landmark_pos[lm] = est.atPoint3(LM(lm))
            if self.landmark_last[lm] < cutoff or not est.exists(LM(lm)):
                del self.active[tid]
                self.landmark_pos.pop(lm, None)
        self.stats["keyframes"] = k + 1

    def _restart(self, values: gtsam.Values) -> None:
        """Recovery after a failed update: a fresh window anchored at the newest keyframe's
        predicted state (moderate priors), with every landmark and buffered track dropped."""
        o, k = self.opt, self.k
        t = self.kf_times[k]
        self.smoother = self._new_smoother()
        self.active.clear()
        self.landmark_pos.clear()
        self.tracks.clear()
        graph = gtsam.NonlinearFactorGraph()
        new = gtsam.Values()
        pose, vel, bias = values.atPose3(X(k)), values.atVector(V(k)), values.atConstantBias(B(k))
        graph.add(
            gtsam.PriorFactorPose3(
                X(k),
                pose,
                gtsam.noiseModel.Diagonal.Sigmas(
                    np.r_[np.full(3, o.recovery_rotation_sigma), np.full(3, o.recovery_position_sigma)]
                ),
            )
        )
        graph.add(gtsam.PriorFactorVector(V(k), vel, gtsam.noiseModel.Isotropic.Sigma(3, 10 * o.prior_velocity_sigma)))
        graph.add(
            gtsam.PriorFactorConstantBias(
                B(k),
                bias,
                gtsam.noiseModel.Diagonal.Sigmas(
                    np.r_[np.full(3, o.prior_acc_bias_sigma), np.full(3, o.prior_gyro_bias_sigma)]
                ),
            )
        )
        new.insert(X(k), pose)
        new.insert(V(k), vel)
        new.insert(B(k), bias)
        stamps = {X(k): t, V(k): t, B(k): t}
        if o.mode == "dcc":
            theta = values.atVector(TH(k))
            graph.add(
                gtsam.PriorFactorVector(TH(k), theta, gtsam.noiseModel.Isotropic.Sigma(self.L, o.theta_prior_sigma))
            )
            new.insert(TH(k), theta)
            stamps[TH(k)] = t
            self._add_camera_pose(k, pose, theta, graph, new, stamps)
        ts = gtsam.FixedLagSmootherKeyTimestampMap()
        for key, tt in stamps.items():
            ts.insert((key, tt / NS))
        self.smoother.update(graph, new, ts)

    def result(self) -> VioResult:
        ks = sorted(self.estimates)
        e = [self.estimates[k] for k in ks]
        return VioResult(
            timestamps_ns=np.array([x[0] for x in e], dtype=np.int64),
            T_WI=np.array([x[1] for x in e]),
            v_W=np.array([x[2] for x in e]),
            acc_bias=np.array([x[3] for x in e]),
            gyro_bias=np.array([x[4] for x in e]),
            theta=np.array([x[5] for x in e]).reshape(len(e), -1),
            mode=self.opt.mode,
            stats=dict(self.stats),
        )


def run_vio(
    frames: list[TrackFrame],
    imu: ImuSamples,
    imu_config: ImuConfig,
    calibration: GimbalCalibration | None = None,
    options: VioOptions | None = None,
    initial: InitialState | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> VioResult:
    """Run the smoother over time-ordered frames; ``initial`` (at the first frame) or standstill."""
    options = options or VioOptions()
    validate_frames(frames)
    t_start = time.perf_counter()
    sm = VioSmoother(imu, imu_config, calibration, options)
    if frames[0].timestamp_ns < imu.t_ns[0] or frames[-1].timestamp_ns > imu.t_ns[-1] + NS // 10:
        log.warning("camera frames extend beyond the IMU data; clipping to the IMU time span")
    frames = [f for f in frames if imu.t_ns[0] <= f.timestamp_ns <= imu.t_ns[-1]]
    if not frames:
        raise ValueError("no camera frame lies within the IMU time span")
    if initial is not None:
        frames = [f for f in frames if f.timestamp_ns >= initial.t_ns]
    sm.initialize(frames[0], initial)
    for i, f in enumerate(frames[1:], start=1):
        sm.add_frame(f)
        if progress is not None:
            progress(i, len(frames))
    res = sm.result()
    duration = (frames[-1].timestamp_ns - frames[0].timestamp_ns) / NS
    res.stats.update(timing_stats(time.perf_counter() - t_start, duration, len(frames)))
    return res


def timing_stats(elapsed_s: float, duration_s: float, frames: int) -> dict[str, float | int]:
    """Processing time, data duration (s), their ratio (the real-time factor) and the frame count."""
    return {
        "processing_time_s": elapsed_s,
        "data_duration_s": duration_s,
        "real_time_factor": elapsed_s / duration_s if duration_s > 0 else float("nan"),
        "frames": frames,
    }


def write_vio_outputs(out_dir: str | Path, result: VioResult, extra: dict[str, Any] | None = None) -> None:
    """``OUT/trajectory.tum`` (body/IMU frame), ``OUT/joint_angles.csv`` (dcc/scc) and ``OUT/summary.json``."""
    from dcc_fg.io.outputs import write_joint_angles_csv, write_json
    from dcc_fg.io.tum import write_tum

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_tum(out / "trajectory.tum", result.timestamps_ns, result.T_WI)
    if result.mode != "mono" and result.theta.shape[1] > 0:
        write_joint_angles_csv(out / "joint_angles.csv", result.timestamps_ns, result.theta)
    summary = {
        "mode": result.mode,
        "keyframes": int(result.timestamps_ns.size),
        "start_ns": int(result.timestamps_ns[0]) if result.timestamps_ns.size else None,
        "end_ns": int(result.timestamps_ns[-1]) if result.timestamps_ns.size else None,
        "final_acc_bias": result.acc_bias[-1] if result.timestamps_ns.size else None,
        "final_gyro_bias": result.gyro_bias[-1] if result.timestamps_ns.size else None,
        **result.stats,
        **(extra or {}),
    }
    write_json(out / "summary.json", summary)
