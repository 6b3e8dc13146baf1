"""Initial values for the calibration graph (frames in docs/architecture.md; ``T_ab`` maps b into a).

* :func:`pnp_pose` - target pose ``T_ct`` (target -> camera c) from one view by planar PnP
  (OpenCV IPPE on undistorted normalized points, then Levenberg-Marquardt refinement).
* :func:`joint_angles_from_T_ds` - joint angles whose chain matches one measured ``T_ds`` (IK).
* :func:`pose_level_refine` / :func:`robust_pose_level_init` - the chain fitted to the per-snapshot
  PnP transforms ``T_ds_i`` (6 rows per snapshot, no projection), which has a much wider basin of
  convergence than the corner-level graph and is solved first.
* :func:`zero_joint_init` - closed-form start of a rigid pair (L = 0).
* hand-measured kinematics come from a ``gimbal.yaml`` (:func:`dcc_fg.model.load_calibration`).
"""

from __future__ import annotations

import cv2
import gtsam
import numpy as np
from numpy.typing import NDArray
from scipy import sparse
from scipy.sparse.linalg import splu
from scipy.spatial.transform import Rotation

from dcc_fg.model import GimbalCalibration
from factors import chain
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]
GAUGE_ROW_WEIGHT = 1e3  # pose-level fit: weight of the rows holding the mean joint angles (gauge)


def pnp_pose(camera: CameraModel, p_t: FloatArray, uv: FloatArray) -> FloatArray:
    """Pose of the target in the camera frame, ``T_ct`` (4x4), from >= 4 corners.

    Args:
        camera: intrinsics of the camera.
        p_t: (N, 3) target points in the target frame, metres (planar, z = 0 for our targets).
        uv: (N, 2) measured pixels.
    """
    if p_t.shape[0] < 4:
        raise ValueError(f"PnP needs at least 4 corners, got {p_t.shape[0]}")
    xy = camera.undistort_points(uv)
    obj = np.ascontiguousarray(p_t, dtype=np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(xy, dtype=np.float64).reshape(-1, 1, 2)
    K = np.eye(3)
    planar = np.ptp(p_t[:, 2]) < 1e-9
    flag = cv2.SOLVEPNP_IPPE if planar else cv2.SOLVEPNP_ITERATIVE
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=flag)
    if not ok:
        raise ValueError("PnP failed")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, None, rvec, tvec)
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    return T


# ------------------------------------------------------------------ averages of rotations and poses


def chordal_mean_rotation(R: FloatArray) -> FloatArray:
    """Chordal L2 mean (3x3) of K rotation matrices (K, 3, 3): the rotation closest in the
    Frobenius norm to their sum (scipy ``Rotation.mean``)."""
    return Rotation.from_matrix(R).mean().as_matrix()


def mean_pose(T: FloatArray) -> FloatArray:
    """Average of K rigid transforms (K, 4, 4): chordal L2 mean rotation and arithmetic mean translation."""
    out = np.eye(4)
    out[:3, :3] = chordal_mean_rotation(T[:, :3, :3])
    out[:3, 3] = T[:, :3, 3].mean(axis=0)
    return out


def zero_joint_init(kin0: FloatArray, T_ds_pnp: FloatArray) -> FloatArray:
    """Closed-form start for L = 0: ``tau_d`` from the mean PnP ``T_ds`` with ``tau_s`` held.

    With no joints ``T_ds = T_de(tau_d) T_bs(tau_s)``, so ``T_de = mean(T_ds) inv(T_bs)``; this
    removes any dependence on the user's initial ``tau_d`` (a far-off one, e.g. a 90-degree
    rotation, otherwise starts the pixel graph with points behind the camera).
    """
    kin = np.asarray(kin0, float).copy()
    T_de = mean_pose(T_ds_pnp) @ chain.inv_se3(chain.se3_from_tau(kin[0:6]))
    kin[6:12] = chain.tau_from_se3(T_de)
    return kin


# ------------------------------------------------------------------ joint angles of one snapshot


