"""The two cameras as the smoother sees them: their poses from the body state and their factors.

Camera 0 (:data:`STATIC`) is fixed to the body: ``T_sI`` maps IMU points into the static camera.
Camera 1 (:data:`GIMBAL`) sits on the gimbal: ``T_dI(theta) = T_ds(theta) T_sI``. Observations are
undistorted normalized coordinates (unit focal length), sigma in the same units.

Gimbal-camera factors by mode: ``dcc`` with ``gimbal_factor='camera_pose'`` projects onto an
auxiliary camera pose ``c(k)`` tied to ``x(k)`` and ``t(k)`` by
:func:`factors.vio.gimbal_camera_pose_factor`; ``dcc`` otherwise uses eq. 14
(:func:`factors.vio.gimbal_reprojection_factor`); ``scc`` projects with the locked extrinsic
``T_dI(theta_fixed)``. See ``docs/architecture.md`` for the frame conventions.
"""

from __future__ import annotations

import gtsam
import numpy as np

from dcc_fg.model import GimbalCalibration
from dcc_fg.vio.backend.keys import camera_key, landmark_key, pose_key, theta_key
from dcc_fg.vio.backend.options import FloatArray, VioOptions
from factors import chain
from factors.vio import ChainCache, ProjectionFactory, gimbal_camera_pose_factor, gimbal_reprojection_factor

STATIC = 0
GIMBAL = 1


class CameraRig:
    """Static and gimbal camera of one run: world poses and reprojection factors (module docstring)."""

    def __init__(self, calibration: GimbalCalibration | None, T_sI: FloatArray, options: VioOptions) -> None:
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

    def T_Wc(self, T_WI: FloatArray, cam: int, theta: FloatArray | None = None) -> FloatArray:
        """Pose (4x4, camera -> W) of camera ``cam`` for body pose ``T_WI`` and joint angles ``theta``
        (rad; needed for the gimbal camera only)."""
        if cam == STATIC:
            return T_WI @ chain.inv_se3(self.T_sI)
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
