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

    def residual(x: FloatArray, jac: bool) -> tuple[FloatArray, FloatArray | None]:
        kin, th = unpack(x)
        r = np.zeros(6 * K + (len(offset_joints) if estimate_theta else 0))
        J = np.zeros((r.size, nf + nt)) if jac else None
        for i in range(K):
            r[6 * i : 6 * i + 6] = w * meas[i].localCoordinates(gtsam.Pose3(chain.T_ds(kin, th[i], L)))
            if J is not None:
                Jk, Jt = chain.d_T_ds_tangent(kin, th[i], L)
                J[6 * i : 6 * i + 6, :nf] = w[:, None] * Jk[:, free_idx]
                if estimate_theta:
                    J[6 * i : 6 * i + 6, nf + i * L : nf + (i + 1) * L] = w[:, None] * Jt
        if estimate_theta:
            for row, j in enumerate(offset_joints):
                r[6 * K + row] = 1e3 * (th[:, j].mean() - mean0[j])
                if J is not None:
                    J[6 * K + row, nf + j : nf + nt : L] = 1e3 / K
        return r, J

    x = np.concatenate([kin0[free_idx], thetas0.ravel() if estimate_theta else np.zeros(0)])
    r, J = residual(x, True)
    cost = float(r @ r)
    lam = 1e-3
    for _ in range(max_iterations):
        assert J is not None
        A = J.T @ J
        g = J.T @ r
        step = np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), -g)
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
