"""Automatic initialization of the gimbal chain from per-snapshot PnP (``--init auto``).

No hand-measured kinematics and no joint-angle guesses are needed. From the PnP poses of both
cameras, ``T_ds_i = T_dt_i inv(T_st_i)``, the dynamic camera's pose in the static camera is the
forward kinematics of the chain (frames as in :mod:`factors.chain`)::

    T_sd(theta) = T_sb A_1(theta_1) ... A_L(theta_L) T_ed,   A_l = Rz(theta_l) Tz(d_l) Tx(a_l) Rx(alpha_l).

Gauge (the values chosen here are the ones :func:`dcc_fg.calibrate.calibrate` then holds):
``d_L = a_L = alpha_L = 0`` (so ``A_L = Rz(theta_L)``), ``tau_s.rz = 0`` and ``tau_s.tz = 0`` (the
base origin is the foot of the perpendicular from the static camera centre onto joint 1's axis),
and the mean of theta_L is chosen so that ``tau_d``'s Euler pitch is 0, far from its singularity.

Closed form, rotation first:

* L = 1: every relative rotation ``R_sd_i R_sd_0^T`` is a rotation about joint 1's axis
  ``w_1`` (in s); ``w_1`` is the principal direction of their axis-angle vectors, the angles
  are their components along it.
* L = 2: joint 1's axis ``w_1`` is fixed in s and joint 2's axis ``b_2`` is fixed in d, so
  ``w_1^T R_sd_i b_2 = cos(alpha_1)`` for every snapshot: the vectors ``R_sd_i^T w_1`` lie in
  one plane with normal ``b_2``. For a candidate ``w_1``, ``b_2`` is the smallest eigenvector of
  their covariance and the eigenvalue measures the misfit, so only ``w_1`` (2 dof) is searched
  (a hemisphere grid refined locally). theta_1 follows from where ``R_sd_i b_2`` lies around
  ``w_1``, theta_2 from the remaining rotation about ``b_2``.

Then, for any L, the translations ``t_sb``, ``d_l, a_l`` (l < L) and ``t_ed`` enter
``t_sd_i`` linearly once the rotations are known: one linear least-squares solve.

L >= 3: three non-parallel axes span all rotations, so the rotations alone do not determine
the axes (no closed form here). The twists and mount rotations are then found by a small
multi-start search on the pose-level cost (:func:`dcc_fg.init.pose_level_refine`), each start
seeded by the closed-form solution of the rotation equations for its twists.

Everything is refined afterwards: the pose-level LM fit, then the corner-level graph.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from dcc_fg.data import CalibrationDataset
from dcc_fg.init import pnp_pose, pose_level_refine
from dcc_fg.model import GimbalCalibration
from factors import chain

FloatArray = NDArray[np.float64]


def pnp_T_ds(data: CalibrationDataset) -> FloatArray:
    """(K, 4, 4) per-snapshot ``T_ds_i = T_dt_i inv(T_st_i)`` from PnP in both cameras."""
    P = data.target_points
    out = []
    for s in data.snapshots:
        T_st = pnp_pose(data.static_camera, P[s.static.ids], s.static.pixels)
        T_dt = pnp_pose(data.dynamic_camera, P[s.dynamic.ids], s.dynamic.pixels)
        out.append(T_dt @ chain.inv_se3(T_st))
    return np.array(out)


# ------------------------------------------------------------------ rotation helpers


def _log_so3(R: FloatArray) -> FloatArray:
    """Axis-angle vector of a rotation matrix (rad)."""
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(c)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if angle < 1e-9:
        return 0.5 * w
    if np.pi - angle < 1e-6:  # near pi: axis from the symmetric part
        M = (R + np.eye(3)) / 2.0
        axis = M[:, int(np.argmax(np.diag(M)))]
        return angle * axis / np.linalg.norm(axis)
    return angle * w / (2.0 * np.sin(angle))


def _project_so3(M: FloatArray) -> FloatArray:
    """Closest rotation matrix (Frobenius norm) to a 3x3 matrix."""
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def _z_angle(R: FloatArray) -> float:
    """Angle of the rotation about z closest to R (rad)."""
    return float(np.arctan2(R[1, 0] - R[0, 1], R[0, 0] + R[1, 1]))


def _wrap(a: FloatArray) -> FloatArray:
    return np.arctan2(np.sin(a), np.cos(a))


def base_rotation(w1: FloatArray) -> FloatArray:
    """``R_bs = Ry(ry) Rx(rx)`` mapping joint 1's axis ``w1`` (unit, in s) onto the base z axis.

    Its Euler yaw is 0: this choice fixes the gauge ``tau_s.rz = 0``.
    """
    w = w1 / np.linalg.norm(w1)
    rx = np.arctan2(w[1], w[2])
    vz = np.hypot(w[1], w[2])
    ry = np.arctan2(-w[0], vz)
    return chain.rot_y(ry) @ chain.rot_x(rx)


def _prefix_rotations(thetas: FloatArray, alphas: FloatArray) -> list[FloatArray]:
    """Per snapshot, ``G_l = prod_{k<l} (Rz(theta_k) Rx(alpha_k)) Rz(theta_l)`` for l = 1..L: (K, L, 3, 3)."""
    K, L = thetas.shape
    out = np.zeros((K, L, 3, 3))
    for i in range(K):
        P = np.eye(3)
        for lnk in range(L):
            out[i, lnk] = P @ chain.rot_z(thetas[i, lnk])
            P = out[i, lnk] @ chain.rot_x(alphas[lnk])
    return list(out)


# ------------------------------------------------------------------ closed forms


def _rotation_one_joint(R_sd: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Joint axis w1 (in s) and relative angles theta_i - theta_0 of an L = 1 mechanism."""
    logs = np.array([_log_so3(R @ R_sd[0].T) for R in R_sd])
    _, _, Vt = np.linalg.svd(logs, full_matrices=False)
    w1 = Vt[0]
    return w1, logs @ w1


