"""Initial values for the calibration graph.

* :func:`pnp_pose` - target pose ``T_ct`` (target -> camera c) from one view by planar PnP
  (OpenCV IPPE on undistorted normalized points, then Levenberg-Marquardt refinement).
* hand-measured kinematics come from a ``gimbal.yaml`` (:func:`dcc_fg.model.load_calibration`).
"""

from __future__ import annotations

import cv2
import gtsam
import numpy as np
from numpy.typing import NDArray
from scipy import sparse
from scipy.sparse.linalg import splu

from factors import chain
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]


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
) -> tuple[FloatArray, FloatArray, float]:
    """Fit the chain to per-snapshot PnP transforms ``T_ds_i = T_dt_i inv(T_st_i)`` (Levenberg-Marquardt).

    Minimizes ``sum_i |W Log(T_ds_measured_i^-1 T_ds(kin, theta_i))|^2`` with W = diag(1/sigma_rot x3,
    1/sigma_trans x3) over the free kinematic entries and (when ``estimate_theta``) the joint
    angles, holding the mean of each joint in ``offset_joints`` (gauge). This small problem (6 rows
    per snapshot, no projection, no depth singularities) has a much wider basin of convergence than
    the pixel-level graph, so it is solved first.

    Returns ``(kin, thetas, rms)`` where ``rms`` is the RMS of the whitened residual per row.
    """
    K = T_ds_measured.shape[0]
    L = n_joints
    free_idx = np.flatnonzero(free)
    nf = free_idx.size
    nt = K * L if estimate_theta else 0
    w = np.array([1 / sigma_rot] * 3 + [1 / sigma_trans] * 3)
    meas = [gtsam.Pose3(T) for T in T_ds_measured]
    mean0 = thetas0.mean(axis=0) if L else np.zeros(0)

    def unpack(x: FloatArray) -> tuple[FloatArray, FloatArray]:
        kin = kin0.copy()
        kin[free_idx] = x[:nf]
        th = x[nf:].reshape(K, L) if estimate_theta else thetas0
        return kin, th

    # Jacobian sparsity: each snapshot's 6 rows touch the free kinematic entries and its own L joint
    # angles; the gauge rows (G) touch every angle of one joint. J is stored sparse without G, and
    # G enters the normal equations by the Woodbury identity, so memory stays linear in K.
    rows_s = np.repeat(np.arange(6 * K), nf + (L if estimate_theta else 0))
    cols_s = (
        np.concatenate(
            [
                np.tile(np.concatenate([np.arange(nf), nf + i * L + np.arange(L if estimate_theta else 0)]), 6)
                for i in range(K)
            ]
        )
        if K
        else np.zeros(0, dtype=np.int64)
    )
    G = np.zeros((len(offset_joints) if estimate_theta else 0, nf + nt))
    for row, j in enumerate(offset_joints if estimate_theta else []):
        G[row, nf + j : nf + nt : L] = 1e3 / K

    def residual(x: FloatArray, jac: bool) -> tuple[FloatArray, sparse.csr_matrix | None]:
        kin, th = unpack(x)
        r = np.zeros(6 * K + G.shape[0])
        blocks = np.zeros((K, 6, nf + (L if estimate_theta else 0))) if jac else None
        for i in range(K):
            r[6 * i : 6 * i + 6] = w * meas[i].localCoordinates(gtsam.Pose3(chain.T_ds(kin, th[i], L)))
            if blocks is not None:
                Jk, Jt = chain.d_T_ds_tangent(kin, th[i], L)
                blocks[i, :, :nf] = w[:, None] * Jk[:, free_idx]
                if estimate_theta:
                    blocks[i, :, nf:] = w[:, None] * Jt
        for row, j in enumerate(offset_joints if estimate_theta else []):
            r[6 * K + row] = 1e3 * (th[:, j].mean() - mean0[j])
        if blocks is None:
            return r, None
        return r, sparse.csr_matrix((blocks.ravel(), (rows_s, cols_s)), shape=(6 * K, nf + nt))

    def lm_step(J: sparse.csr_matrix, r: FloatArray, lam: float) -> FloatArray:
        """Solve (J^T J + G^T G + lam diag) dx = -(J^T r_s + G^T r_g) (Woodbury for G)."""
        B = (J.T @ J).tocsc()
        diag = B.diagonal() + np.sum(G * G, axis=0)
        B = B + sparse.diags(lam * (diag + 1e-12), format="csc")
        g = J.T @ r[: 6 * K] + G.T @ r[6 * K :]
        lu = splu(B)
        Bg = lu.solve(-g)
        if G.shape[0] == 0:
            return Bg
        BGt = lu.solve(np.ascontiguousarray(G.T))
        S = np.eye(G.shape[0]) + G @ BGt
        return Bg - BGt @ np.linalg.solve(S, G @ Bg)

    x = np.concatenate([kin0[free_idx], thetas0.ravel() if estimate_theta else np.zeros(0)])
    r, J = residual(x, True)
    cost = float(r @ r)
    lam = 1e-3
    for _ in range(max_iterations):
        assert J is not None
        step = lm_step(J, r, lam)
        r_new, _ = residual(x + step, False)
        cost_new = float(r_new @ r_new)
        if cost_new < cost:
            x = x + step
            converged = cost - cost_new < 1e-12 * cost
            r, J = residual(x, True)
            cost = cost_new
            lam = max(lam / 3.0, 1e-9)
            if converged:
                break
        else:
            lam *= 4.0
            if lam > 1e10:
                break
    kin, th = unpack(x)
    return kin, th.copy(), float(np.sqrt(cost / r.size))
