"""Reprojection factors of the VIO smoother, including the gimbal-camera factor of the paper's eq. 14.

Frames (docs/architecture.md): ``W`` world, ``I`` IMU/body, ``s`` static camera, ``d`` gimbal camera.
Measurements are *undistorted normalized* image coordinates ``z = (x/z, y/z)`` (unitless);
``sigma`` is their standard deviation (pixel sigma / focal length).

Gimbal camera (paper eq. 14): with ``T_dI(theta) = T_ds(theta) T_sI`` (eq. 13),
``e = pi(T_ds(theta) T_sI T_WI^-1 p_W) - z``, ``pi(p) = (p_x / p_z, p_y / p_z)``.
Jacobians (right perturbation of the pose, gtsam's convention ``T_WI Exp([omega, v])``):

* ``p_I = R_WI^T (p_W - t_WI)``: ``d p_I / d omega = [p_I]_x``, ``d p_I / d v = -I``,
  ``d p_I / d p_W = R_WI^T``;
* ``p_d = T_ds(theta) (R_sI p_I + t_sI)``: ``d p_d / d p_I = R_ds R_sI``; ``d p_d / d theta`` is the
  chain's analytic joint-angle Jacobian (eq. 15, :func:`factors.chain.transform_points`);
* ``d pi / d p = [[1/z, 0, -x/z^2], [0, 1/z, -y/z^2]]``.

The static camera, and the gimbal camera locked at known angles, use gtsam's C++
``GenericProjectionFactorCal3_S2`` with identity intrinsics and ``body_P_sensor`` = the inverse
camera extrinsic (:func:`static_projection_factor`); :func:`gimbal_residuals` with ``kin=None`` is
the same model in numpy and both are tested against each other.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors import chain

FloatArray = NDArray[np.float64]
MIN_DEPTH = 1e-6


@dataclass(frozen=True)
class GimbalResiduals:
    """Residuals (N, 2) and Jacobians w.r.t. the pose (N, 2, 6), landmarks (N, 2, 3), joints (N, 2, L)."""

    r: FloatArray
    d_pose: FloatArray | None
    d_point: FloatArray | None
    d_theta: FloatArray | None
    depth: FloatArray


def _project(p: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Normalized projection of (N, 3) points, its (N, 2, 3) Jacobian and the depths."""
    z = np.maximum(p[:, 2], MIN_DEPTH)
    iz = 1.0 / z
    xy = p[:, :2] * iz[:, None]
    J = np.zeros((p.shape[0], 2, 3))
    J[:, 0, 0] = iz
    J[:, 1, 1] = iz
    J[:, 0, 2] = -xy[:, 0] * iz
    J[:, 1, 2] = -xy[:, 1] * iz
    return xy, J, p[:, 2]


