"""Reprojection factors of the VIO smoother, including the gimbal-camera factor of the paper's eq. 14.

Frames (ARCHITECTURE.md): ``W`` world, ``I`` IMU/body, ``s`` static camera, ``d`` gimbal camera.
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

The static camera uses the same expression with ``T_ds = I`` (or gtsam's C++
``GenericProjectionFactorCal3_S2`` with identity intrinsics and ``body_P_sensor = T_Is``, which is
what the smoother uses for speed; both are tested against each other).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors import chain
from factors.calibration import RobustLoss

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


def _whiten(
    r: FloatArray, blocks: list[FloatArray], sigma: float, robust: RobustLoss | None
) -> tuple[FloatArray, list[FloatArray]]:
    r = r / sigma
    blocks = [b / sigma for b in blocks]
    if robust is None:
        return r, blocks
    if not blocks:
        return r * robust.scale(r)[:, None], blocks
    widths = [b.shape[2] for b in blocks]
    r2, J2 = robust.apply(r, np.concatenate(blocks, axis=2))
    return r2, np.split(J2, np.cumsum(widths)[:-1], axis=2)


def gimbal_batch_factor(
    z: FloatArray,
    sigma: float,
    pose_key: int,
    landmark_keys: list[int],
    theta_key: int | None,
    kin: FloatArray,
    n_joints: int,
    T_sI: FloatArray,
    theta_const: FloatArray | None = None,
    robust: RobustLoss | None = None,
) -> gtsam.CustomFactor:
    """Eq. 14 for N observations of one gimbal-camera frame, keys ``[pose, theta?, landmark_1..N]``.

    One factor per frame keeps Python callbacks few; the residual is the stacked whitened
    2N-vector (robust loss per observation, exact Jacobian). ``theta_key=None`` holds the joints
    at ``theta_const`` (gimbal locked at known angles, the scc mode).
    """
    z = np.asarray(z, float).reshape(-1, 2)
    if z.shape[0] != len(landmark_keys):
        raise ValueError("one measurement per landmark key is needed")
    if theta_key is None and theta_const is None:
        raise ValueError("either theta_key or theta_const is needed")
    kin = np.asarray(kin, float)
    T_sI = np.asarray(T_sI, float)
    keys = [pose_key] + ([theta_key] if theta_key is not None else []) + list(landmark_keys)
    n = z.shape[0]

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[FloatArray] | None) -> FloatArray:
        T = values.atPose3(pose_key).matrix()
        theta = values.atVector(theta_key) if theta_key is not None else theta_const
        p_W = np.array([values.atPoint3(k) for k in landmark_keys]).reshape(n, 3)
        res = gimbal_residuals(T, p_W, theta, kin, n_joints, T_sI, z, H is not None)
        if H is None:
            r, _ = _whiten(res.r, [], sigma, robust)
            return r.ravel()
        assert res.d_pose is not None and res.d_point is not None and res.d_theta is not None
        blocks = [res.d_pose] + ([res.d_theta] if theta_key is not None else []) + [res.d_point]
        r, (Jp, *rest) = _whiten(res.r, blocks, sigma, robust)
        H[0] = Jp.reshape(2 * n, 6)
        pos = 1
        if theta_key is not None:
            H[1] = rest[0].reshape(2 * n, n_joints)
            pos = 2
        Jl = rest[-1]
        for i in range(n):
            block = np.zeros((2 * n, 3))
            block[2 * i : 2 * i + 2] = Jl[i]
            H[pos + i] = block
        return r.ravel()

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(2 * n), keys, error)


def gimbal_reprojection_factor(
    z: FloatArray,
    sigma: float,
    pose_key: int,
    landmark_key: int,
    theta_key: int,
    kin: FloatArray,
    n_joints: int,
    T_sI: FloatArray,
    robust: RobustLoss | None = None,
) -> gtsam.CustomFactor:
    """Eq. 14 for one observation, keys ``[pose (Pose3 T_WI), theta (Vector L), landmark (Point3 p_W)]``."""
    f = gimbal_batch_factor(
        np.asarray(z).reshape(1, 2), sigma, pose_key, [landmark_key], theta_key, kin, n_joints, T_sI, robust=robust
    )
    return f


def static_batch_factor(
    z: FloatArray,
    sigma: float,
    pose_key: int,
    landmark_keys: list[int],
    T_sI: FloatArray,
    robust: RobustLoss | None = None,
) -> gtsam.CustomFactor:
    """Static-camera reprojection of N observations of one frame, keys ``[pose, landmark_1..N]`` (numpy)."""
    z = np.asarray(z, float).reshape(-1, 2)
    T_sI = np.asarray(T_sI, float)
    n = z.shape[0]

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[FloatArray] | None) -> FloatArray:
        T = values.atPose3(pose_key).matrix()
        p_W = np.array([values.atPoint3(k) for k in landmark_keys]).reshape(n, 3)
        res = gimbal_residuals(T, p_W, None, None, 0, T_sI, z, H is not None)
        if H is None:
            r, _ = _whiten(res.r, [], sigma, robust)
            return r.ravel()
        assert res.d_pose is not None and res.d_point is not None
        r, (Jp, Jl) = _whiten(res.r, [res.d_pose, res.d_point], sigma, robust)
        H[0] = Jp.reshape(2 * n, 6)
        for i in range(n):
            block = np.zeros((2 * n, 3))
            block[2 * i : 2 * i + 2] = Jl[i]
            H[1 + i] = block
        return r.ravel()

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(2 * n), [pose_key] + list(landmark_keys), error)


def static_projection_factor(
    z: FloatArray, sigma: float, pose_key: int, landmark_key: int, T_sI: FloatArray, huber_k: float | None = None
) -> gtsam.GenericProjectionFactorCal3_S2:
    """gtsam's C++ projection factor on normalized coordinates (identity intrinsics, ``body_P_sensor = T_Is``)."""
    noise: gtsam.noiseModel.Base = gtsam.noiseModel.Isotropic.Sigma(2, sigma)
    if huber_k is not None:
        noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(huber_k), noise)
    T_Is = gtsam.Pose3(chain.inv_se3(np.asarray(T_sI, float)))
    K = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)
    return gtsam.GenericProjectionFactorCal3_S2(
        np.asarray(z, float).reshape(2), noise, pose_key, landmark_key, K, False, False, T_Is
    )


def joint_random_walk_factor(key_i: int, key_j: int, n_joints: int, sigma: float) -> gtsam.BetweenFactorVector:
    """``theta_j - theta_i ~ N(0, sigma^2 I)`` (rad): the joint-angle random walk between keyframes."""
    return gtsam.BetweenFactorVector(
        key_i, key_j, np.zeros(n_joints), gtsam.noiseModel.Isotropic.Sigma(n_joints, sigma)
    )
