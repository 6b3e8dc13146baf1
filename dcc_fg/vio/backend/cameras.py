"""The two cameras as the smoother sees them: their poses from the body state and their factors.

Camera 0 (:data:`STATIC`) is fixed to the body: ``T_sI`` maps IMU points into the static camera.
Camera 1 (:data:`GIMBAL`) sits on the gimbal: ``T_dI(theta) = T_ds(theta) T_sI``. Observations are
undistorted normalized coordinates (unit focal length), sigma in the same units.

Gimbal-camera factors by mode: ``dcc`` with ``gimbal_factor='camera_pose'`` projects onto an
auxiliary camera pose ``c(k)`` tied to ``x(k)`` and ``t(k)`` by
:func:`factors.vio.gimbal_camera_pose_factor`; ``dcc`` otherwise uses eq. 14
(:func:`factors.vio.gimbal_reprojection_factor`); ``scc`` projects with the locked extrinsic
``T_dI(theta_fixed)``. See ``docs/architecture.md`` for the frame conventions.

Further cameras of an N-camera cluster (run index >= 2, :class:`~dcc_fg.data.cameras.RunCamera`) are
exposed with the static image, so they project through the static camera's pose at that exposure: onto
the static camera's exposure-time pose ``s(k)`` when that image is timed, through its per-keyframe shifted
mount when the offsets are known, else onto ``x(k)``. A *rigid* camera (``T_cs`` constant) uses the C++
projection factor with the mount ``T_cs`` (``T_cs T_sI`` on ``x(k)``). A camera on the primary chain
shares ``t(k)``: its observations are C++ projection factors on its own auxiliary pose ``e(k)``
(:func:`~.keys.extra_camera_key`), tied once per keyframe to the static camera's pose at the exposure
(``x(k)`` through ``T_sI``, ``s(k)``, or ``x(k)`` through the shifted mount) and ``t(k)`` by eq. 13 with its
own chain parameters (its own ``tau_d``), like the gimbal camera's ``c(k)``; with
``gimbal_factor='eq14'`` they are eq. 14 factors instead.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import gtsam
import numpy as np

from dcc_fg.data.cameras import RunCamera
from dcc_fg.model import GimbalCalibration
from dcc_fg.vio.backend.keys import (
    camera_key,
    chain_theta_key,
    extra_camera_key,
    landmark_key,
    pose_key,
    static_camera_key,
    theta_key,
)
from dcc_fg.vio.backend.options import FloatArray, VioOptions
from factors import chain
from factors.vio import ChainCache, ProjectionFactory, gimbal_camera_pose_factor, gimbal_reprojection_factor

STATIC = 0
GIMBAL = 1


class CameraRig:
    """Static and gimbal camera of one run: world poses and reprojection factors (module docstring)."""

    def __init__(
        self,
        calibration: GimbalCalibration | None,
        T_sI: FloatArray,
        options: VioOptions,
        extra: Sequence[RunCamera] = (),
    ) -> None:
        self.cal = calibration
        self.opt = options
        self.T_sI = T_sI
        self.L = calibration.n_joints if calibration is not None else 0
        self.chain_cache = ChainCache(calibration.kin, self.L) if calibration is not None else None
        self.project_static = ProjectionFactory(options.sigma, T_sI, options.robust_k)
        self.project_camera = ProjectionFactory(options.sigma, np.eye(4), options.robust_k)
        self.T_dI_fixed = np.eye(4)
        if options.mode == "scc":
            assert calibration is not None and options.theta_fixed is not None
            self.T_dI_fixed = calibration.T_ds(np.asarray(options.theta_fixed, float)) @ T_sI
        self.project_locked = ProjectionFactory(options.sigma, self.T_dI_fixed, options.robust_k)
        self.extra = {c.index: c for c in extra}
        self._extra_body: dict[int, ProjectionFactory] = {}  # rigid: on x(k) through T_cI
        self._extra_static: dict[int, ProjectionFactory] = {}  # rigid: on s(k) through T_cs
        self._extra_chain: dict[int, ChainCache] = {}  # primary chain: its own tau_d
        for c in extra:
            if c.on_gimbal:
                if options.mode != "dcc":
                    raise ValueError(f"camera {c.name} is on a gimbal chain: it needs dcc mode")
                assert c.kin is not None
                self._extra_chain[c.index] = ChainCache(c.kin, c.n_joints)
            else:
                self._extra_body[c.index] = ProjectionFactory(options.sigma, c.T_cI(T_sI), options.robust_k)
                self._extra_static[c.index] = ProjectionFactory(options.sigma, c.T_cs_at(), options.robust_k)

    @property
    def has_camera_poses(self) -> bool:
        """Whether keyframes get auxiliary poses ``e(k)`` of further cameras (chain cameras, ``camera_pose``)."""
        return self.opt.gimbal_factor == "camera_pose" and bool(self._extra_chain)

    def is_rigid(self, cam: int) -> bool:
        """Whether camera ``cam`` (run index) is rigid to the body: cam0, and further rigid cameras."""
        return cam == STATIC or (cam in self.extra and not self.extra[cam].on_gimbal)

    def T_Wc(self, T_WI: FloatArray, cam: int, theta: FloatArray | None = None) -> FloatArray:
        """Pose (4x4, camera -> W) of camera ``cam`` for body pose ``T_WI`` and joint angles ``theta``
        (rad; needed for the gimbal camera only)."""
        if cam == STATIC:
            return T_WI @ chain.inv_se3(self.T_sI)
        if cam in self.extra:
            return T_WI @ chain.inv_se3(self.extra[cam].T_cI(self.T_sI, theta))
        assert self.cal is not None and theta is not None
        return T_WI @ chain.inv_se3(self.cal.T_ds(theta) @ self.T_sI)

    def observation_factor(self, k: int, cam: int, lm: int, z: FloatArray) -> gtsam.NonlinearFactor:
        """Reprojection factor of landmark ``lm`` seen at ``z`` by camera ``cam`` at keyframe ``k``."""
        o = self.opt
        if cam == STATIC:
            return self.project_static(z, pose_key(k), landmark_key(lm))
        if o.mode == "dcc" and o.gimbal_factor == "camera_pose":
            return self.project_camera(z, camera_key(k), landmark_key(lm))
        if o.mode == "dcc":
            assert self.chain_cache is not None
            return gimbal_reprojection_factor(
                z, o.sigma, pose_key(k), landmark_key(lm), theta_key(k), self.chain_cache, self.T_sI, o.robust_k
            )
        return self.project_locked(z, pose_key(k), landmark_key(lm))

    def extra_factor(
        self,
        k: int,
        cam: int,
        lm: int,
        z: FloatArray,
        static_timed: bool,
        static_shift: gtsam.Pose3 | None,
    ) -> gtsam.NonlinearFactor:
        """Reprojection factor of landmark ``lm`` seen at ``z`` by further camera ``cam`` (run index >= 2)
        at keyframe ``k`` (module docstring). ``static_timed``: the static image has an exposure-time pose
        ``s(k)``; ``static_shift``: else its per-keyframe shifted mount ``T_Is`` (or None)."""
        o = self.opt
        if cam in self._extra_body:
            if static_timed:
                return self._extra_static[cam](z, static_camera_key(k), landmark_key(lm))
            if static_shift is not None:
                T_Ic = static_shift.compose(gtsam.Pose3(chain.inv_se3(self.extra[cam].T_cs_at())))
                return self.project_shifted(z, pose_key(k), landmark_key(lm), T_Ic)
            return self._extra_body[cam](z, pose_key(k), landmark_key(lm))
        if o.gimbal_factor == "camera_pose":
            return self.project_camera(z, extra_camera_key(k, cam), landmark_key(lm))
        key, T_sX = self._static_exposure(k, static_timed, static_shift)
        return gimbal_reprojection_factor(
            z, o.sigma, key, landmark_key(lm), self.theta_key(k, cam), self._extra_chain[cam], T_sX, o.robust_k
        )

    def theta_key(self, k: int, cam: int) -> int:
        """The joint-angle variable further camera ``cam`` follows at keyframe ``k``: ``t(k)`` on the primary
        chain, ``u(64 k + slot)`` on a further chain (:mod:`.chains`)."""
        slot = self.extra[cam].slot
        return theta_key(k) if slot == 0 else chain_theta_key(k, slot)

    def _static_exposure(self, k: int, static_timed: bool, static_shift: gtsam.Pose3 | None) -> tuple[int, FloatArray]:
        """The variable holding the static camera's pose at its exposure in keyframe ``k`` and the transform
        from that variable's frame into s: ``s(k)`` and I, ``x(k)`` and the inverse shifted mount, or
        ``x(k)`` and ``T_sI``."""
        if static_timed:
            return static_camera_key(k), np.eye(4)
        if static_shift is not None:
            return pose_key(k), chain.inv_se3(static_shift.matrix())
        return pose_key(k), self.T_sI

    def add_extra_camera_poses(
        self,
        k: int,
        t_ns: int,
        T_Ws: FloatArray,
        theta_of: Callable[[int], FloatArray],
        static_timed: bool,
        static_shift: gtsam.Pose3 | None,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        stamps: dict[int, int],
    ) -> None:
        """dcc with ``gimbal_factor='camera_pose'``: the auxiliary pose ``e(k)`` = ``T_Wc`` of every further
        camera on a gimbal chain at keyframe ``k`` (start value from the static camera's pose ``T_Ws`` at
        the exposure and its chain's angles ``theta_of(slot)``) and its eq. 13 tie to the static camera's
        pose and the chain's joint angles (:meth:`theta_key`)."""
        if not self.has_camera_poses:
            return
        key, T_sX = self._static_exposure(k, static_timed, static_shift)
        sig = self.opt.camera_pose_sigma
        for cam, cache in self._extra_chain.items():
            e = extra_camera_key(k, cam)
            theta = theta_of(self.extra[cam].slot)
            values.insert(e, gtsam.Pose3(T_Ws @ chain.inv_se3(self.extra[cam].T_cs_at(theta))))
            stamps[e] = t_ns
            graph.add(gimbal_camera_pose_factor(key, self.theta_key(k, cam), e, cache, T_sX, sig, sig))

    def project_shifted(self, z: FloatArray, pose_k: int, landmark: int, T_Ic: gtsam.Pose3) -> gtsam.NonlinearFactor:
        """Projection factor on the body pose ``x(k)`` through a per-keyframe mount ``T_Ic`` (a camera with a
        constant mount at its exposure time relative to the keyframe, :mod:`.exposure`)."""
        f = self.project_static
        return gtsam.GenericProjectionFactorCal3_S2(
            np.asarray(z, float).reshape(2), f.noise, pose_k, landmark, f.K, False, False, T_Ic
        )

    def add_gimbal_camera_pose(
        self,
        k: int,
        t_ns: int,
        pose: gtsam.Pose3,
        theta: FloatArray,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        stamps: dict[int, int],
    ) -> None:
        """dcc with ``gimbal_factor='camera_pose'``: the auxiliary gimbal-camera pose ``T_Wd`` of
        keyframe ``k`` (initial value from ``pose`` and ``theta``) and its tie to x(k), t(k)."""
        if self.opt.gimbal_factor != "camera_pose":
            return
        assert self.cal is not None and self.chain_cache is not None
        T_Wd = pose.compose(gtsam.Pose3(self.cal.T_ds(theta) @ self.T_sI).inverse())
        values.insert(camera_key(k), T_Wd)
        stamps[camera_key(k)] = t_ns
        sig = self.opt.camera_pose_sigma
        graph.add(
            gimbal_camera_pose_factor(pose_key(k), theta_key(k), camera_key(k), self.chain_cache, self.T_sI, sig, sig)
        )
