"""Joint-angle handling of the smoother: the starting angles, the per-keyframe angle fit and the
direct joint-angle measurement prior.

Joint angles ``theta`` are in rad (L of them). The fit is stage one of the two-stage gimbal outlier
handling the paper proposes as future work: the angles of a new keyframe are first fitted (Huber,
no rejection) to the gimbal observations of known landmarks with the IMU-predicted body pose
``T_WI`` (body -> W); observations are then gated with the updated extrinsics ``T_dI(theta)``.
"""

from __future__ import annotations

import gtsam
import numpy as np

from dcc_fg.vio.backend.options import FloatArray, InitialState, VioOptions
from factors.calibration import RobustLoss
from factors.vio import gimbal_residuals


def start_joint_angles(initial: InitialState, options: VioOptions, n_joints: int) -> FloatArray:
    """Joint angles of the first keyframe: ``theta_fixed`` in ``scc``, else the initial state's
    (which must have ``n_joints`` of them in ``dcc``)."""
    theta0 = np.asarray(initial.theta, float).reshape(-1)
    if options.mode == "dcc" and theta0.shape[0] != n_joints:
        raise ValueError(f"initial theta must have {n_joints} joint angles")
    if options.mode == "scc":
        theta0 = np.asarray(options.theta_fixed, float)
    return theta0


def fit_joint_angles_to_landmarks(
    T_WI: FloatArray,
    p_W: FloatArray,
    z: FloatArray,
    theta0: FloatArray,
    prior_sigma: float,
    kin: FloatArray,
    T_sI: FloatArray,
    sigma: float,
    robust: RobustLoss,
) -> FloatArray:
    """Gauss-Newton (iteratively reweighted, ``robust`` weights) on the joint angles alone.

    Args:
        T_WI: body pose (4x4, body -> W), held fixed.
        p_W: (N, 3) landmark positions in W (m), held fixed.
        z: (N, 2) their normalized gimbal-camera observations.
        theta0: starting angles (rad), also the mean of a prior with ``prior_sigma`` (rad).
        kin: the gimbal chain's kinematic parameters; ``T_sI`` IMU -> static camera.
        sigma: standard deviation of a normalized coordinate.
        robust: the loss whose weights down-weight outliers.

    Returns:
        the fitted angles; ``theta0`` (a copy) with fewer than 3 observations.
    """
    L = theta0.shape[0]
    if len(z) < 3:
        return theta0.copy()
    theta = theta0.copy()
    for _ in range(10):  # iteratively reweighted least squares with Huber weights
        res = gimbal_residuals(T_WI, p_W, theta, kin, L, T_sI, z)
        assert res.d_theta is not None
        r = res.r / sigma
        _, w = robust.rho(np.sum(r * r, axis=1))
        sw = np.sqrt(w)[:, None]
        A = (res.d_theta / sigma * sw[:, :, None]).reshape(-1, L)
        b = (r * sw).reshape(-1)
        H = A.T @ A + np.eye(L) / prior_sigma**2
        g = A.T @ b + (theta - theta0) / prior_sigma**2
        step = -np.linalg.solve(H, g)
        theta = theta + step
        if np.max(np.abs(step)) < 1e-7:
            break
    return theta


def joint_measurement_prior(
    key: int, measurement: tuple[FloatArray, FloatArray], n_joints: int, inflation: float
) -> tuple[FloatArray, gtsam.PriorFactorVector] | None:
    """A direct joint-angle measurement (theta (L,) rad, covariance (L, L) rad^2) as a starting
    value and a prior on ``key`` with the covariance inflated by ``inflation``; None if its shapes
    do not match ``n_joints`` or the covariance is not finite."""
    th_m, cov_m = (np.asarray(x, float) for x in measurement)
    if th_m.shape != (n_joints,) or cov_m.shape != (n_joints, n_joints) or not np.all(np.isfinite(cov_m)):
        return None
    cov = cov_m * inflation**2 + np.eye(n_joints) * 1e-10
    return th_m.copy(), gtsam.PriorFactorVector(key, th_m, gtsam.noiseModel.Gaussian.Covariance(cov))