def tangent_error(T_a: FloatArray, T_b: FloatArray) -> FloatArray:
    """6-vector [omega, v] of Log(T_b^-1 T_a) (gtsam convention)."""
    return gtsam.Pose3(T_b).localCoordinates(gtsam.Pose3(T_a))


def joint_angles_from_T_ds(
    cal: GimbalCalibration, T_ds_measured: FloatArray, guess: FloatArray | None, n_starts: int = 12
) -> FloatArray:
    """Joint angles (rad) whose chain best matches a measured T_ds (Gauss-Newton on its tangent
    error, from ``guess`` and ``n_starts`` seeded random starts; the lowest cost wins).

    Used to initialize joint angles from PnP when no initial angles are given.
    """
    L = cal.n_joints
    if L == 0:
        return np.zeros(0)
    starts = [np.asarray(guess, float)] if guess is not None else []
    rng = np.random.default_rng(0)
    starts += [rng.uniform(-np.pi, np.pi, size=L) for _ in range(n_starts)]
    best, best_cost = starts[0], np.inf
    for th in starts:
        th = th.copy()
        for _ in range(30):
            e = tangent_error(cal.T_ds(th), T_ds_measured)
            _, J = chain.d_T_ds_tangent(cal.kin, th, L)
            step = np.linalg.lstsq(J, -e, rcond=None)[0]
            th += step
            if np.linalg.norm(step) < 1e-10:
                break
        cost = float(np.sum(tangent_error(cal.T_ds(th), T_ds_measured) ** 2))
        if cost < best_cost:
            best, best_cost = th, cost
    return np.arctan2(np.sin(best), np.cos(best))


# ------------------------------------------------------------------ pose-level fit


