"""Exposure times of the smoother's camera images: the time-offset state and the exposure-time camera poses.

A keyframe sits at its static image's header stamp ``t_k`` read as IMU time. With the convention
``t_imu = t_cam_stamp + t_offset`` the static image was exposed ``t_s`` s and the gimbal image of the
same frame ``(t_stamp_d - t_k) + t_d`` s from the keyframe (an unsynchronized gimbal camera adds the
stamp gap). :class:`ExposureModel` gives each timed image an auxiliary camera pose (``s(k)``,
``c(k)``, keys in :mod:`.keys`) tied to the keyframe's pose, velocity, joint angles and the offsets
by :func:`factors.exposure.exposure_pose_factor`; the observations of that image are gtsam's C++
projection factors on the auxiliary pose.

The offsets ``[t_s, t_d]`` are one ``Vector 2`` variable ``o(0)`` for the whole run, anchored by a
prior (``time_offset_prior_sigma`` around the start values ``time_offsets``), timed with the newest
keyframe at every update so the fixed-lag smoother never marginalizes it; after a restart of the
window it is re-anchored at its estimate with its marginal sigma. With
``estimate_time_offsets=False`` they are constants. Once both offsets' 1-sigma fall below
``time_offset_freeze_sigma`` they are held at their estimate from then on (:meth:`ExposureModel.maybe_freeze`;
the auxiliary static pose then costs more than the offsets still gain). An image is *timed* (an
auxiliary pose) when its offset is estimated, or (gimbal) not zero or its stamp differs from the
keyframe's; a static image at a known non-zero offset projects from ``x(k)`` through a fixed mount per
keyframe (:meth:`ExposureModel.add_image`); untimed images keep the direct factors (static: on
``x(k)``; gimbal: :func:`factors.vio.gimbal_camera_pose_factor`), so a synchronized run without
offsets is exactly the same graph as before.

The body twist of a keyframe is its velocity and the gyro's mean rate over the exposure interval
(minus the gyro bias estimate at the keyframe's creation), a constant of the factor; the joints
move at the rate from the previous keyframe's estimate to this keyframe's starting value (a
constant too). Header stamps scattered around the exposure times (``stamp_jitter``, s, per camera)
loosen each tie along the camera's motion (:func:`factors.exposure.exposure_rate`): without it the
offsets' 1-sigma would count every image as exactly timed. Times: ns for stamps, s for offsets; rad, m.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np

from dcc_fg.data.vio import ImuSamples
from dcc_fg.vio.backend.keys import (
    camera_key,
    offsets_key,
    pose_key,
    static_camera_key,
    theta_key,
    velocity_key,
)
from dcc_fg.vio.backend.options import NS, FloatArray, VioOptions
from factors.exposure import CameraMount, ExposureKeys, exposure_pose, exposure_pose_factor, exposure_rate
from factors.vio import gimbal_camera_pose_factor

STATIC = 0
GIMBAL = 1
log = logging.getLogger(__name__)
#: Seconds of data between two convergence checks of :meth:`ExposureModel.maybe_freeze` (each needs the
#: offsets' marginal covariance: up to 0.1 s of ISAM2 work on a 60 s flight).
FREEZE_CHECK_PERIOD_S = 2.0
#: Stamp jitter below this (s) is the nanosecond rounding of regular stamps: treated as none.
MIN_JITTER_S = 1e-6
#: Smallest offset sigma (s) carried across a restart of the window.
MIN_RESTART_SIGMA_S = 1e-5


@dataclass(frozen=True)
class ImageTiming:
    """One timed image of keyframe k: stamp gap to the keyframe (s), body rate (rad/s in I) and the
    joint rate (rad/s, gimbal camera)."""

    stamp_gap_s: float
    omega_I: FloatArray
    theta_rate: FloatArray


def mean_gyro(imu: ImuSamples, t0_ns: int, t1_ns: int) -> FloatArray:
    """Mean gyro rate (rad/s) of the samples in [min, max] of the two times, or of the nearest sample."""
    a, b = min(t0_ns, t1_ns), max(t0_ns, t1_ns)
    i0 = int(np.searchsorted(imu.t_ns, a, side="left"))
    i1 = int(np.searchsorted(imu.t_ns, b, side="right"))
    if i1 > i0:
        return np.asarray(imu.gyro[i0:i1].mean(axis=0), float)
    i = int(np.clip(np.searchsorted(imu.t_ns, t0_ns), 0, len(imu) - 1))
    if i > 0 and abs(int(imu.t_ns[i - 1]) - t0_ns) < abs(int(imu.t_ns[i]) - t0_ns):
        i -= 1
    return np.asarray(imu.gyro[i], float)


class ExposureModel:
    """Offsets variable and exposure-time camera poses of one run (module docstring)."""

    def __init__(self, options: VioOptions, imu: ImuSamples, mounts: dict[int, CameraMount]) -> None:
        self.opt = options
        self.imu = imu
        self.mounts = mounts
        self.estimate = bool(options.estimate_time_offsets)
        self.active = self.estimate  # the offsets are a variable of the window (until frozen)
        self.offsets = np.asarray(options.offsets, float)
        self.sigma = np.full(2, options.time_offset_prior_sigma)
        self.timed: dict[int, dict[int, ImageTiming]] = {}
        self.shift: dict[tuple[int, int], gtsam.Pose3] = {}
        self.started_ns: int | None = None
        self.frozen_at_ns: int | None = None
        self.frozen_sigma: FloatArray | None = None
        self.last_check_ns: int | None = None
        jitter = np.zeros(2) if options.stamp_jitter is None else np.asarray(options.stamp_jitter, float)
        self.jitter = np.where(jitter < MIN_JITTER_S, 0.0, jitter)

    # ------------------------------------------------------------------ offsets variable
    def anchor(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict[int, int], t: int) -> None:
        """A (fresh) window: the offsets variable with its prior (start values, or the estimate and
        its marginal sigma after a restart)."""
        if self.started_ns is None:
            self.started_ns = t
        if not self.active:
            return
        values.insert(offsets_key, self.offsets.copy())
        graph.add(
            gtsam.PriorFactorVector(offsets_key, self.offsets.copy(), gtsam.noiseModel.Diagonal.Sigmas(self.sigma))
        )
        stamps[offsets_key] = t

    def touch(self, stamps: dict[int, int], t: int) -> None:
        """Keep the offsets in the window: time them with the newest keyframe."""
        if self.active:
            stamps[offsets_key] = t

    def refresh(self, estimate: gtsam.Values) -> None:
        if self.active and estimate.exists(offsets_key):
            self.offsets = np.asarray(estimate.atVector(offsets_key), float).copy()

    def marginal_sigma(self, smoother: object) -> FloatArray | None:
        """1-sigma (s) of the offsets from the window's marginal covariance (None if unavailable); after
        freezing, the 1-sigma they had then."""
        if not self.active:
            return self.frozen_sigma
        try:
            cov = np.asarray(smoother.marginalCovariance(offsets_key), float)  # type: ignore[attr-defined]
        except (RuntimeError, IndexError):  # indeterminant, or the key is not in a (failed) Bayes tree
            return None
        return np.sqrt(np.maximum(np.diag(cov), 0.0))

    def before_restart(self, smoother: object) -> None:
        """Carry the offsets' uncertainty into a restarted window."""
        sigma = self.marginal_sigma(smoother)
        if sigma is not None and np.all(np.isfinite(sigma)):
            self.sigma = np.clip(sigma, MIN_RESTART_SIGMA_S, self.opt.time_offset_prior_sigma)

    def maybe_freeze(self, smoother: object, t_ns: int) -> None:
        """Hold the offsets at their estimate once every used camera's 1-sigma is below
        ``time_offset_freeze_sigma`` (checked every :data:`FREEZE_CHECK_PERIOD_S` of data, at least one
        window ``lag`` after the start): from then on the images need no auxiliary static pose and the
        smoother runs at the cost of a run with known offsets."""
        limit = self.opt.time_offset_freeze_sigma
        if not self.active or limit is None or self.started_ns is None:
            return
        since = t_ns - (self.started_ns if self.last_check_ns is None else self.last_check_ns)
        if since < max(FREEZE_CHECK_PERIOD_S, self.opt.window_s) * NS:
            return
        self.last_check_ns = t_ns
        sigma = self.marginal_sigma(smoother)
        if sigma is None or not all(sigma[c] < limit for c in self.mounts):
            return
        self.active = False
        self.frozen_at_ns = t_ns
        self.frozen_sigma = sigma.copy()
        log.info(
            "time offsets %s ms (1-sigma %s ms) determined at t_ns %d: held from here on",
            np.round(1e3 * self.offsets, 3),
            np.round(1e3 * sigma, 4),
            t_ns,
        )

    # ------------------------------------------------------------------ images
    def static_timed(self) -> bool:
        """The static image is not at its keyframe's time (offset estimated or not zero)."""
        return self.active or self.offsets[STATIC] != 0.0

    def gimbal_timed(self, stamp_gap_s: float) -> bool:
        return self.active or self.offsets[GIMBAL] != 0.0 or stamp_gap_s != 0.0

    def is_timed(self, k: int, cam: int) -> bool:
        return cam in self.timed.get(k, {})

    def _body_rate(self, t_ns: int, delta_s: float, gyro_bias: FloatArray) -> FloatArray:
        """Mean bias-corrected gyro rate (rad/s in I) from a keyframe at ``t_ns`` to ``delta_s`` later."""
        return mean_gyro(self.imu, t_ns, t_ns + int(round(delta_s * NS))) - np.asarray(gyro_bias, float)

    def T_Wc(self, k: int, cam: int, T_WI: FloatArray, v_W: FloatArray, theta: FloatArray | None) -> FloatArray | None:
        """Exposure-time pose (camera -> W) of camera ``cam`` at keyframe k (auxiliary pose or constant
        per-keyframe mount), None if the image is at its keyframe's time."""
        shift = self.shift.get((k, cam))
        if shift is not None:
            return np.asarray(T_WI, float) @ shift.matrix()
        timing = self.timed.get(k, {}).get(cam)
        if timing is None:
            return None
        delta = timing.stamp_gap_s + float(self.offsets[cam])
        mount = self.mounts[cam]
        th = None
        if mount.on_gimbal:
            assert theta is not None
            th = np.asarray(theta, float) + delta * timing.theta_rate
        T_Ic, _ = mount(th)
        return exposure_pose(T_WI, v_W, timing.omega_I, delta, T_Ic)

    def body_pose_at(
        self,
        T_WI: FloatArray,
        v_W: FloatArray,
        t_ns: int,
        cam: int,
        stamp_gap_s: float,
        bias: gtsam.imuBias.ConstantBias,
    ) -> FloatArray:
        """Body pose (I -> W) at the exposure of camera ``cam``'s image ``stamp_gap_s`` after a keyframe at
        ``t_ns`` with pose ``T_WI`` and velocity ``v_W`` (current offsets, gyro minus ``bias``)."""
        delta = stamp_gap_s + float(self.offsets[cam])
        return exposure_pose(T_WI, v_W, self._body_rate(t_ns, delta, bias.gyroscope()), delta, np.eye(4))

    def add_image(
        self,
        k: int,
        cam: int,
        t_ns: int,
        stamp_gap_s: float,
        pose: gtsam.Pose3,
        velocity: FloatArray,
        gyro_bias: FloatArray,
        theta: FloatArray | None,
        previous: tuple[int, FloatArray] | None,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        stamps: dict[int, int],
    ) -> None:
        """Camera ``cam``'s image of keyframe k (time ``t_ns``) at its exposure time. Offsets estimated:
        an auxiliary pose, its start value and :func:`~factors.exposure.exposure_pose_factor`. Offsets
        known: a constant mount ``Exp(delta xi) T_Ic`` per keyframe (``xi`` from the predicted
        velocity; a velocity error ``dv`` moves it by ``delta dv``, 0.05 mm for 5 ms and 1 cm/s) for the
        C++ projection factors on ``x(k)``, or for a gimbal chain the auxiliary pose tied by
        :func:`~factors.vio.gimbal_camera_pose_factor` with that body motion. ``previous`` = (time ns,
        joint angles) of the previous keyframe of the segment (gimbal: the joint rate), or None."""
        delta0 = stamp_gap_s + float(self.offsets[cam])
        omega = self._body_rate(t_ns, delta0, gyro_bias)
        mount = self.mounts[cam]
        L = mount.n_joints
        rate = np.zeros(L)
        if mount.on_gimbal and previous is not None and theta is not None and t_ns > previous[0]:
            rate = (np.asarray(theta, float) - np.asarray(previous[1], float)) / ((t_ns - previous[0]) / NS)
        v_W = np.asarray(velocity, float)
        # offsets known: the body's motion from the keyframe to the exposure, from the predicted velocity
        M = (
            None
            if self.active
            else exposure_pose(np.eye(4), pose.rotation().matrix().T @ v_W, omega, delta0, np.eye(4))
        )
        if M is not None and not mount.on_gimbal:
            X, _, _ = mount.pose(None)
            self.shift[(k, cam)] = gtsam.Pose3(M @ X.matrix())
            return
        self.timed.setdefault(k, {})[cam] = ImageTiming(stamp_gap_s, omega, rate)
        key = static_camera_key(k) if cam == STATIC else camera_key(k)
        jitter = None
        if self.jitter[cam] > 0:
            th = None if theta is None or not mount.on_gimbal else np.asarray(theta, float) + delta0 * rate
            T_Ic, G = mount(th)
            u = exposure_rate(pose.matrix(), v_W, omega, T_Ic, G, rate)
            jitter = self.jitter[cam] * u
        T_Wc = self.T_Wc(k, cam, pose.matrix(), v_W, theta)
        assert T_Wc is not None
        values.insert(key, gtsam.Pose3(T_Wc))
        stamps[key] = t_ns
        sig = self.opt.camera_pose_sigma
        if M is not None:  # a gimbal chain at a known offset: the tie with a constant body motion
            assert mount.cache is not None and mount.T_sI is not None
            graph.add(gimbal_camera_pose_factor(pose_key(k), theta_key(k), key, mount.cache, mount.T_sI, sig, sig,
                                                M, delta0 * rate))  # fmt: skip
            return
        keys = ExposureKeys(
            pose_key(k),
            velocity_key(k),
            key,
            offsets_key,
            cam,
            theta_key(k) if mount.on_gimbal else None,
        )
        graph.add(
            exposure_pose_factor(keys, mount, stamp_gap_s, omega, float(self.offsets[cam]), rate, sig, sig, jitter)
        )

    def forget(self, before_k: int) -> None:
        """Drop the timing of keyframes before ``before_k`` (left the window, or lost in a failed update)."""
        for kk in [kk for kk in self.timed if kk < before_k]:
            del self.timed[kk]
        for kc in [kc for kc in self.shift if kc[0] < before_k]:
            del self.shift[kc]

    def summary(self, smoother: object, gimbal: bool) -> dict[str, object]:
        """``time_offsets`` block of the result: estimates and 1-sigma (s), the convention."""
        sigma = self.marginal_sigma(smoother)
        out: dict[str, object] = {
            "convention": "t_imu = t_cam_stamp + t_offset",
            "estimated": self.estimate,
            "held_from_ns": self.frozen_at_ns,
            "start_s": {"static": self.opt.offsets[0], "dynamic": self.opt.offsets[1]},
            "stamp_jitter_s": {"static": float(self.jitter[STATIC]), "dynamic": float(self.jitter[GIMBAL])},
            "static_s": float(self.offsets[STATIC]),
            "static_sigma_s": None if sigma is None else float(sigma[STATIC]),
        }
        if gimbal:
            out["dynamic_s"] = float(self.offsets[GIMBAL])
            out["dynamic_sigma_s"] = None if sigma is None else float(sigma[GIMBAL])
        return out
