"""Joint angles of one frame from static <-> gimbal correspondences (VIO start-up without encoders).

A pair of normalized image points ``x_s`` (static camera s) and ``x_d`` (gimbal camera d) of the
same scene point satisfies the epipolar constraint ``x_d^T E(theta) x_s = 0`` with
``E(theta) = [t_ds(theta)]x R_ds(theta)`` from the calibrated chain ``T_ds(theta)`` (paper eq. 5).
The joint angles ``theta`` (L,) are the minimizer of the Huber-weighted Sampson errors of all pairs;
no depth is needed.  Gauss-Newton with a central-difference Jacobian over the L angles (L is 1-3,
each residual evaluation is a few hundred flops per pair), started from the user's guess and, if
that does not fit, from a grid over the joint space.

Units: radians; errors in normalized image units (pixels / focal length).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from dcc_fg.model import GimbalCalibration
from dcc_fg.vio.epipolar import essential, sampson_distance

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class JointFit:
    """Result of :func:`fit_joint_angles`: angles (rad), RMS Sampson error of the inliers
    (normalized units), inlier count, total pair count and the Gauss-Newton covariance of the
    angles (rad^2, ``rms^2 (J^T W J)^-1`` over the inliers; None when not estimated)."""

    theta: FloatArray
    rms: float
    inliers: int
    pairs: int
    covariance: FloatArray | None = None


def _residuals(cal: GimbalCalibration, theta: FloatArray, xy_s: FloatArray, xy_d: FloatArray) -> FloatArray:
    return sampson_distance(essential(cal.T_ds(theta)), xy_s, xy_d)


def _jacobian(cal: GimbalCalibration, theta: FloatArray, xy_s: FloatArray, xy_d: FloatArray) -> FloatArray:
    """Central-difference Jacobian (N, L) of the Sampson errors with respect to theta."""
    h = 1e-6
    J = np.empty((xy_s.shape[0], theta.size))
    for j in range(theta.size):
        e = np.zeros(theta.size)
        e[j] = h
        J[:, j] = (_residuals(cal, theta + e, xy_s, xy_d) - _residuals(cal, theta - e, xy_s, xy_d)) / (2 * h)
    return J


def _gauss_newton(
    cal: GimbalCalibration, theta0: FloatArray, xy_s: FloatArray, xy_d: FloatArray, huber: float, iters: int = 20
) -> tuple[FloatArray, float]:
    """Huber-IRLS Gauss-Newton on theta; returns (theta, robust cost)."""
    theta = theta0.astype(float).copy()
    L = theta.size
    for _ in range(iters):
        r = _residuals(cal, theta, xy_s, xy_d)
        w = np.where(r <= huber, 1.0, huber / np.maximum(r, 1e-300))
        J = _jacobian(cal, theta, xy_s, xy_d)
        A = J * w[:, None]
        H = J.T @ A + 1e-9 * np.eye(L)
        step = -np.linalg.solve(H, A.T @ r)
        step = np.clip(step, -0.3, 0.3)  # at most ~17 deg per iteration: stay in the basin
        theta = theta + step
        if np.max(np.abs(step)) < 1e-9:
            break
    r = _residuals(cal, theta, xy_s, xy_d)
    cost = float(np.sum(np.where(r <= huber, 0.5 * r**2, huber * (r - 0.5 * huber))))
    return theta, cost


def fit_joint_angles(
    cal: GimbalCalibration,
    xy_s: FloatArray,
    xy_d: FloatArray,
    theta_guess: FloatArray | None = None,
    inlier_threshold: float = 3.0 / 460.0,
    grid: int = 12,
) -> JointFit:
    """Joint angles that make the static/gimbal pairs epipolar-consistent (module docstring).

    Args:
        cal: calibrated chain (``T_ds(theta)``).
        xy_s, xy_d: (N, 2) undistorted normalized coordinates of the same points in s and d.
        theta_guess: (L,) start, e.g. the gimbal's home position; None: grid only.
        inlier_threshold: Sampson error (normalized units) below which a pair is an inlier; also
            the Huber threshold.
        grid: grid points per joint over [-pi, pi) for the global search (0: none; used when the guess
            leaves fewer than half of the pairs as inliers).

    Raises:
        ValueError: fewer than 2L + 2 pairs, or mismatched shapes.
    """
    xy_s = np.asarray(xy_s, dtype=float).reshape(-1, 2)
    xy_d = np.asarray(xy_d, dtype=float).reshape(-1, 2)
    L = cal.n_joints
    if xy_s.shape != xy_d.shape:
        raise ValueError(f"static and gimbal points differ in shape: {xy_s.shape} vs {xy_d.shape}")
    if xy_s.shape[0] < 2 * L + 2:
        raise ValueError(f"{xy_s.shape[0]} static/gimbal pairs cannot determine {L} joint angles (need {2 * L + 2})")

    def summary(theta: FloatArray) -> JointFit:
        r = _residuals(cal, theta, xy_s, xy_d)
        inl = r < inlier_threshold
        rms = float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else float("inf")
        cov = None
        if inl.sum() > L:
            J = _jacobian(cal, theta, xy_s[inl], xy_d[inl])
            H = J.T @ J
            if np.linalg.cond(H) < 1e12:
                cov = rms**2 * inl.sum() / (inl.sum() - L) * np.linalg.inv(H)
        return JointFit(theta, rms, int(inl.sum()), int(r.size), cov)

    best: tuple[float, FloatArray] | None = None
    if theta_guess is not None:
        theta, cost = _gauss_newton(cal, np.asarray(theta_guess, float).reshape(L), xy_s, xy_d, inlier_threshold)
        fit = summary(theta)
        if fit.inliers >= 0.5 * fit.pairs:
            return fit
        best = (cost, theta)
    axis = np.linspace(-np.pi, np.pi, grid, endpoint=False)
    starts = [np.array(c) for c in itertools.product(axis, repeat=L)]
    # rank the grid by the robust cost at the start, refine the most promising few
    costs = []
    for s in starts:
        r = _residuals(cal, s, xy_s, xy_d)
        costs.append(float(np.sum(np.minimum(r, 10 * inlier_threshold))))
    for i in np.argsort(costs)[:8]:
        theta, cost = _gauss_newton(cal, starts[i], xy_s, xy_d, inlier_threshold)
        if best is None or cost < best[0]:
            best = (cost, theta)
    assert best is not None
    theta = (best[1] + np.pi) % (2 * np.pi) - np.pi
    return summary(theta)