def gimbal_residuals(
    T_WI: FloatArray,
    p_W: FloatArray,
    theta: FloatArray | None,
    kin: FloatArray | None,
    n_joints: int,
    T_sI: FloatArray,
    z: FloatArray,
    jacobians: bool = True,
) -> GimbalResiduals:
    """Residuals of eq. 14 for N landmarks ``p_W`` (N, 3) seen at ``z`` (N, 2) from body pose ``T_WI``.

    ``kin=None`` means the static camera (``T_ds = I``, no joint Jacobian).
    """
    p_W = np.asarray(p_W, float).reshape(-1, 3)
    R_WI, t_WI = T_WI[:3, :3], T_WI[:3, 3]
    p_I = (p_W - t_WI) @ R_WI
    p_s = p_I @ T_sI[:3, :3].T + T_sI[:3, 3]
    if kin is None:
        p_c, Jc = p_s, None
        R_cs = np.eye(3)
    else:
        p_c, Jc = chain.transform_points(kin, np.asarray(theta, float), p_s, n_joints, jacobians)
        R_cs = chain.T_ds(kin, np.asarray(theta, float), n_joints)[:3, :3]
    xy, Jpi, depth = _project(p_c)
    r = xy - z
    if not jacobians:
        return GimbalResiduals(r, None, None, None, depth)
    R_cI = R_cs @ T_sI[:3, :3]
    J_cI = np.einsum("nij,jk->nik", Jpi, R_cI)  # d e / d p_I
    n = p_W.shape[0]
    d_pose = np.empty((n, 2, 6))
    skew = np.zeros((n, 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -p_I[:, 2], p_I[:, 1], -p_I[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = p_I[:, 2], -p_I[:, 1], p_I[:, 0]
    d_pose[:, :, :3] = np.einsum("nij,njk->nik", J_cI, skew)
    d_pose[:, :, 3:] = -J_cI
    d_point = J_cI @ R_WI.T
    d_theta = None if Jc is None else np.einsum("nij,njk->nik", Jpi, Jc.d_theta)
    return GimbalResiduals(r, d_pose, d_point, d_theta, depth)


class ChainCache:
    """Memo of ``T_ds(theta)`` and its tangent Jacobian for recently seen joint angles.

    Every gimbal observation of a keyframe shares the keyframe's joint angles, so the chain and
    its derivative are computed once per linearization point instead of once per observation.
    """

    def __init__(self, kin: FloatArray, n_joints: int, maxsize: int = 512) -> None:
        self.kin = np.asarray(kin, float)
        self.L = n_joints
        self.maxsize = maxsize
        self._memo: dict[bytes, tuple[FloatArray, FloatArray]] = {}

    def get(self, theta: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``(T_ds (4, 4), J (6, L))`` with ``T_ds(theta + d) ~= T_ds(theta) Exp(J d)``."""
        theta = np.asarray(theta, float)
        key = theta.tobytes()
        hit = self._memo.get(key)
        if hit is None:
            if len(self._memo) >= self.maxsize:
                self._memo.clear()
            T = chain.T_ds(self.kin, theta, self.L)
            _, J = chain.d_T_ds_tangent(self.kin, theta, self.L)
            hit = (T, J)
            self._memo[key] = hit
        return hit


def _noise(sigma: float, huber_k: float | None) -> gtsam.noiseModel.Base:
    noise: gtsam.noiseModel.Base = gtsam.noiseModel.Isotropic.Sigma(2, sigma)
    if huber_k is not None:
        noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(huber_k), noise)
    return noise


def gimbal_reprojection_factor(
    z: FloatArray,
    sigma: float,
    pose_key: int,
    landmark_key: int,
    theta_key: int,
    cache: ChainCache,
    T_sI: FloatArray,
    huber_k: float | None = None,
) -> gtsam.CustomFactor:
    """Eq. 14 for one gimbal-camera observation ``z`` (normalized), keys ``[pose (Pose3 T_WI),
    landmark (Point3 p_W), theta (Vector L)]``, whitened by ``sigma`` with an optional Huber loss.

    The joint-angle Jacobian (eq. 15) is ``d pi/d p_d R_ds (-[p_s]_x J_omega + J_v)`` with
    ``J = [J_omega; J_v]`` the tangent Jacobian of ``T_ds`` from :func:`factors.chain.d_T_ds_tangent`.
    """
    z = np.asarray(z, float).reshape(2)
    R_sI = np.asarray(T_sI, float)[:3, :3].copy()
    t_sI = np.asarray(T_sI, float)[:3, 3].copy()

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[FloatArray] | None) -> FloatArray:
        T = values.atPose3(pose_key).matrix()
        p_W = values.atPoint3(landmark_key)
        T_ds, J_th = cache.get(values.atVector(theta_key))
        R = T[:3, :3]
        p_I = R.T @ (p_W - T[:3, 3])
        p_s = R_sI @ p_I + t_sI
        R_ds = T_ds[:3, :3]
        p_d = R_ds @ p_s + T_ds[:3, 3]
        zd = p_d[2] if p_d[2] > MIN_DEPTH else MIN_DEPTH
        x, y = p_d[0] / zd, p_d[1] / zd
        if H is not None:
            Jpi = np.array([[1.0 / zd, 0.0, -x / zd], [0.0, 1.0 / zd, -y / zd]])
            A = Jpi @ R_ds
            J_I = A @ R_sI
            H[0] = np.hstack([J_I @ chain.skew(p_I), -J_I])
            H[1] = J_I @ R.T
            H[2] = A @ (J_th[3:] - chain.skew(p_s) @ J_th[:3])
        return np.array([x - z[0], y - z[1]])

    return gtsam.CustomFactor(_noise(sigma, huber_k), [pose_key, landmark_key, theta_key], error)


def gimbal_camera_pose_factor(
    pose_key: int,
    theta_key: int,
    camera_key: int,
    cache: ChainCache,
    T_sI: FloatArray,
    sigma_rotation: float = 1e-5,
    sigma_translation: float = 1e-5,
    body_motion: FloatArray | None = None,
    theta_shift: FloatArray | None = None,
) -> gtsam.CustomFactor:
    """Ties an auxiliary gimbal-camera pose ``T_Wd`` to the body pose and joint angles (eq. 13).

    ``e = Log((T_WI T_dI(theta)^-1)^-1 T_Wd)`` (rad, m) with a tight noise: gimbal observations can
    then be gtsam's C++ projection factors on ``T_Wd``, and eq. 14 is their composition with this
    constraint (one Python callback per keyframe instead of one per observation). Keys
    ``[pose (Pose3 T_WI), theta (Vector L), camera (Pose3 T_Wd)]``. Jacobians, with ``D = C^-1 T_Wd``,
    ``C = T_WI T_Id``: ``d e/d T_Wd = J_r^-1(e)``, ``d e/d T_WI = -J_r^-1(e) Ad(D^-1) Ad(T_dI)``,
    ``d e/d theta = J_r^-1(e) Ad(D^-1) Ad(T_ds) J_theta`` (``J_theta`` the tangent Jacobian of T_ds).

    An image exposed at a known time ``delta`` from the keyframe (:mod:`factors.exposure` with fixed
    offsets) gives the constants ``body_motion`` ``M`` (4x4, the body's motion over ``delta``) and
    ``theta_shift`` (the joints' motion, rad): ``C = T_WI M T_Id(theta + theta_shift)``, and the pose
    Jacobian becomes ``-J_r^-1(e) Ad(D^-1) Ad(T_dI) Ad(M^-1)``.
    """
    T_sI = np.asarray(T_sI, float)
    M = None if body_motion is None else gtsam.Pose3(np.asarray(body_motion, float))
    Ad_Minv = None if M is None else M.inverse().AdjointMap()
    shift = None if theta_shift is None else np.asarray(theta_shift, float)
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, sigma_rotation), np.full(3, sigma_translation)])

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[FloatArray] | None) -> FloatArray:
        T_WI = values.atPose3(pose_key)
        T_Wd = values.atPose3(camera_key)
        theta = values.atVector(theta_key)
        T_ds, J_th = cache.get(theta if shift is None else theta + shift)
        T_dI = gtsam.Pose3(T_ds @ T_sI)
        C = T_WI.compose(T_dI.inverse()) if M is None else T_WI.compose(M).compose(T_dI.inverse())
        D = C.between(T_Wd)
        e = gtsam.Pose3.Logmap(D)
        if H is not None:
            Jl = gtsam.Pose3.LogmapDerivative(e)
            Ad = Jl @ D.inverse().AdjointMap()
            H[0] = -Ad @ T_dI.AdjointMap() if Ad_Minv is None else -Ad @ T_dI.AdjointMap() @ Ad_Minv
            H[1] = Ad @ gtsam.Pose3(T_ds).AdjointMap() @ J_th
            H[2] = Jl
        return e

    return gtsam.CustomFactor(noise, [pose_key, theta_key, camera_key], error)


def static_projection_factor(
    z: FloatArray, sigma: float, pose_key: int, landmark_key: int, T_sI: FloatArray, huber_k: float | None = None
) -> gtsam.GenericProjectionFactorCal3_S2:
    """gtsam's C++ projection factor on normalized coordinates (identity intrinsics, ``body_P_sensor = T_Is``)."""
    noise = _noise(sigma, huber_k)
    T_Is = gtsam.Pose3(chain.inv_se3(np.asarray(T_sI, float)))
    K = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)
    return gtsam.GenericProjectionFactorCal3_S2(
        np.asarray(z, float).reshape(2), noise, pose_key, landmark_key, K, False, False, T_Is
    )


class ProjectionFactory:
    """Builds :func:`static_projection_factor`-equivalent factors for one camera mount with the noise
    model, intrinsics and ``body_P_sensor`` created once (the smoother makes thousands per second)."""

    def __init__(self, sigma: float, T_cI: FloatArray, huber_k: float | None = None) -> None:
        self.noise = _noise(sigma, huber_k)
        self.K = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)
        self.body_P_sensor = gtsam.Pose3(chain.inv_se3(np.asarray(T_cI, float)))

    def __call__(self, z: FloatArray, pose_key: int, landmark_key: int) -> gtsam.GenericProjectionFactorCal3_S2:
        return gtsam.GenericProjectionFactorCal3_S2(
            np.asarray(z, float).reshape(2),
            self.noise,
            pose_key,
            landmark_key,
            self.K,
            False,
            False,
            self.body_P_sensor,
        )


def joint_random_walk_factor(key_i: int, key_j: int, n_joints: int, sigma: float) -> gtsam.BetweenFactorVector:
    """``theta_j - theta_i ~ N(0, sigma^2 I)`` (rad): the joint-angle random walk between keyframes."""
    return gtsam.BetweenFactorVector(
        key_i, key_j, np.zeros(n_joints), gtsam.noiseModel.Isotropic.Sigma(n_joints, sigma)
    )