def _axis_pair_cost(R_sd: FloatArray, U: FloatArray) -> tuple[FloatArray, FloatArray]:
    """For candidate joint-1 axes U (M, 3) in s: the smallest eigenvalue of the covariance of
    ``r_i = R_sd_i^T u`` over the snapshots and its eigenvector (the best joint-2 axis in d)."""
    K = R_sd.shape[0]
    C = np.empty((U.shape[0], 3, 3))
    step = max(1, 200_000 // max(K, 1))  # candidates per block: (step, K, 3) doubles, ~5 MB
    for a in range(0, U.shape[0], step):
        r = np.einsum("kji,mj->mki", R_sd, U[a : a + step])
        r -= r.mean(axis=1, keepdims=True)
        C[a : a + step] = np.einsum("mki,mkj->mij", r, r) / K
    w, V = np.linalg.eigh(C)
    return w[:, 0], V[:, :, 0]


def _sphere_points(n: int) -> FloatArray:
    """n roughly uniform unit vectors on the upper hemisphere (Fibonacci lattice)."""
    k = np.arange(n) + 0.5
    z = k / n
    phi = np.pi * (1.0 + 5.0**0.5) * k
    rho = np.sqrt(1.0 - z * z)
    return np.column_stack([rho * np.cos(phi), rho * np.sin(phi), z])


def _refine_axis(R_sd: FloatArray, u: FloatArray, step: float = 0.06) -> FloatArray:
    """Local refinement of a joint-1 axis candidate by shrinking grids around it."""
    for _ in range(4):
        e1 = np.linalg.svd(u.reshape(1, 3))[2][1:]
        g = np.linspace(-step, step, 13)
        cand = u + np.array([a * e1[0] + b * e1[1] for a in g for b in g])
        cand /= np.linalg.norm(cand, axis=1, keepdims=True)
        c, _ = _axis_pair_cost(R_sd, cand)
        u = cand[int(np.argmin(c))]
        step /= 5.0
    return u


def _rotation_two_joints(R_sd: FloatArray, n_candidates: int = 4) -> list[tuple[FloatArray, FloatArray, float]]:
    """Candidate axes ``w1`` (in s), ``b2`` (in d) and cos(alpha_1) of an L = 2 mechanism, best first.

    ``w1^T R_sd_i b2`` is the same for every snapshot, so for the true ``w1`` the vectors
    ``R_sd_i^T w1`` lie in one plane normal to ``b2``. The linear version of this (null vector of
    ``[vec(R_sd_i), -1]``) is swamped by PnP noise when a joint moves only +-10 deg, so the search
    is over the unit vector ``w1`` (2 dof; ``b2`` and the constant follow from the smallest
    eigenvector of a 3x3 covariance): a hemisphere grid, then finer local grids around the best
    few well-separated grid minima (small joint ranges can leave more than one plausible minimum;
    the pose-level fit decides between them).
    """
    U = _sphere_points(3000)
    cost, _ = _axis_pair_cost(R_sd, U)
    picked: list[FloatArray] = []
    for k in np.argsort(cost):
        if all(abs(float(U[k] @ p)) < np.cos(np.deg2rad(15.0)) for p in picked):
            picked.append(U[k])
        if len(picked) == n_candidates:
            break
    out = []
    for u0 in picked:
        u = _refine_axis(R_sd, u0)
        c_min, V = _axis_pair_cost(R_sd, u.reshape(1, 3))
        b2 = V[0]
        c = float(np.mean(np.einsum("kji,j,i->k", R_sd, u, b2)))
        out.append((float(c_min[0]), u, b2, float(np.clip(c, -1.0, 1.0))))
    out.sort(key=lambda t: t[0])
    return [(u, b2, c) for _, u, b2, c in out]


def _translation_solve(
    T_sd: FloatArray, R_sb: FloatArray, thetas: FloatArray, alphas: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Linear least squares for ``t_sb`` (perpendicular to joint 1's axis: ``tau_s.tz = 0``),
    ``(d_l, a_l)`` for l < L and ``t_ed``, given all rotations. Returns (t_sb, da (L-1, 2), t_ed)."""
    K, L = thetas.shape
    w1 = R_sb[:, 2]
    # basis of the plane perpendicular to w1
    P = np.linalg.svd(w1.reshape(1, 3))[2][1:].T  # (3, 2)
    G = _prefix_rotations(thetas, alphas)
    n = 2 + 2 * (L - 1) + 3
    A = np.zeros((3 * K, n))
    b = np.zeros(3 * K)
    for i in range(K):
        rows = slice(3 * i, 3 * i + 3)
        A[rows, 0:2] = P
        for lnk in range(L - 1):
            M = R_sb @ G[i][lnk]
            A[rows, 2 + 2 * lnk] = M[:, 2]  # d_l along z_{l-1}
            A[rows, 3 + 2 * lnk] = M[:, 0]  # a_l along x_l
        A[rows, n - 3 :] = R_sb @ G[i][L - 1]
        b[rows] = T_sd[i, :3, 3]
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    return P @ x[0:2], x[2 : 2 + 2 * (L - 1)].reshape(L - 1, 2), x[n - 3 :]


def _assemble(
    R_sb: FloatArray,
    t_sb: FloatArray,
    R_ed: FloatArray,
    t_ed: FloatArray,
    alphas: FloatArray,
    da: FloatArray,
) -> FloatArray:
    """kin vector from the chain pieces (last link d = a = alpha = 0)."""
    T_sb = np.eye(4)
    T_sb[:3, :3], T_sb[:3, 3] = R_sb, t_sb
    T_ed = np.eye(4)
    T_ed[:3, :3], T_ed[:3, 3] = R_ed, t_ed
    tau_s = chain.tau_from_se3(chain.inv_se3(T_sb))
    tau_d = chain.tau_from_se3(chain.inv_se3(T_ed))
    L = alphas.size
    dh = np.zeros((L, 3))
    dh[:-1, 0] = da[:, 0]
    dh[:-1, 1] = da[:, 1]
    dh[:, 2] = alphas
    dh[-1] = 0.0
    return np.concatenate([tau_s, tau_d, dh.ravel()])


def _end_mount(W: FloatArray, rel_last: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Given ``W_i = Rz(theta_L,i) R_ed`` up to a common offset of theta_L, choose the offset so that
    tau_d's Euler pitch is 0 and return (theta_L (K,), R_ed)."""
    th = _wrap(rel_last - np.angle(np.mean(np.exp(1j * rel_last))))
    R_ed = _project_so3(sum(chain.rot_z(-t) @ Wi for t, Wi in zip(th, W, strict=True)))
    R_de = R_ed.T
    phi = float(np.arctan2(-R_de[2, 0], R_de[2, 1]))  # R_de Rz(phi) has (2, 0) entry 0
    return th + phi, chain.rot_z(-phi) @ R_ed


def closed_form_low_dof(
    T_ds: FloatArray, n_joints: int, axes: tuple[FloatArray, FloatArray, float] | None = None
) -> tuple[FloatArray, FloatArray]:
    """Closed-form kin (12 + 3L) and joint angles (K, L) for L in {1, 2} (module docstring).

    ``axes``: (w1, b2, cos alpha_1) for L = 2 (default: the best candidate of the axis search)."""
    T_sd = np.array([chain.inv_se3(T) for T in T_ds])
    R_sd = T_sd[:, :3, :3]
    K = T_sd.shape[0]
    if n_joints == 1:
        w1, rel = _rotation_one_joint(R_sd)
        R_bs = base_rotation(w1)
        W = np.array([R_bs @ R for R in R_sd])  # = Rz(theta_i) R_ed
        th1, R_ed = _end_mount(W, rel)
        thetas = th1.reshape(K, 1)
        alphas = np.zeros(1)
    elif n_joints == 2:
        w1, b2, c = axes if axes is not None else _rotation_two_joints(R_sd)[0]
        alpha1 = float(np.arccos(c))
        R_bs = base_rotation(w1)
        v = np.einsum("ij,kjl,l->ki", R_bs, R_sd, b2)  # Rz(theta_1) [0, -sin a1, cos a1]
        th1 = _wrap(np.arctan2(v[:, 1], v[:, 0]) + np.pi / 2.0)
        W = np.array(
            [chain.rot_x(alpha1).T @ chain.rot_z(t).T @ R_bs @ R for t, R in zip(th1, R_sd, strict=True)]
        )  # = Rz(theta_2) R_ed
        rel2 = np.array([_z_angle(Wi @ W[0].T) for Wi in W])
        th2, R_ed = _end_mount(W, rel2)
        thetas = np.column_stack([th1, th2])
        alphas = np.array([alpha1, 0.0])
    else:
        raise ValueError(f"the closed-form initialization covers L = 1 or 2 joints, not {n_joints}")
    R_sb = R_bs.T
    t_sb, da, t_ed = _translation_solve(T_sd, R_sb, thetas, alphas)
    return _assemble(R_sb, t_sb, R_ed, t_ed, alphas, da), thetas


def _rotation_ik(Q: FloatArray, alphas: FloatArray, th2_sign: float) -> FloatArray:
    """Joint angles with ``Rz(t1) Rx(a1) Rz(t2) Rx(a2) Rz(t3) = Q`` (three joints, closed form)."""
    a1, a2 = alphas[0], alphas[1]
    denom = np.sin(a1) * np.sin(a2)
    c2 = (np.cos(a1) * np.cos(a2) - Q[2, 2]) / denom if abs(denom) > 1e-9 else 1.0
    t2 = th2_sign * float(np.arccos(np.clip(c2, -1.0, 1.0)))
    u = chain.rot_x(a1) @ chain.rot_z(t2) @ chain.rot_x(a2) @ np.array([0.0, 0.0, 1.0])
    qz = Q[:, 2]
    t1 = np.arctan2(qz[1], qz[0]) - np.arctan2(u[1], u[0])
    rz = np.array([0.0, 0.0, 1.0]) @ chain.rot_x(a1) @ chain.rot_z(t2) @ chain.rot_x(a2)  # row e_z^T (...)
    qr = Q[2, :]
    t3 = np.arctan2(qr[1], qr[0]) - np.arctan2(rz[1], rz[0])
    return _wrap(np.array([t1, t2, t3]))


def multistart_three_joints(
    T_ds: FloatArray, n_starts: int = 24, seed: int = 0, good_rms: float = 5.0
) -> tuple[FloatArray, FloatArray, float]:
    """L = 3: random twists and joint-1/joint-3 axes, closed-form rotation IK and translations per
    start, then the pose-level LM fit; the best fit wins (see the module docstring)."""
    T_sd = np.array([chain.inv_se3(T) for T in T_ds])
    R_sd = T_sd[:, :3, :3]
    rng = np.random.default_rng(seed)
    free = np.ones(chain.n_kin(3), dtype=bool)
    free[[2, 5, 18, 19, 20]] = False
    best: tuple[FloatArray, FloatArray, float] | None = None
    for _ in range(n_starts):
        w1 = rng.normal(size=3)
        w1 /= np.linalg.norm(w1)
        b3 = rng.normal(size=3)
        b3 /= np.linalg.norm(b3)
        alphas = np.array([rng.uniform(0.3, np.pi - 0.3), rng.uniform(0.3, np.pi - 0.3), 0.0])
        R_bs = base_rotation(w1)
        R_ed = _project_so3(base_rotation(b3))  # maps b3 (in d) onto the end-effector z axis
        sign = 1.0 if rng.uniform() < 0.5 else -1.0
        thetas = np.array([_rotation_ik(R_bs @ R @ R_ed.T, alphas, sign) for R in R_sd])
        R_sb = R_bs.T
        t_sb, da, t_ed = _translation_solve(T_sd, R_sb, thetas, alphas)
        kin0 = _assemble(R_sb, t_sb, R_ed, t_ed, alphas, da)
        kin, th, rms = pose_level_refine(kin0, 3, T_ds, thetas, free, [2], True, max_iterations=60)
        if best is None or rms < best[2]:
            best = (kin, th, rms)
        if best[2] < good_rms:
            break
    assert best is not None
    return best


def _two_joint_candidates(
    T: FloatArray, free: NDArray[np.bool_], good_rms: float = 5.0
) -> tuple[FloatArray, FloatArray, float]:
    """Closed form for each axis candidate, then the pose-level fit; the lowest fit RMS wins.

    Nearly parallel joint axes (|sin alpha_1| small) put the closed form next to the DH
    singularity, where d_1 is undefined; there the twist is also started at +-0.25 rad from
    0 or pi and the pose-level fit decides.
    """
    R_sd = np.array([chain.inv_se3(x)[:3, :3] for x in T])
    best: tuple[FloatArray, FloatArray, float] | None = None
    for axes in _rotation_two_joints(R_sd):
        kin0, th0 = closed_form_low_dof(T, 2, axes)
        starts = [(kin0, th0)]
        if abs(np.sin(kin0[14])) < 0.25:
            # nearly parallel axes: the rotations only give theta_1 + theta_2; split it several ways
            base = 0.0 if np.cos(kin0[14]) > 0 else np.pi
            total = th0[:, 0] + th0[:, 1] * np.cos(kin0[14])
            for a in (base + 0.25, base - 0.25):
                for share in (0.3, 0.7):
                    k = kin0.copy()
                    k[14] = a
                    th = np.column_stack([share * total, (1.0 - share) * total * np.cos(a - base)])
                    th -= th.mean(axis=0) - th0.mean(axis=0)
                    starts.append((k, th))
        for k0, t0 in starts:
            cand = pose_level_refine(k0, 2, T, t0, free, [1], True)
            if best is None or cand[2] < best[2]:
                best = cand
        if best is not None and best[2] < good_rms and abs(np.sin(best[0][14])) > 0.25:
            break
    assert best is not None
    return best


def auto_initialize(
    data: CalibrationDataset, n_joints: int, T_ds: FloatArray | None = None
) -> tuple[GimbalCalibration, FloatArray, float]:
    """Initial kinematics and joint angles with no gimbal.yaml.

    Args:
        data: the calibration snapshots (snapshot ``joints`` are ignored).
        n_joints: L (0 to 3).
        T_ds: per-snapshot PnP ``T_ds`` (K, 4, 4) when already computed.

    Returns:
        (initial calibration, joint angles (K, L) in rad, whitened RMS of the pose-level fit with
        1 mrad / 1 mm per unit). The gauge-fixed entries (module docstring) define the gauge the
        calibration keeps.
    """
    if n_joints < 0 or n_joints > 3:
        raise ValueError(f"automatic initialization supports 0 to 3 joints, got --joints {n_joints}")
    if not data.snapshots:
        raise ValueError(f"{data.source}: the snapshot list is empty")
    T = pnp_T_ds(data) if T_ds is None else T_ds
    K = T.shape[0]
    if n_joints > 0:
        from dcc_fg.calibrate import check_joint_motion  # calibrate never imports auto_init

        check_joint_motion(data, T, n_joints)  # a joint that never moves: say so before fitting noise
    cams = {"static_camera": data.static_camera, "dynamic_camera": data.dynamic_camera}
    if n_joints == 0:
        R = _project_so3(T[:, :3, :3].sum(axis=0))
        T0 = np.eye(4)
        T0[:3, :3], T0[:3, 3] = R, T[:, :3, 3].mean(axis=0)
        kin = np.concatenate([np.zeros(6), chain.tau_from_se3(T0)])
        return GimbalCalibration(kin, 0, **cams), np.zeros((K, 0)), float("nan")
    free = np.ones(chain.n_kin(n_joints), dtype=bool)
    last = 12 + 3 * (n_joints - 1)
    free[[2, 5, last, last + 1, last + 2]] = False
    if n_joints == 1:
        kin0, th0 = closed_form_low_dof(T, 1)
        kin, th, rms = pose_level_refine(kin0, 1, T, th0, free, [0], True)
    elif n_joints == 2:
        kin, th, rms = _two_joint_candidates(T, free)
    else:
        kin, th, rms = multistart_three_joints(T)
    return GimbalCalibration(kin, n_joints, **cams), th, rms
