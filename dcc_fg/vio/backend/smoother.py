"""The keyframe smoother: feeds frames through IMU propagation, joint angles, landmarks and the window.

:class:`VioSmoother` orchestrates the pieces of :mod:`dcc_fg.vio.backend` (package docstring): per
keyframe it preintegrates the IMU from the previous keyframe (:mod:`.imu`), fits the joint angles
(:mod:`.joints`, ``dcc``), adds zero-velocity factors at standstill (:mod:`.zupt`), adds the
observations of known landmarks and triangulates ready tracks (:mod:`.landmarks`, factors from
:mod:`.cameras`) and updates the fixed-lag window (:mod:`.window`), restarting it after a failure.
Estimates are kept per keyframe as :class:`~.state.KeyframeState`. ``T_WI`` maps body/IMU points into
W (gravity along -z); times in ns, angles in rad (``docs/architecture.md``).

Recovery: every keyframe is checked against the physical limits of :mod:`.divergence` (finite,
speed, position jump, velocity covariance). A keyframe whose IMU interval has a gap (a sample
spacing longer than ``imu_gap_periods`` median periods), a diverged keyframe and a failed update
each start a new *trajectory segment*: the window and the landmarks are dropped and the smoother is
re-anchored at that keyframe, from standstill when the IMU and the static camera's tracks are at
rest, else from the last healthy keyframe's attitude and velocity (IMU-propagated to the keyframe
when the IMU covers the interval) with loose priors, and vision starts afresh. Frames inside an IMU
gap make no keyframes. The segments (start/end stamps, reason) and the divergence events are in
``stats['segments']`` / ``stats['divergences']``; a segment's pose is only defined up to its own
start (evaluate per segment).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import gtsam
import numpy as np
from numpy.typing import NDArray

from dcc_fg.data.cameras import RunCamera
from dcc_fg.data.vio import ImuConfig, ImuSamples, TrackFrame
from dcc_fg.model import GimbalCalibration
from dcc_fg.util.errors import EstimatorError
from dcc_fg.vio.backend.cameras import GIMBAL, STATIC, CameraRig
from dcc_fg.vio.backend.chains import ChainStates
from dcc_fg.vio.backend.divergence import DivergenceLimits, divergence
from dcc_fg.vio.backend.exposure import ExposureModel
from dcc_fg.vio.backend.imu import preintegrate, preintegration_params, standstill_state, validate_imu
from dcc_fg.vio.backend.joints import fit_joint_angles_to_landmarks, joint_measurement_prior, start_joint_angles
from dcc_fg.vio.backend.keys import (
    bias_key,
    camera_key,
    landmark_key,
    pose_key,
    static_camera_key,
    theta_key,
    velocity_key,
)
from dcc_fg.vio.backend.landmarks import LandmarkMap, prediction_errors
from dcc_fg.vio.backend.options import NS, FloatArray, InitialState, VioOptions, VioResult
from dcc_fg.vio.backend.residuals import CameraResiduals
from dcc_fg.vio.backend.state import KeyframeState, result_from_states
from dcc_fg.vio.backend.structureless import StructurelessLandmarks
from dcc_fg.vio.backend.window import AnchorSigmas, FixedLagWindow, anchor_factors, window_start_ns
from dcc_fg.vio.backend.zupt import static_tracks_at_rest, zero_velocity_factors
from dcc_fg.vio.joint_init import fit_joint_angles
from factors import chain
from factors.calibration import RobustLoss
from factors.exposure import CameraMount
from factors.vio import joint_random_walk_factor

log = logging.getLogger(__name__)


class VioSmoother:
    """Incremental keyframe smoother; feed frames in time order with :meth:`add_frame`.

    Public state: ``k`` the newest keyframe's index, ``kf_times`` keyframe index -> time (ns),
    ``estimates`` keyframe index -> :class:`KeyframeState`, ``state``/``bias``/``theta`` the newest
    keyframe's navigation state, IMU bias and joint angles, ``landmarks`` the
    :class:`~.landmarks.LandmarkMap`, ``stats`` counters of the run.
    """

    def __init__(
        self,
        imu: ImuSamples,
        imu_config: ImuConfig,
        calibration: GimbalCalibration | None,
        options: VioOptions,
        cameras: Sequence[RunCamera] = (),
    ) -> None:
        """``cameras``: the further cameras of an N-camera run (run index >= 2,
        :func:`dcc_fg.data.cameras.run_cameras`); their tracks come in :attr:`TrackFrame.extra`.
        ``options`` not resolved (``persistent_landmarks`` ``auto`` or ``lag`` None) are resolved as for
        unsynchronized cameras (every landmark persistent, 1.5 s): the callers that see the data
        (:func:`~.runner.run_vio`, :func:`dcc_fg.vio.pipeline.run_vio_bag`) resolve them from it first."""
        validate_imu(imu)
        if not options.is_resolved:
            options = options.resolved(synchronized=False)
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
        self.rig = CameraRig(calibration, self.T_sI, options, cameras)
        self.chains = ChainStates(cameras, options, self.T_sI)  # further chains' joint angles (dcc)
        self.residuals = self._camera_residuals(cameras, calibration)
        self.exposure = ExposureModel(options, imu, self._mounts())
        self.window = FixedLagWindow(options)
        self.landmarks = LandmarkMap(
            frozenset(c for c in (STATIC, *self.rig.extra) if self.rig.is_rigid(c)),
            options.persistent_landmarks,
        )
        self.structureless: StructurelessLandmarks | None = None
        if options.landmarks == "smart":
            if cameras:
                raise ValueError("landmarks 'smart' supports the static and the gimbal camera only: use 'explicit'")
            self.structureless = StructurelessLandmarks(options.sigma, options.max_depth, options.smart_outlier_sigmas)
        self.k = -1
        self.kf_times: dict[int, int] = {}
        self.estimates: dict[int, KeyframeState] = {}
        self.state: gtsam.NavState | None = None
        self.bias = gtsam.imuBias.ConstantBias()
        self.theta = np.zeros(self.L)
        # frames added since the last keyframe (the first added frame is a keyframe)
        self.since_keyframe = options.keyframe_every - 1
        self.prev_static: dict[int, FloatArray] = {}
        self.stats: dict[str, Any] = {
            "keyframes": 0,
            "landmarks": 0,
            "static_obs": 0,
            "dynamic_obs": 0,
            "extra_obs": {c.name: 0 for c in cameras},
            "gated": 0,
            "failed_updates": 0,
            "window": {"persistent_landmarks": options.persistent_landmarks, "lag_s": options.window_s},
        }
        # recovery bookkeeping (module docstring)
        self.limits = DivergenceLimits.from_options(options, imu_config)
        dt_imu = np.diff(imu.t_ns)
        self.max_imu_gap_ns = int(options.imu_gap_periods * float(np.median(dt_imu)))
        self.segments: list[dict[str, Any]] = []  # start keyframe index, start time, reason
        self.divergences: list[dict[str, Any]] = []
        self.healthy_k = 0
        self.in_gap = False
        self.last_frame_static: dict[int, FloatArray] = {}
        self.vision_factors = 0  # visual factors (reprojection, zero velocity) of the keyframe being built
        self.last_vision_ns: int | None = None
        self.longest_without_vision_ns = 0
        self.velocity_sigma: dict[int, float] = {}
        self.theta_sigma: dict[int, FloatArray] = {}  # joint-angle 1-sigma per keyframe (joint_sigmas)

    # ------------------------------------------------------------------ helpers
    def _camera_residuals(
        self, cameras: Sequence[RunCamera], calibration: GimbalCalibration | None
    ) -> CameraResiduals | None:
        """Per-camera residual bookkeeping of an N-camera run (None for one or two cameras, or without
        cam0's intrinsics): focal lengths (px) of cam0, the gimbal camera (scc / dcc) and each further one."""
        if not cameras or calibration is None or calibration.static_camera is None:
            return None
        focal = {STATIC: float(np.mean(calibration.static_camera.intrinsics[:2]))}
        if self.opt.mode != "mono" and calibration.dynamic_camera is not None:
            focal[GIMBAL] = float(np.mean(calibration.dynamic_camera.intrinsics[:2]))
        for c in cameras:
            focal[c.index] = float(np.mean(c.model.intrinsics[:2]))
        return CameraResiduals(focal)

    def _mounts(self) -> dict[int, CameraMount]:
        """``T_Ic`` of each camera for the exposure-time poses (:mod:`.exposure`)."""
        o = self.opt
        timed = o.estimate_time_offsets or any(x != 0.0 for x in o.offsets)
        if timed and o.mode == "dcc" and o.gimbal_factor != "camera_pose":
            raise ValueError(
                "time offsets (estimated or not zero) need gimbal_factor 'camera_pose' (the gimbal observations "
                "project onto an exposure-time camera pose); set estimate_time_offsets False and time_offsets 0"
            )
        mounts = {STATIC: CameraMount(T_Ic=chain.inv_se3(self.T_sI))}
        if o.mode == "dcc":
            mounts[GIMBAL] = CameraMount(cache=self.rig.chain_cache, T_sI=self.T_sI)
        elif o.mode == "scc":
            mounts[GIMBAL] = CameraMount(T_Ic=chain.inv_se3(self.rig.T_dI_fixed))
        return mounts

    def _theta_at(self, k: int, values: gtsam.Values | None = None) -> FloatArray:
        """Joint angles of keyframe ``k``: fixed (scc), none (mono), else from ``values`` or the estimates."""
        if self.opt.mode == "scc":
            return np.asarray(self.opt.theta_fixed, float)
        if self.opt.mode == "mono":
            return np.zeros(self.L)
        if values is not None and values.exists(theta_key(k)):
            return values.atVector(theta_key(k))
        return self.estimates[k].theta if k in self.estimates else self.theta

    def _theta_for(self, k: int, cam: int, values: gtsam.Values | None = None) -> FloatArray:
        """Joint angles camera ``cam`` follows at keyframe ``k``: a further chain's for a camera on it,
        else the primary chain's (:meth:`_theta_at`)."""
        c = self.rig.extra.get(cam)
        if c is not None and c.slot >= 1:
            return self.chains.theta_at(k, c.slot, values)
        return self._theta_at(k, values)

    def _T_Wc(self, k: int, cam: int, theta: FloatArray | None = None) -> FloatArray:
        """Pose (camera -> W) of camera ``cam`` at keyframe ``k`` from its current estimate, at the
        exposure time of its image when that is timed (:mod:`.exposure`)."""
        if theta is None and (cam == GIMBAL or not self.rig.is_rigid(cam)):
            theta = self._theta_for(k, cam)
        if cam in self.rig.extra:  # exposed with the static image: T_Wc = T_Ws T_sc(theta)
            return self._T_Wc(k, STATIC) @ chain.inv_se3(self.rig.extra[cam].T_cs_at(theta))
        est = self.estimates[k]
        T = self.exposure.T_Wc(k, cam, est.T_WI, est.v_W, theta)
        return T if T is not None else self.rig.T_Wc(est.T_WI, cam, theta)

    def _add_camera_poses(
        self,
        k: int,
        frame: TrackFrame,
        pose: gtsam.Pose3,
        velocity: FloatArray,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        stamps: dict[int, int],
    ) -> None:
        """Camera poses of keyframe ``k``: exposure-time poses of its timed images (:mod:`.exposure`),
        else (dcc) the gimbal camera's pose at the keyframe time."""
        t = self.kf_times[k]
        gyro_bias = self.bias.gyroscope()
        if self.exposure.static_timed():
            self.exposure.add_image(k, STATIC, t, 0.0, pose, velocity, gyro_bias, None, None, graph, values, stamps)
        if self.opt.mode == "mono":
            return
        if self.rig.has_camera_poses:  # further cameras on a chain: their poses e(k), nothing to do otherwise
            T_Ws = self.exposure.T_Wc(k, STATIC, pose.matrix(), velocity, None)
            T_Ws = pose.matrix() @ chain.inv_se3(self.T_sI) if T_Ws is None else T_Ws
            static = (self.exposure.is_timed(k, STATIC), self.exposure.shift.get((k, STATIC)))

            def theta_of(slot: int) -> FloatArray:
                return self._theta_at(k, values) if slot == 0 else self.chains.theta_at(k, slot, values)

            self.rig.add_extra_camera_poses(k, t, T_Ws, theta_of, *static, graph, values, stamps)
        gap = frame.dynamic_gap_s
        theta = self._theta_at(k, values)
        if not self.exposure.gimbal_timed(gap):
            if self.opt.mode == "dcc":
                self.rig.add_gimbal_camera_pose(k, t, pose, theta, graph, values, stamps)
            return
        previous = None
        k_prev = k - 1
        if self.opt.mode == "dcc" and k_prev >= self.segments[-1]["k"] and k_prev in self.kf_times:
            previous = (self.kf_times[k_prev], self._theta_at(k_prev))
        self.exposure.add_image(
            k,
            GIMBAL,
            t,
            gap,
            pose,
            velocity,
            gyro_bias,
            theta if self.opt.mode == "dcc" else None,
            previous,
            graph,
            values,
            stamps,
        )

    def _theta_initial(self) -> FloatArray:
        """``theta_initial`` (rad), which a ``dcc`` start without given joint angles needs."""
        if self.opt.theta_initial is None or len(self.opt.theta_initial) != self.L:
            raise ValueError(f"dcc mode from standstill needs theta_initial ({self.L} joint angles, rad)")
        return np.asarray(self.opt.theta_initial, float)

    def _standstill_initial_state(self, frame: TrackFrame) -> InitialState:
        initial = standstill_state(self.imu, frame.timestamp_ns, self.opt.standstill_window, self.cfg.gravity, self.L)
        if self.opt.mode != "dcc":
            return initial
        i = initial
        return InitialState(i.t_ns, i.T_WI, i.v_W, i.acc_bias, i.gyro_bias, self._theta_initial())

    # ------------------------------------------------------------------ main loop
    def initialize(self, frame: TrackFrame, initial: InitialState | None, sigmas: AnchorSigmas | None = None) -> None:
        """Start at ``frame`` from ``initial`` (at the frame's time; without joint angles in ``dcc``:
        ``theta_initial``) or from standstill, anchored with ``sigmas`` (default: the first keyframe's)."""
        if initial is None:
            initial = self._standstill_initial_state(frame)
        elif self.opt.mode == "dcc" and np.asarray(initial.theta).size == 0:
            i = initial
            initial = InitialState(i.t_ns, i.T_WI, i.v_W, i.acc_bias, i.gyro_bias, self._theta_initial())
        theta0 = start_joint_angles(initial, self.opt, self.L)
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
        dcc = self.opt.mode == "dcc"
        sigmas = sigmas or AnchorSigmas.first_keyframe(self.opt)
        graph, values, stamps = anchor_factors(0, t, pose, v, self.bias, self.theta if dcc else None, sigmas)
        self.chains.anchor(0, t, sigmas.theta, graph, values, stamps, self.chains.fit_pairs(frame))
        self.exposure.anchor(graph, values, stamps, t)
        self.segments.append({"k": 0, "start_ns": t, "reason": "start"})
        self._add_camera_poses(0, frame, pose, v, graph, values, stamps)
        self.state = gtsam.NavState(pose, v)
        self.estimates[0] = KeyframeState(
            t, pose.matrix(), v, self.bias.accelerometer(), self.bias.gyroscope(), self.theta.copy()
        )
        self.last_vision_ns = t
        self.vision_factors = 0
        self._observe(0, frame, graph, values, stamps)
        self.prev_static = dict(zip(frame.static_ids.tolist(), frame.static_xy, strict=True))
        self.last_frame_static = dict(self.prev_static)
        self._update(graph, values, stamps)
        self._after_keyframe(0)

    def next_is_keyframe(self) -> bool:
        """True if a keyframe is due at the next :meth:`add_frame` call (:meth:`_makes_keyframe`)."""
        return self.since_keyframe >= self.opt.keyframe_every - 1

    def _makes_keyframe(self, frame: TrackFrame) -> bool:
        """Every ``keyframe_every``-th frame is a keyframe; with a gimbal camera a due keyframe waits (up
        to ``keyframe_every - 1`` more frames) for a frame with gimbal observations, so that cameras at
        different rates (a static frame without a gimbal partner) do not leave the joints unobserved."""
        n = self.opt.keyframe_every
        if self.since_keyframe < n - 1:
            return False
        waiting = self.opt.mode != "mono" and frame.dynamic_ids.size == 0
        return not waiting or self.since_keyframe >= 2 * n - 2

    def gimbal_landmarks(self, frame: TrackFrame) -> int:
        """How many of the frame's gimbal-camera tracks are mapped landmarks."""
        return sum(int(tid) in self.landmarks.active for tid in frame.dynamic_ids)

    def add_frame(self, frame: TrackFrame, theta_measurement: tuple[FloatArray, FloatArray] | None = None) -> bool:
        """Process one frame; returns True if it became a keyframe.

        ``theta_measurement`` = (theta (L,) rad, covariance (L, L) rad^2): a direct measurement of
        the joint angles, e.g. from the frame's static <-> gimbal epipolar geometry
        (:func:`dcc_fg.vio.joint_init.fit_joint_angles`). It is used (``dcc`` mode) only while the
        gimbal camera sees fewer than ``min_gimbal_landmarks`` mapped landmarks, i.e. when the
        reprojection factors cannot determine the angles yet (start-up at standstill, after a gap),
        as the starting value and a prior with the covariance inflated by ``theta_measurement_inflation``.
        """
        if not self._makes_keyframe(frame):
            self.since_keyframe += 1
            self.last_frame_static = dict(zip(frame.static_ids.tolist(), frame.static_xy, strict=True))
            return False
        self.since_keyframe = 0
        k_prev, k = self.k, self.k + 1
        t = frame.timestamp_ns
        gap = self.in_gap or self._imu_gap_ns(self.kf_times[k_prev], t) > self.max_imu_gap_ns
        if gap:
            return self._after_imu_gap(k, frame, theta_measurement)
        self.vision_factors = 0
        graph, values, stamps, pred = self._propagate(k_prev, k, t)
        if self.opt.mode == "dcc":
            self._add_joint_angles(k_prev, k, frame, pred.pose(), theta_measurement, graph, values, stamps)
            dt = (t - self.kf_times[k_prev]) / NS
            self.chains.add(k_prev, k, dt, frame, pred.pose().matrix(), self.landmarks, t, graph, values, stamps)
        self._add_camera_poses(k, frame, pred.pose(), pred.velocity(), graph, values, stamps)
        self._zero_velocity(k_prev, k, frame, graph)
        self._observe(k, frame, graph, values, stamps)
        self._update(graph, values, stamps)
        self._after_keyframe(k)
        self.last_frame_static = dict(zip(frame.static_ids.tolist(), frame.static_xy, strict=True))
        return True

    # ------------------------------------------------------------------ recovery
    def _imu_gap_ns(self, t0: int, t1: int) -> int:
        """Longest stretch (ns) of [t0, t1] without an IMU sample (sample spacing, or the part of
        the interval before the first / after the last sample)."""
        t = self.imu.t_ns
        i0 = max(int(np.searchsorted(t, t0, side="right")) - 1, 0)
        i1 = min(int(np.searchsorted(t, t1, side="left")), len(t) - 1)
        inner = t[i0 : i1 + 1]
        gap = int(np.diff(inner).max()) if inner.size > 1 else 0
        gap = max(gap, int(t[0]) - t0, t1 - int(t[-1]))
        return gap

    def _imu_around(self, t: int) -> bool:
        """True if IMU samples lie within the gap limit before and after ``t`` (a keyframe can be
        started there) and the standstill window after it is covered."""
        return self._imu_gap_ns(t - self.max_imu_gap_ns, t + self.max_imu_gap_ns) <= self.max_imu_gap_ns

    def _after_imu_gap(
        self, k: int, frame: TrackFrame, theta_measurement: tuple[FloatArray, FloatArray] | None
    ) -> bool:
        """A keyframe candidate whose IMU interval has a gap: skip it while the IMU is missing, then
        start a new segment at the first keyframe the IMU covers again."""
        t = frame.timestamp_ns
        t_prev = self.kf_times[self.k]
        if not self.in_gap:
            self.in_gap = True
            log.warning(
                "IMU gap of %.3f s after the keyframe at t_ns %d (limit %.3f s = %g IMU periods): no IMU factor can "
                "bridge it; a new trajectory segment starts where the IMU resumes",
                self._imu_gap_ns(t_prev, t) / NS,
                t_prev,
                self.max_imu_gap_ns / NS,
                self.opt.imu_gap_periods,
            )
            self.stats["imu_gaps"] = self.stats.get("imu_gaps", 0) + 1
        if not self._imu_around(t):
            self.last_frame_static = dict(zip(frame.static_ids.tolist(), frame.static_xy, strict=True))
            return False
        self.in_gap = False
        self._new_segment(k, frame, theta_measurement, f"IMU gap of {(t - t_prev) / NS:.3f} s before it")
        return True

    def _at_rest(self, frame: TrackFrame) -> InitialState | None:
        """Standstill state at ``frame`` when both the static camera's tracks (since the previous
        frame) and the IMU (``standstill_window`` after it) are at rest, else None."""
        cur = dict(zip(frame.static_ids.tolist(), frame.static_xy, strict=True))
        if not static_tracks_at_rest(self.last_frame_static, cur, self.opt):
            return None
        try:
            return standstill_state(self.imu, frame.timestamp_ns, self.opt.standstill_window, self.cfg.gravity, self.L)
        except ValueError:
            return None

    def _new_segment(
        self, k: int, frame: TrackFrame, theta_measurement: tuple[FloatArray, FloatArray] | None, reason: str
    ) -> None:
        """Start trajectory segment at new keyframe ``k`` (``frame``) without an IMU factor from the
        previous keyframe: a fresh window and landmark map, anchored from standstill or from the last
        healthy keyframe's attitude and velocity (module docstring)."""
        t = frame.timestamp_ns
        last = self.estimates[self.healthy_k]
        rest = self._at_rest(frame)
        dt = (t - last.t_ns) / NS
        if rest is not None:
            T = np.array(last.T_WI, float)
            T[:3, :3] = rest.T_WI[:3, :3]
            v = np.zeros(3)
            bias = gtsam.imuBias.ConstantBias(np.asarray(last.acc_bias, float), rest.gyro_bias)
            how = "standstill"
        else:
            T = np.array(last.T_WI, float)
            T[:3, 3] += np.asarray(last.v_W, float) * dt
            v = np.asarray(last.v_W, float)
            bias = gtsam.imuBias.ConstantBias(np.asarray(last.acc_bias, float), np.asarray(last.gyro_bias, float))
            how = "last healthy attitude and velocity"
        theta = np.asarray(last.theta, float).copy() if self.L else np.zeros(0)
        if self.opt.mode == "scc":
            theta = np.asarray(self.opt.theta_fixed, float)
        elif self.opt.mode == "dcc":
            theta = (
                np.asarray(theta_measurement[0], float)
                if theta_measurement is not None
                else self._fit_pairs(frame, theta)
            )
        self._anchor_segment(k, t, gtsam.Pose3(T), v, bias, theta, rest is not None, reason, how, frame)

    def _fit_pairs(self, frame: TrackFrame, theta0: FloatArray) -> FloatArray:
        """dcc restart: the joint angles (rad) from the frame's static <-> gimbal pairs (epipolar fit,
        :func:`~dcc_fg.vio.joint_init.fit_joint_angles`) when enough of them agree, else ``theta0``."""
        assert self.cal is not None
        _, i_s, i_d = np.intersect1d(frame.static_ids, frame.dynamic_ids, return_indices=True)
        need = max(8, 2 * self.L + 2)
        if i_s.size < need:
            return theta0
        fit = fit_joint_angles(self.cal, frame.static_xy[i_s], frame.dynamic_xy[i_d], theta0)
        if fit.inliers < max(need, fit.pairs // 2):
            return theta0
        return np.asarray(fit.theta, float)

    def _anchor_segment(
        self,
        k: int,
        t: int,
        pose: gtsam.Pose3,
        v: FloatArray,
        bias: gtsam.imuBias.ConstantBias,
        theta: FloatArray,
        at_rest: bool,
        reason: str,
        how: str,
        frame: TrackFrame | None,
    ) -> None:
        """New segment at keyframe ``k`` (time ``t``) from the given state: drop landmarks, anchor a
        fresh window (loose restart priors), observe ``frame`` and refresh the estimates."""
        o = self.opt
        self._clear_landmarks()
        self.k = k
        self.kf_times[k] = t
        dcc = o.mode == "dcc"
        sigmas = AnchorSigmas(
            o.restart_rotation_sigma,
            o.prior_position_sigma,
            o.zupt_velocity_sigma if at_rest else o.restart_velocity_sigma,
            o.prior_acc_bias_sigma,
            o.prior_gyro_bias_sigma,
            o.restart_theta_sigma,
        )
        graph, values, stamps = anchor_factors(k, t, pose, v, bias, theta if dcc else None, sigmas)
        further = self.chains.fit_pairs(frame) if frame is not None else None
        self.chains.anchor(k, t, sigmas.theta, graph, values, stamps, further)
        self.exposure.before_restart(self.window.smoother)
        self.exposure.anchor(graph, values, stamps, t)
        self.state = gtsam.NavState(pose, v)
        self.bias = bias
        self.theta = theta if self.L else np.zeros(0)
        self.estimates[k] = KeyframeState(t, pose.matrix(), v, bias.accelerometer(), bias.gyroscope(), theta.copy())
        self.segments.append({"k": k, "start_ns": t, "reason": reason})
        if frame is not None:
            self._add_camera_poses(k, frame, pose, v, graph, values, stamps)
        elif dcc:
            self.rig.add_gimbal_camera_pose(k, t, pose, theta, graph, values, stamps)
        self.stats["segments_started"] = self.stats.get("segments_started", 0) + 1
        log.warning("new trajectory segment %d at t_ns %d (%s): restarted from %s", len(self.segments), t, reason, how)
        self.vision_factors = 0
        if frame is not None:
            self._observe(k, frame, graph, values, stamps)
            self.prev_static = dict(zip(frame.static_ids.tolist(), frame.static_xy, strict=True))
        self._restart_window(graph, values, stamps, k, t, pose, v, bias, theta if dcc else None)
        self._refresh()
        self.healthy_k = k
        self._after_keyframe(k, check=False)

    def _after_keyframe(self, k: int, check: bool = True) -> None:
        """Bookkeeping of keyframe ``k`` after its update: vision time, velocity sigma, divergence."""
        t = self.kf_times[k]
        if self.vision_factors > 0 or self.last_vision_ns is None:
            self.last_vision_ns = t
        self.longest_without_vision_ns = max(self.longest_without_vision_ns, t - self.last_vision_ns)
        # the marginal covariance costs as much as the update: only where vision did not constrain
        # the keyframe (the covariance can only blow up there); the last keyframe's in result()
        sigma = self._velocity_sigma(k) if self.vision_factors == 0 else None
        if sigma is not None:
            self.velocity_sigma[k] = sigma
        if not check:
            return
        seg_start = self.segments[-1]["k"]
        prev = self.estimates.get(k - 1) if k - 1 >= seg_start else None
        reason = divergence(prev, self.estimates[k], self.limits, sigma)
        if reason is None:
            self.healthy_k = k
            return
        self._diverged(k, reason)

    def _velocity_sigma(self, k: int) -> float | None:
        """Largest 1-sigma (m/s) of keyframe ``k``'s velocity from the window's marginal covariance."""
        try:
            cov = np.asarray(self.window.smoother.marginalCovariance(velocity_key(k)), float)
        except RuntimeError:
            return None
        return float(np.sqrt(max(np.linalg.eigvalsh(cov).max(), 0.0)))

    def _diverged(self, k: int, reason: str) -> None:
        """Keyframe ``k`` broke a physical limit: record it, drop the diverged keyframes since the
        last healthy one and start a new segment at ``k`` from the last healthy state, propagated
        with the IMU to ``k``'s time."""
        t = self.kf_times[k]
        h = self.healthy_k
        last = self.estimates[h]
        log.warning("divergence at keyframe %d (t_ns %d): %s", k, t, reason)
        self.divergences.append({"t_ns": t, "keyframe": k, "reason": reason, "last_healthy_ns": last.t_ns})
        for kk in range(h + 1, k):
            self.estimates.pop(kk, None)
        bias = gtsam.imuBias.ConstantBias(np.asarray(last.acc_bias, float), np.asarray(last.gyro_bias, float))
        nav = gtsam.NavState(gtsam.Pose3(np.asarray(last.T_WI, float)), np.asarray(last.v_W, float))
        if self._imu_gap_ns(last.t_ns, t) <= self.max_imu_gap_ns:
            nav = preintegrate(self.params, bias, self.imu, last.t_ns, t).predict(nav, bias)
        v = np.asarray(nav.velocity(), float)
        if not np.all(np.isfinite(v)) or np.linalg.norm(v) > self.limits.max_speed:
            v = np.asarray(last.v_W, float)
        theta = np.asarray(last.theta, float).copy()
        self._anchor_segment(
            k, t, nav.pose(), v, bias, theta, False, f"divergence: {reason}", "last healthy state", None
        )

    def _propagate(
        self, k_prev: int, k: int, t: int
    ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, dict[int, int], gtsam.NavState]:
        """New keyframe ``k`` at ``t`` (ns): the IMU factor from ``k_prev``, the predicted state as
        its starting value and first estimate; returns the new graph, values, key times, prediction."""
        t_prev = self.kf_times[k_prev]
        if t - t_prev > 2 * NS:
            log.warning(
                "gap of %.2f s between keyframes at t_ns %d: IMU-only propagation across it", (t - t_prev) / NS, t
            )
        pim = preintegrate(self.params, self.bias, self.imu, t_prev, t)
        assert self.state is not None
        pred = pim.predict(self.state, self.bias)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        graph.add(
            gtsam.CombinedImuFactor(
                pose_key(k_prev), velocity_key(k_prev), pose_key(k), velocity_key(k), bias_key(k_prev), bias_key(k), pim
            )
        )
        values.insert(pose_key(k), pred.pose())
        values.insert(velocity_key(k), pred.velocity())
        values.insert(bias_key(k), self.bias)
        stamps = {pose_key(k): t, velocity_key(k): t, bias_key(k): t}
        self.k = k
        self.kf_times[k] = t
        self.estimates[k] = KeyframeState.from_prediction(t, pred, self.bias, self.theta.copy())
        return graph, values, stamps, pred

    def _add_joint_angles(
        self,
        k_prev: int,
        k: int,
        frame: TrackFrame,
        pose: gtsam.Pose3,
        theta_measurement: tuple[FloatArray, FloatArray] | None,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        stamps: dict[int, int],
    ) -> None:
        """dcc: keyframe ``k``'s joint angles, started from the fit to known landmarks (or from a
        direct measurement while few are seen), with the random walk from ``k_prev``."""
        t = self.kf_times[k]
        dt = (t - self.kf_times[k_prev]) / NS
        T_WI = pose.matrix()
        if self.exposure.gimbal_timed(frame.dynamic_gap_s):  # the body at the gimbal image's exposure
            T_WI = self.exposure.body_pose_at(T_WI, self.estimates[k].v_W, t, GIMBAL, frame.dynamic_gap_s, self.bias)
        theta0 = self._fit_theta(frame, T_WI, self.theta, self.opt.theta_random_walk * np.sqrt(dt))
        if theta_measurement is not None and self.gimbal_landmarks(frame) < self.opt.min_gimbal_landmarks:
            prior = joint_measurement_prior(
                theta_key(k), theta_measurement, self.L, self.opt.theta_measurement_inflation
            )
            if prior is not None:
                theta0 = prior[0]
                graph.add(prior[1])
                self.stats["theta_measurements"] = self.stats.get("theta_measurements", 0) + 1
        values.insert(theta_key(k), theta0)
        stamps[theta_key(k)] = t
        sigma = max(self.opt.theta_random_walk * np.sqrt(dt), 1e-6)
        graph.add(joint_random_walk_factor(theta_key(k_prev), theta_key(k), self.L, sigma))
        self.estimates[k] = self.estimates[k].with_theta(theta0)

    def _fit_theta(self, frame: TrackFrame, T_WI: FloatArray, theta0: FloatArray, prior_sigma: float) -> FloatArray:
        """Stage one of the gimbal outlier handling (:func:`~.joints.fit_joint_angles_to_landmarks`)
        against the frame's gimbal observations of known landmarks, pose from the IMU."""
        assert self.cal is not None
        lms = self.landmarks
        idx = [i for i, tid in enumerate(frame.dynamic_ids) if int(tid) in lms.active]
        p_W = np.array([lms.position[lms.active[int(frame.dynamic_ids[i])]] for i in idx]).reshape(-1, 3)
        z = frame.dynamic_xy[idx]
        return fit_joint_angles_to_landmarks(
            T_WI, p_W, z, theta0, prior_sigma, self.cal.kin, self.T_sI, self.opt.sigma, self.robust
        )

    def _zero_velocity(self, k_prev: int, k: int, frame: TrackFrame, graph: gtsam.NonlinearFactorGraph) -> None:
        """Zero-velocity factors when the static-camera tracks stood still (:mod:`.zupt`)."""
        prev = self.prev_static
        cur = dict(zip(frame.static_ids.tolist(), frame.static_xy, strict=True))
        self.prev_static = cur
        if not static_tracks_at_rest(prev, cur, self.opt):
            return
        self.stats["zero_velocity"] = self.stats.get("zero_velocity", 0) + 1
        self.vision_factors += 1
        for factor in zero_velocity_factors(k_prev, k, self.opt):
            graph.add(factor)

    def _observe(
        self, k: int, frame: TrackFrame, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict[int, int]
    ) -> None:
        """Add factors of known landmarks (gated), buffer the rest, triangulate ready tracks."""
        t = frame.timestamp_ns
        o = self.opt
        lms = self.landmarks
        cams = [(STATIC, frame.static_ids, frame.static_xy)]
        if o.mode != "mono":
            cams.append((GIMBAL, frame.dynamic_ids, frame.dynamic_xy))
        cams.extend((c.camera, c.ids, c.xy) for c in frame.extra if c.camera in self.rig.extra)
        for cam, ids, xy in cams:
            if ids.size == 0:
                continue
            T_cW = chain.inv_se3(self._T_Wc(k, cam, self._theta_for(k, cam, values)))
            if self.residuals is not None:
                self.residuals.offer(cam, ids.size)
            tids = ids.tolist()
            lm_of = [lms.active.get(tid) for tid in tids]
            known = [i for i, lm in enumerate(lm_of) if lm is not None]
            errors = np.full(len(tids), np.inf)  # predicted errors of the known landmarks' observations
            errors[known] = prediction_errors(
                T_cW, np.array([lms.position[lm_of[i]] for i in known]).reshape(-1, 3), xy[known]
            )
            for i, (tid, z) in enumerate(zip(tids, xy, strict=True)):
                lm = lm_of[i]
                if lm is None:
                    lms.buffer(tid, k, cam, z)
                    continue
                err = float(errors[i])
                if err > o.gate * o.sigma:
                    self.stats["gated"] += 1
                    if self.residuals is not None:  # a gated observation counts with its predicted error
                        self.residuals.add_gated(cam, err)
                    continue
                self._add_observation(k, cam, lm, z, graph)
                lms.last_seen_ns[lm] = t
                if self.structureless is None:
                    stamps[landmark_key(lm)] = lms.stamp_ns(lm)
        self._triangulate_ready(k, t, graph, values, stamps)

    def _add_observation(self, k: int, cam: int, lm: int, z: FloatArray, graph: gtsam.NonlinearFactorGraph) -> None:
        """Landmark ``lm`` seen at ``z`` by camera ``cam`` in keyframe ``k``: its reprojection factor, or, with
        structureless landmarks, an observation of its smart factor on the camera's pose."""
        factor = self._factor(k, cam, lm, z)
        if self.structureless is None:
            graph.add(factor)
        else:
            self.structureless.add(lm, self._camera_pose_key(k, cam), z)

    def _camera_pose_key(self, k: int, cam: int) -> int:
        """The identity-mount camera pose an observation of camera ``cam`` in keyframe ``k`` is on
        (structureless landmarks): ``s(k)`` of a timed static image, ``c(k)`` of the gimbal camera."""
        if cam == STATIC and self.exposure.is_timed(k, STATIC):
            return static_camera_key(k)
        if cam == GIMBAL and (self.exposure.is_timed(k, GIMBAL) or self.opt.mode == "dcc"):
            return camera_key(k)
        raise RuntimeError(
            f"keyframe {k}: camera {cam}'s observation has no camera-pose variable; landmarks 'smart' needs "
            "estimated time offsets and gimbal_factor 'camera_pose'"
        )

    def _clear_landmarks(self) -> None:
        """Drop every landmark and buffered track (and their smart factors' bookkeeping)."""
        self.landmarks.clear()
        if self.structureless is not None:
            self.structureless.clear()

    def _factor(self, k: int, cam: int, lm: int, z: FloatArray) -> gtsam.NonlinearFactor:
        """Reprojection factor of landmark ``lm`` seen by camera ``cam`` at keyframe k (counted)."""
        self.vision_factors += 1
        factor = self._camera_factor(k, cam, lm, z)
        if self.residuals is not None:
            self.residuals.add(cam, factor)
        return factor

    def _camera_factor(self, k: int, cam: int, lm: int, z: FloatArray) -> gtsam.NonlinearFactor:
        """The reprojection factor of :meth:`_factor` (module docstring of :mod:`.cameras`)."""
        if cam in self.rig.extra:
            self.stats["extra_obs"][self.rig.extra[cam].name] += 1
            return self.rig.extra_factor(
                k,
                cam,
                lm,
                z,
                self.exposure.is_timed(k, STATIC),
                self.exposure.shift.get((k, STATIC)),
            )
        self.stats["static_obs" if cam == STATIC else "dynamic_obs"] += 1
        if self.exposure.is_timed(k, cam):
            key = static_camera_key(k) if cam == STATIC else camera_key(k)
            return self.rig.project_camera(z, key, landmark_key(lm))
        shift = self.exposure.shift.get((k, cam))
        if shift is not None:
            return self.rig.project_shifted(z, pose_key(k), landmark_key(lm), shift)
        return self.rig.observation_factor(k, cam, lm, z)

    def _triangulate_ready(
        self, k: int, t: int, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict[int, int]
    ) -> None:
        """New landmarks from ready tracks: value, a very weak prior (keeps a landmark determined
        if all its projections fail cheirality) and the factors of every buffered observation."""
        start = window_start_ns(t, self.kf_times[k - 1] if k >= 1 else None, self.opt.window_s)
        made = self.landmarks.triangulate_ready(k, t, self.kf_times, start, self._T_Wc, self.opt)
        noise = gtsam.noiseModel.Isotropic.Sigma(3, self.opt.landmark_prior_sigma)
        for new in made:
            self.stats["landmarks"] += 1
            if self.structureless is None:
                key = landmark_key(new.index)
                values.insert(key, new.p_W)
                graph.add(gtsam.PriorFactorPoint3(key, new.p_W, noise))
                stamps[key] = self.landmarks.stamp_ns(new.index)
            for kk, cam, z in new.obs:
                self._add_observation(kk, cam, new.index, z, graph)

    def _update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict[int, int]) -> None:
        """Update the window (restart it after a failure), then refresh estimates and landmarks."""
        self.exposure.touch(stamps, self.kf_times[self.k])
        smart = self.structureless
        remove = smart.stage(graph) if smart is not None else None
        error = self.window.update(graph, values, stamps, remove)
        if smart is not None:
            if error is None:
                smart.adopt(self.window.new_factor_slots())
            else:
                smart.discard()
        if error is not None:  # indeterminant system etc.: log, restart from the IMU prediction
            self.stats["failed_updates"] += 1
            log.warning(
                "smoother update failed at keyframe %d (%s); restarting the window from the IMU prediction",
                self.k,
                error,
            )
            self._restart(values)
            self.segments.append({"k": self.k, "start_ns": self.kf_times[self.k], "reason": f"failed update: {error}"})
            self.divergences.append(
                {"t_ns": self.kf_times[self.k], "keyframe": self.k, "reason": f"failed update: {error}"}
            )
        est = self._refresh()
        if self.residuals is not None:
            if error is None:
                self.residuals.evaluate(est, self._landmark_points())
            else:
                self.residuals.discard()
        self.exposure.maybe_freeze(self.window.smoother, self.kf_times[self.k])
        if error is None and self.opt.joint_sigmas and self.opt.mode == "dcc":
            self._joint_sigmas(leaving_only=True)

    def _landmark_points(self) -> dict[int, FloatArray] | None:
        """Structureless landmarks: landmark key -> position (W, m), for evaluating reprojection residuals."""
        if self.structureless is None:
            return None
        lms = self.landmarks
        return {landmark_key(lm): p for lm, p in lms.position.items()}

    def _joint_sigmas(self, leaving_only: bool) -> None:
        """Joint-angle 1-sigma (rad) of the window's keyframes from its marginal covariances, each keyframe
        once: those the next update may marginalize (older than the newest keyframe's time plus twice the
        last keyframe interval minus the lag), or, with ``leaving_only`` False, every one left."""
        k = self.k
        t = self.kf_times[k]
        dt = t - self.kf_times[k - 1] if k - 1 in self.kf_times else 0
        cutoff = t + 2 * dt - int(self.opt.window_s * NS)
        est = self.window.estimate()
        oldest = t - 2 * int(self.opt.window_s * NS)  # older keyframes have left the window
        for kk in range(k, -1, -1):
            if kk not in self.kf_times:
                continue
            if self.kf_times[kk] < oldest:
                break
            if kk in self.theta_sigma or (leaving_only and self.kf_times[kk] >= cutoff):
                continue
            if not est.exists(theta_key(kk)):
                continue
            try:
                cov = np.asarray(self.window.smoother.marginalCovariance(theta_key(kk)), float)
            except RuntimeError:
                continue
            self.theta_sigma[kk] = np.sqrt(np.maximum(np.diag(cov), 0.0))

    def _refresh(self) -> gtsam.Values:
        """Estimates of the window's keyframes, the newest navigation state, bias, joint angles and
        the landmark positions from the window's current estimate (returned)."""
        est = self.window.estimate()
        self.exposure.refresh(est)
        oldest = self.k
        for kk, t in self.kf_times.items():
            if est.exists(pose_key(kk)):
                self.estimates[kk] = KeyframeState.from_values(est, kk, t, self._theta_at(kk))
                oldest = min(oldest, kk)
        self.exposure.forget(oldest)
        k = self.k
        self.state = gtsam.NavState(est.atPose3(pose_key(k)), est.atVector(velocity_key(k)))
        self.bias = est.atConstantBias(bias_key(k))
        if self.opt.mode == "dcc":
            self.theta = est.atVector(theta_key(k))
        self.chains.refresh(est, self.kf_times, k)
        cutoff = self.kf_times[k] - int(self.opt.window_s * NS)
        if self.structureless is None:
            self.landmarks.refresh(est, cutoff)
        else:
            self.structureless.prune(est)
            for lm in self.landmarks.refresh_from(self.structureless.positions(est), cutoff):
                self.structureless.forget(lm)
        self.stats["keyframes"] = k + 1
        return est

    def _restart(self, values: gtsam.Values) -> None:
        """Recovery after a failed update: a fresh window anchored at the newest keyframe's
        predicted state (moderate priors), with every landmark and buffered track dropped."""
        k = self.k
        t = self.kf_times[k]
        self._clear_landmarks()
        self.exposure.forget(k + 1)  # keyframe k's camera poses were lost with the failed update
        self.exposure.before_restart(self.window.smoother)
        pose = values.atPose3(pose_key(k))
        dcc = self.opt.mode == "dcc"
        theta = values.atVector(theta_key(k)) if dcc else None
        graph, new, stamps = anchor_factors(
            k,
            t,
            pose,
            values.atVector(velocity_key(k)),
            values.atConstantBias(bias_key(k)),
            theta,
            AnchorSigmas.recovery(self.opt),
        )
        further = {ch.slot: self.chains.theta_at(k, ch.slot, values) for ch in self.chains.chains}
        self.chains.anchor(k, t, AnchorSigmas.recovery(self.opt).theta, graph, new, stamps, further)
        self.exposure.anchor(graph, new, stamps, t)
        if theta is not None:
            self.rig.add_gimbal_camera_pose(k, t, pose, theta, graph, new, stamps)
        v = values.atVector(velocity_key(k))
        self._restart_window(graph, new, stamps, k, t, pose, v, values.atConstantBias(bias_key(k)), theta)

    def _restart_window(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        stamps: dict[int, int],
        k: int,
        t: int,
        pose: gtsam.Pose3,
        v: FloatArray,
        bias: gtsam.imuBias.ConstantBias,
        theta: FloatArray | None,
    ) -> None:
        """A fresh window from ``graph``; if gtsam finds that system indeterminate (loose restart priors
        and few observations can leave it too poorly conditioned), a fresh window from keyframe k's
        state alone: the recovery priors on pose, velocity, bias (and joint angles, ``theta`` not None)
        and no observations (landmarks and tracks dropped)."""
        try:
            self.window.restart(graph, values, stamps)
            return
        except RuntimeError as err:
            first = " ".join(str(err).strip().split("\n\n")[0].split())
        log.warning(
            "restarting the window at keyframe %d failed (%s); restarting from its state alone (recovery priors, "
            "no observations)",
            k,
            first,
        )
        self.stats["restart_fallbacks"] = self.stats.get("restart_fallbacks", 0) + 1
        self._clear_landmarks()
        self.exposure.forget(k + 1)
        g, vals, st = anchor_factors(k, t, pose, v, bias, theta, AnchorSigmas.recovery(self.opt))
        self.chains.anchor(k, t, AnchorSigmas.recovery(self.opt).theta, g, vals, st)
        self.exposure.anchor(g, vals, st, t)
        if theta is not None:
            self.rig.add_gimbal_camera_pose(k, t, pose, theta, g, vals, st)
        try:
            self.window.restart(g, vals, st)
        except RuntimeError as err:
            raise EstimatorError(
                "VIO smoother",
                f"the window could not be restarted at keyframe {k} (t_ns {t}) even from its state alone: "
                + " ".join(str(err).strip().split("\n\n")[0].split()),
                "check the IMU noise settings (imu.yaml) and the camera calibration; rerun with -v for the updates "
                "before it",
            ) from err

    def result(self) -> VioResult:
        """Every keyframe's latest estimate, in time order, with the run's counters and the recovery
        record: ``segments`` (start/end stamps, keyframes, reason), ``segment_count``,
        ``divergences`` (each with ``recovered``: the segment it started lasted ``lag`` seconds
        without a further divergence), ``longest_without_vision_s`` and ``max_velocity_sigma_mps``."""
        if self.k >= 0 and self.k not in self.velocity_sigma:
            sigma = self._velocity_sigma(self.k)
            if sigma is not None:
                self.velocity_sigma[self.k] = sigma
        want_sigmas = self.opt.joint_sigmas and self.opt.mode == "dcc"
        if want_sigmas and self.k >= 0:
            self._joint_sigmas(leaving_only=False)
        res = result_from_states(self.estimates, self.opt.mode, self.stats, self.theta_sigma if want_sigmas else None)
        res.chain_theta = self.chains.result(sorted(self.estimates))
        if self.residuals is not None:
            names = {STATIC: "cam0", **{c: cam.name for c, cam in self.rig.extra.items()}}
            if self.cal is not None:
                names[GIMBAL] = self.cal.cluster().primary_gimbal_camera
            res.stats["residual_median_px"] = {names[c]: m for c, m in self.residuals.medians().items()}
            res.stats["observations_used_fraction"] = {names[c]: f for c, f in self.residuals.used_fractions().items()}
        res.stats.update(self.recovery_stats(res.timestamps_ns))
        res.stats["time_offsets"] = self.exposure.summary(self.window.smoother, gimbal=self.opt.mode != "mono")
        return res

    def recovery_stats(self, stamps: NDArray[np.int64]) -> dict[str, Any]:
        """The recovery record of :meth:`result` for the result's keyframe stamps (ns)."""
        segments = []
        for i, seg in enumerate(self.segments):
            end = self.segments[i + 1]["start_ns"] if i + 1 < len(self.segments) else None
            inside = stamps[(stamps >= seg["start_ns"]) & (end is None or stamps < end)]
            if inside.size == 0:
                continue
            segments.append(
                {
                    "start_ns": int(inside[0]),
                    "end_ns": int(inside[-1]),
                    "keyframes": int(inside.size),
                    "reason": seg["reason"],
                }
            )
        lag_ns = int(self.opt.window_s * NS)
        events = []
        for ev in self.divergences:
            seg = next((s for s in segments if s["start_ns"] == ev["t_ns"]), None)
            recovered = seg is not None and seg["end_ns"] - seg["start_ns"] >= lag_ns
            events.append({**ev, "recovered": bool(recovered)})
        sigmas = [v for v in self.velocity_sigma.values() if np.isfinite(v)]
        return {
            "segments": segments,
            "segment_count": len(segments),
            "divergences": events,
            "longest_without_vision_s": self.longest_without_vision_ns / NS,
            "max_velocity_sigma_mps": max(sigmas) if sigmas else None,
            "final_velocity_sigma_mps": self.velocity_sigma.get(self.k),
        }