class PoseLevelProblem:
    """Whitened residuals of the chain against per-snapshot ``T_ds_i`` and their sparse Jacobian.

    Unknowns ``x = [free kinematic entries, joint angles (K*L, row-major) when estimated]``. Rows:
    per snapshot ``W_i Log(T_ds_measured_i^-1 T_ds(kin, theta_i))`` (6; W_i = diag(1/sigma_rot x3,
    1/sigma_trans x3), rad and m, or the snapshot's ``whitening[i]`` (6, 6) when given, e.g. the
    square root of its PnP information, :meth:`dcc_fg.noise_floor.NoiseFloor.T_ds_whitening`), then
    one gauge row per joint in ``offset_joints``:
    ``GAUGE_ROW_WEIGHT * (mean_i theta_ij - mean_i theta0_ij)``. Each snapshot's rows touch the
    free kinematic entries and its own L angles; the gauge rows (``G``, dense over one joint's
    angles) are kept apart and enter the normal equations by the Woodbury identity, so memory stays
    linear in K.
    """

    def __init__(
        self,
        kin0: FloatArray,
        n_joints: int,
        T_ds_measured: FloatArray,
        thetas0: FloatArray,
        free: NDArray[np.bool_],
        offset_joints: list[int],
        estimate_theta: bool,
        sigma_rot: float,
        sigma_trans: float,
        whitening: FloatArray | None = None,
    ) -> None:
        K, L = T_ds_measured.shape[0], n_joints
        self.kin0, self.thetas0, self.n_joints, self.K = kin0, thetas0, L, K
        self.estimate_theta = estimate_theta
        self.free_idx = np.flatnonzero(free)
        self.nf = nf = self.free_idx.size
        self.nt = nt = K * L if estimate_theta else 0
        self.n_local = L if estimate_theta else 0
        w = np.diag([1 / sigma_rot] * 3 + [1 / sigma_trans] * 3)
        self.W = np.broadcast_to(w, (K, 6, 6)) if whitening is None else np.asarray(whitening, float)
        if self.W.shape != (K, 6, 6):
            raise ValueError(f"whitening has shape {self.W.shape}, expected ({K}, 6, 6)")
        self.meas = [gtsam.Pose3(T) for T in T_ds_measured]
        self.mean0 = thetas0.mean(axis=0) if L else np.zeros(0)
        self.rows = np.repeat(np.arange(6 * K), nf + self.n_local)
        per_snapshot = [np.concatenate([np.arange(nf), nf + i * L + np.arange(self.n_local)]) for i in range(K)]
        self.cols = np.concatenate([np.tile(c, 6) for c in per_snapshot]) if K else np.zeros(0, dtype=np.int64)
        self.gauge_joints = offset_joints if estimate_theta else []
        self.G = np.zeros((len(self.gauge_joints), nf + nt))
        for row, j in enumerate(self.gauge_joints):
            self.G[row, nf + j : nf + nt : L] = GAUGE_ROW_WEIGHT / K

    def x0(self) -> FloatArray:
        return np.concatenate([self.kin0[self.free_idx], self.thetas0.ravel() if self.estimate_theta else np.zeros(0)])

    def unpack(self, x: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(kin (12 + 3L), joint angles (K, L)) of the unknowns ``x``."""
        kin = self.kin0.copy()
        kin[self.free_idx] = x[: self.nf]
        th = x[self.nf :].reshape(self.K, self.n_joints) if self.estimate_theta else self.thetas0
        return kin, th

    def residual(self, x: FloatArray, jac: bool) -> tuple[FloatArray, sparse.csr_matrix | None]:
        """Whitened residual (6K + gauge rows) and, when ``jac``, the sparse Jacobian of its first 6K rows."""
        kin, th = self.unpack(x)
        K, L, nf, W = self.K, self.n_joints, self.nf, self.W
        r = np.zeros(6 * K + self.G.shape[0])
        blocks = np.zeros((K, 6, nf + self.n_local)) if jac else None
        if blocks is None:
            T = chain.T_ds_batch(kin, th, L)
        else:
            T, Jk, Jt = chain.d_T_ds_tangent_batch(kin, th, L)
            blocks[:, :, :nf] = W @ Jk[:, :, self.free_idx]
            if self.estimate_theta:
                blocks[:, :, nf:] = W @ Jt
        for i in range(K):
            r[6 * i : 6 * i + 6] = W[i] @ self.meas[i].localCoordinates(gtsam.Pose3(T[i]))
        for row, j in enumerate(self.gauge_joints):
            r[6 * K + row] = GAUGE_ROW_WEIGHT * (th[:, j].mean() - self.mean0[j])
        if blocks is None:
            return r, None
        return r, sparse.csr_matrix((blocks.ravel(), (self.rows, self.cols)), shape=(6 * K, nf + self.nt))

    def damped_step(self, J: sparse.csr_matrix, r: FloatArray, lam: float) -> FloatArray:
        """Solve (J^T J + G^T G + lam diag) dx = -(J^T r_s + G^T r_g) (Woodbury for G)."""
        G, n_rows = self.G, 6 * self.K
        B = (J.T @ J).tocsc()
        diag = B.diagonal() + np.sum(G * G, axis=0)
        B = B + sparse.diags(lam * (diag + 1e-12), format="csc")
        g = J.T @ r[:n_rows] + G.T @ r[n_rows:]
        lu = splu(B)
        Bg = lu.solve(-g)
        if G.shape[0] == 0:
            return Bg
        BGt = lu.solve(np.ascontiguousarray(G.T))
        S = np.eye(G.shape[0]) + G @ BGt
        return Bg - BGt @ np.linalg.solve(S, G @ Bg)


def levenberg_marquardt(
    problem: PoseLevelProblem, max_iterations: int, rel_tol: float = 1e-12
) -> tuple[FloatArray, FloatArray]:
    """Minimize ``|r(x)|^2`` of a :class:`PoseLevelProblem` from ``problem.x0()``.

    Marquardt damping of the diagonal, lambda from 1e-3, divided by 3 after an accepted step (down to
    1e-9) and multiplied by 4 after a rejected one (giving up above 1e10); stops after an accepted step
    that lowers the cost by less than ``rel_tol`` of it, or after ``max_iterations`` steps.
    Returns (x, residual at x).
    """
    x = problem.x0()
    r, J = problem.residual(x, True)
    cost = float(r @ r)
    lam = 1e-3
    for _ in range(max_iterations):
        assert J is not None
        step = problem.damped_step(J, r, lam)
        r_new, _ = problem.residual(x + step, False)
        cost_new = float(r_new @ r_new)
        if cost_new < cost:
            x = x + step
            converged = cost - cost_new < rel_tol * cost
            r, J = problem.residual(x, True)
            cost = cost_new
            lam = max(lam / 3.0, 1e-9)
            if converged:
                break
        else:
            lam *= 4.0
            if lam > 1e10:
                break
    return x, r


def pose_level_refine(
    kin0: FloatArray,
    n_joints: int,
    T_ds_measured: FloatArray,
    thetas0: FloatArray,
    free: NDArray[np.bool_],
    offset_joints: list[int],
    estimate_theta: bool = True,
    sigma_rot: float = 1e-3,
    sigma_trans: float = 1e-3,
    max_iterations: int = 200,
    rel_tol: float = 1e-12,
    whitening: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, float]:
    """Fit the chain to per-snapshot PnP transforms ``T_ds_i = T_dt_i inv(T_st_i)``.

    Minimizes ``sum_i |W Log(T_ds_measured_i^-1 T_ds(kin, theta_i))|^2`` with W = diag(1/sigma_rot x3,
    1/sigma_trans x3) (rad, m) over the free kinematic entries and (when ``estimate_theta``) the joint
    angles, holding the mean of each joint in ``offset_joints`` (gauge), by
    :func:`levenberg_marquardt` on a :class:`PoseLevelProblem`.

    Returns ``(kin, thetas, rms)`` where ``rms`` is the RMS of the whitened residual per row.
    ``rel_tol``: relative cost decrease that stops the solve (:func:`levenberg_marquardt`).
    ``whitening``: (K, 6, 6) per-snapshot whitening instead of W (:class:`PoseLevelProblem`).
    """
    problem = PoseLevelProblem(
        kin0, n_joints, T_ds_measured, thetas0, free, offset_joints, estimate_theta, sigma_rot, sigma_trans, whitening
    )
    x, r = levenberg_marquardt(problem, max_iterations, rel_tol)
    kin, th = problem.unpack(x)
    return kin, th.copy(), float(np.sqrt(float(r @ r) / r.size))


def robust_pose_level_init(
    kin0: FloatArray,
    L: int,
    T_ds_pnp: FloatArray,
    thetas0: FloatArray,
    free: NDArray[np.bool_],
    offsets: list[int],
    estimate_theta: bool,
    restarts: int = 16,
    good_rms: float = 5.0,
    rel_tol: float = 1e-12,
    max_iterations: int = 200,
) -> tuple[FloatArray, FloatArray, float]:
    """:func:`pose_level_refine` with deterministic restarts.

    A fit is accepted when its whitened RMS (1 mrad / 1 mm per unit) is below ``good_rms``
    (PnP noise alone gives ~1-3); otherwise the free kinematic entries are re-drawn around the
    initial values (10 deg / 3 cm) and the best fit is kept. ``rel_tol``, ``max_iterations``: see
    :func:`pose_level_refine`.
    """

    def fit(kin: FloatArray) -> tuple[FloatArray, FloatArray, float]:
        limits = {"max_iterations": max_iterations, "rel_tol": rel_tol}
        return pose_level_refine(kin, L, T_ds_pnp, thetas0, free, offsets, estimate_theta, **limits)  # type: ignore[arg-type]

    best = fit(kin0)
    rng = np.random.default_rng(12345)
    is_angle = chain.kin_is_angle(L)
    for _ in range(restarts):
        if best[2] < good_rms:
            break
        kin_try = kin0.copy()
        noise = rng.normal(size=kin0.shape) * np.where(is_angle, np.deg2rad(10.0), 0.03)
        kin_try[free] += noise[free]
        cand = fit(kin_try)
        if cand[2] < best[2]:
            best = cand
    return best
