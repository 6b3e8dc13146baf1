"""Gimbal kinematic chain of a dynamic camera cluster, with analytic Jacobians.

Conventions (paper sections III-IV, docs/architecture.md):

* ``T_ab`` is a 4x4 homogeneous transform mapping a point expressed in frame ``b`` into
  frame ``a``: ``p_a = T_ab @ p_b`` (the paper's T^{a:b}).
* ``tau = [rx, ry, rz, tx, ty, tz]``: 3-2-1 Euler angles, ``R = Rz(rz) @ Ry(ry) @ Rx(rx)``
  (radians), then the translation (metres).
* DH link ``A_l(theta_l) = Rz(theta_l) Tz(d_l) Tx(a_l) Rx(alpha_l)`` maps frame ``l`` into
  frame ``l-1`` (frame 0 = gimbal base ``b``, frame L = end effector ``e``);
  ``omega_l = [d_l, a_l, alpha_l]`` (metres, metres, radians).
* Chain (paper eq. 5): ``T_ds(theta) = T_de(tau_d) @ inv(A_1 ... A_L) @ T_bs(tau_s)``.
  L = 0 is a rigid stereo pair, ``T_ds = T_de @ T_bs``.

The kinematic parameters are packed in one vector ``kin`` of length 12 + 3L:
``[tau_s (6), tau_d (6), d_1, a_1, alpha_1, ..., d_L, a_L, alpha_L]``.

:func:`transform_points` maps static-camera points into the dynamic camera and returns the
Jacobians of the result with respect to ``kin``, ``theta`` and the input points, derived
analytically (the paper's eq. 15 generalised to every kinematic parameter).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

E_X = np.array([1.0, 0.0, 0.0])
E_Z = np.array([0.0, 0.0, 1.0])


def n_kin(n_joints: int) -> int:
    """Number of kinematic parameters for an ``n_joints`` mechanism: 12 + 3L."""
    return 12 + 3 * n_joints


def kin_names(n_joints: int) -> list[str]:
    """Human-readable names of the entries of ``kin`` (units in brackets)."""
    names = [f"tau_s.{c}" for c in ("rx", "ry", "rz", "tx", "ty", "tz")]
    names += [f"tau_d.{c}" for c in ("rx", "ry", "rz", "tx", "ty", "tz")]
    for link in range(1, n_joints + 1):
        names += [f"dh{link}.d", f"dh{link}.a", f"dh{link}.alpha"]
    return names


def kin_is_angle(n_joints: int) -> NDArray[np.bool_]:
    """Boolean mask of the entries of ``kin`` that are angles (radians); the rest are metres."""
    mask = np.zeros(n_kin(n_joints), dtype=bool)
    mask[0:3] = True
    mask[6:9] = True
    mask[12 + 2 :: 3] = True
    return mask


def rot_x(a: float) -> FloatArray:
    """Rotation matrix about x by ``a`` radians."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> FloatArray:
    """Rotation matrix about y by ``a`` radians."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> FloatArray:
    """Rotation matrix about z by ``a`` radians."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def skew(v: FloatArray) -> FloatArray:
    """Cross-product matrix: ``skew(v) @ w == np.cross(v, w)``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def se3_from_tau(tau: FloatArray) -> FloatArray:
    """4x4 transform from ``tau = [rx, ry, rz, tx, ty, tz]`` (R = Rz Ry Rx)."""
    T = np.eye(4)
    T[:3, :3] = rot_z(tau[2]) @ rot_y(tau[1]) @ rot_x(tau[0])
    T[:3, 3] = tau[3:6]
    return T


def tau_from_se3(T: FloatArray) -> FloatArray:
    """Inverse of :func:`se3_from_tau` (ry in [-pi/2, pi/2]; singular at ry = +-pi/2)."""
    R = T[:3, :3]
    ry = -np.arcsin(np.clip(R[2, 0], -1.0, 1.0))
    rx = np.arctan2(R[2, 1], R[2, 2])
    rz = np.arctan2(R[1, 0], R[0, 0])
    return np.array([rx, ry, rz, T[0, 3], T[1, 3], T[2, 3]])


def euler_rotation_derivatives(r: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Derivatives dR/drx, dR/dry, dR/drz of ``R = Rz(rz) Ry(ry) Rx(rx)``."""
    Rx, Ry, Rz = rot_x(r[0]), rot_y(r[1]), rot_z(r[2])
    return (
        Rz @ Ry @ Rx @ skew(E_X),
        Rz @ Ry @ skew(np.array([0.0, 1.0, 0.0])) @ Rx,
        skew(E_Z) @ Rz @ Ry @ Rx,
    )


def dh_link(theta: float, d: float, a: float, alpha: float) -> FloatArray:
    """Standard DH link ``A = Rz(theta) Tz(d) Tx(a) Rx(alpha)`` (maps frame l into frame l-1)."""
    A = np.eye(4)
    A[:3, :3] = rot_z(theta) @ rot_x(alpha)
    A[:3, 3] = rot_z(theta) @ np.array([a, 0.0, d])
    return A


def inv_se3(T: FloatArray) -> FloatArray:
    """Inverse of a 4x4 rigid transform."""
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


@dataclass(frozen=True)
class ChainJacobians:
    """Jacobians of ``p_d = T_ds(kin, theta) @ p_s`` for N points.

    Attributes:
        d_kin: (N, 3, 12 + 3L) derivative of each p_d with respect to ``kin``.
        d_theta: (N, 3, L) derivative with respect to the joint angles (rad).
        d_point: (3, 3) derivative with respect to the input point p_s (same for all points).
    """

    d_kin: FloatArray
    d_theta: FloatArray
    d_point: FloatArray


def split_kin(kin: FloatArray, n_joints: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Split ``kin`` into ``tau_s`` (6), ``tau_d`` (6) and ``dh`` (L, 3) rows ``[d, a, alpha]``."""
    kin = np.asarray(kin, dtype=float)
    if kin.shape != (n_kin(n_joints),):
        raise ValueError(f"kin must have {n_kin(n_joints)} entries for L={n_joints}, got {kin.shape}")
    return kin[0:6], kin[6:12], kin[12:].reshape(n_joints, 3)


def T_eb(dh: FloatArray, theta: FloatArray) -> FloatArray:
    """End effector from base, ``inv(A_1 ... A_L)`` (4x4); identity for L = 0."""
    T_be = np.eye(4)
    for (d, a, alpha), th in zip(dh, theta, strict=True):
        T_be = T_be @ dh_link(th, d, a, alpha)
    return inv_se3(T_be)


def T_ds(kin: FloatArray, theta: FloatArray, n_joints: int) -> FloatArray:
    """Static-to-dynamic camera transform ``T_ds(theta)`` (paper eq. 5), 4x4."""
    tau_s, tau_d, dh = split_kin(kin, n_joints)
    theta = np.asarray(theta, dtype=float).reshape(n_joints)
    return se3_from_tau(tau_d) @ T_eb(dh, theta) @ se3_from_tau(tau_s)


def transform_points(
    kin: FloatArray, theta: FloatArray, p_s: FloatArray, n_joints: int, jacobians: bool = True
) -> tuple[FloatArray, ChainJacobians | None]:
    """Map static-camera points into the dynamic camera: ``p_d = T_ds(kin, theta) @ p_s``.

    Args:
        kin: kinematic parameters (12 + 3L), see module docstring.
        theta: joint angles (L,), radians.
        p_s: (N, 3) points in the static-camera frame, metres.
        n_joints: L.
        jacobians: also return the analytic Jacobians.

    Returns:
        p_d (N, 3) and, if requested, :class:`ChainJacobians`.

    Derivation. With ``q_0 = p_b = R_bs p_s + t_bs`` and
    ``q_l = inv(A_l) q_{l-1} = Rx(-alpha_l) (Rz(-theta_l) q_{l-1} - a_l e_x - d_l e_z)``,
    ``p_e = q_L`` and ``p_d = R_de p_e + t_de``:

    * d p_d / d t_de = I, d p_d / d r_de,k = (dR_de/dr_k) p_e;
    * d p_d / d tau_s = R_db [ (dR_bs/dr_k) p_s | I ] with R_db = R_de R_eb;
    * d q_l / d theta_l = -Rx(-alpha_l) (e_z x Rz(-theta_l) q_{l-1}),
      d q_l / d d_l = -Rx(-alpha_l) e_z, d q_l / d a_l = -e_x, d q_l / d alpha_l = -e_x x q_l,
      each carried to the dynamic camera by d p_d / d q_l = R_de prod_{k=L..l+1} Rx(-alpha_k) Rz(-theta_k).
    """
    tau_s, tau_d, dh = split_kin(kin, n_joints)
    theta = np.asarray(theta, dtype=float).reshape(n_joints)
    p_s = np.asarray(p_s, dtype=float).reshape(-1, 3)
    R_bs = rot_z(tau_s[2]) @ rot_y(tau_s[1]) @ rot_x(tau_s[0])
    R_de = rot_z(tau_d[2]) @ rot_y(tau_d[1]) @ rot_x(tau_d[0])

    # forward pass through the links: q[l] is the point in link frame l (q[0] in the base frame)
    q = [p_s @ R_bs.T + tau_s[3:6]]
    link_rot = []  # rotation part of inv(A_l): Rx(-alpha_l) Rz(-theta_l)
    for (d, a, alpha), th in zip(dh, theta, strict=True):
        Rxm = rot_x(-alpha)
        link_rot.append(Rxm @ rot_z(-th))
        q.append((q[-1] @ rot_z(-th).T - a * E_X - d * E_Z) @ Rxm.T)
    p_e = q[-1]
    p_d = p_e @ R_de.T + tau_d[3:6]
    if not jacobians:
        return p_d, None

    n = p_s.shape[0]
    L = n_joints
    d_kin = np.zeros((n, 3, n_kin(L)))
    d_theta = np.zeros((n, 3, L))

    # tau_d
    for k, dR in enumerate(euler_rotation_derivatives(tau_d[0:3])):
        d_kin[:, :, 6 + k] = p_e @ dR.T
    d_kin[:, :, 9:12] = np.eye(3)

    # carry[l] = d p_d / d q_l, built from the end effector backwards
    carry = [np.zeros((3, 3))] * (L + 1)
    carry[L] = R_de
    for l in range(L, 0, -1):
        carry[l - 1] = carry[l] @ link_rot[l - 1]
    R_db = carry[0]

    # tau_s
    for k, dR in enumerate(euler_rotation_derivatives(tau_s[0:3])):
        d_kin[:, :, k] = p_s @ (R_db @ dR).T
    d_kin[:, :, 3:6] = R_db

    link_jacobians(dh, theta, q, carry, d_kin, d_theta)
    R_ds = R_db @ R_bs
    return p_d, ChainJacobians(d_kin=d_kin, d_theta=d_theta, d_point=R_ds)


def link_jacobians(
    dh: FloatArray,
    theta: FloatArray,
    q: list[FloatArray],
    carry: list[FloatArray],
    d_kin: FloatArray,
    d_theta: FloatArray,
) -> None:
    """Fill the DH-link columns of ``d_kin`` and all of ``d_theta`` (:func:`transform_points`, in place).

    ``q[l]`` (N, 3) are the points in link frame l (q[0] in the base frame, metres) and ``carry[l]``
    = d p_d / d q_l (3x3); see the derivation in :func:`transform_points`.
    """
    for l in range(1, dh.shape[0] + 1):
        d, a, alpha = dh[l - 1]
        th = theta[l - 1]
        Rxm = rot_x(-alpha)
        C = carry[l]
        rotated = q[l - 1] @ rot_z(-th).T  # Rz(-theta_l) q_{l-1}
        z_cross = np.zeros_like(rotated)  # e_z x rotated = [-y, x, 0]
        z_cross[:, 0], z_cross[:, 1] = -rotated[:, 1], rotated[:, 0]
        dq_dtheta = -z_cross @ Rxm.T
        dq_dalpha = np.zeros_like(q[l])  # -(e_x x q_l) = [0, z, -y]
        dq_dalpha[:, 1], dq_dalpha[:, 2] = q[l][:, 2], -q[l][:, 1]
        col = 12 + 3 * (l - 1)
        d_theta[:, :, l - 1] = dq_dtheta @ C.T
        d_kin[:, :, col + 0] = C @ (-Rxm @ E_Z)
        d_kin[:, :, col + 1] = C @ (-E_X)
        d_kin[:, :, col + 2] = dq_dalpha @ C.T


def inverse_transform_points(
    kin: FloatArray, theta: FloatArray, p_d: FloatArray, n_joints: int, jacobians: bool = True
) -> tuple[FloatArray, ChainJacobians | None]:
    """Map dynamic-camera points into the static camera: ``p_s = inv(T_ds(kin, theta)) @ p_d``.

    Jacobians follow from differentiating ``p_d = T_ds p_s`` implicitly:
    ``d p_s / d x = -R_ds^T (d (T_ds p) / d x)|_{p = p_s}`` for any parameter x, and
    ``d p_s / d p_d = R_ds^T``.
    """
    T = T_ds(kin, theta, n_joints)
    R_ds = T[:3, :3]
    p_d = np.asarray(p_d, dtype=float).reshape(-1, 3)
    p_s = (p_d - T[:3, 3]) @ R_ds
    if not jacobians:
        return p_s, None
    _, J = transform_points(kin, theta, p_s, n_joints, jacobians=True)
    assert J is not None
    d_kin = -np.einsum("ji,njk->nik", R_ds, J.d_kin)
    d_theta = -np.einsum("ji,njk->nik", R_ds, J.d_theta)
    return p_s, ChainJacobians(d_kin=d_kin, d_theta=d_theta, d_point=R_ds.T)


def d_T_ds_tangent(kin: FloatArray, theta: FloatArray, n_joints: int) -> tuple[FloatArray, FloatArray]:
    """Jacobians of ``T_ds`` in its local (gtsam Pose3, right-perturbation) tangent space.

    Returns ``(J_kin (6, 12+3L), J_theta (6, L))`` with rows ``[omega (rad), v (m)]`` such that
    ``T_ds(x + dx) ~= T_ds(x) @ Exp(J dx)``. Computed from the point Jacobians of three
    probe points: for ``T Exp(xi)``, ``d (T p) = R (omega x p + v)``.
    """
    T = T_ds(kin, theta, n_joints)
    R = T[:3, :3]
    probes = np.vstack([np.zeros(3), np.eye(3)])
    _, J = transform_points(kin, theta, probes, n_joints, jacobians=True)
    assert J is not None
    out = []
    for block in (J.d_kin, J.d_theta):
        local = np.einsum("ji,njk->nik", R, block)  # R^T dp, per probe: omega x p + v
        v = local[0]
        # local[1 + i] - v = omega x e_i ; (omega x e_x) = [0, w_z, -w_y], (omega x e_y) = [-w_z, 0, w_x]
        wx = (local[2] - v)[2]
        wy = -(local[1] - v)[2]
        wz = (local[1] - v)[1]
        out.append(np.vstack([wx, wy, wz, v]))
    return out[0], out[1]


# ------------------------------------------------------------------ batched over snapshots


def _rot_z_batch(a: FloatArray) -> FloatArray:
    """(K, 3, 3) rotations about z by the angles ``a`` (K,), radians."""
    c, s = np.cos(a), np.sin(a)
    R = np.zeros((a.shape[0], 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R


def _inv_dh_links(dh_l: FloatArray, theta_l: FloatArray) -> FloatArray:
    """(K, 4, 4) ``inv(A_l(theta_l))`` for K angles (rad) of one DH link ``[d, a, alpha]``.

    ``A_l = [Rz(theta) Rx(alpha), Rz(theta) (a e_x + d e_z)]`` so
    ``inv(A_l) = [Rx(-alpha) Rz(-theta), -Rx(-alpha) (a e_x + d e_z)]``.
    """
    d, a, alpha = dh_l
    Rxm = rot_x(-alpha)
    out = np.zeros((theta_l.shape[0], 4, 4))
    out[:, :3, :3] = Rxm @ _rot_z_batch(-theta_l)
    out[:, :3, 3] = -Rxm @ np.array([a, 0.0, d])
    out[:, 3, 3] = 1.0
    return out


def _inv_se3_batch(T: FloatArray) -> FloatArray:
    """(K, 4, 4) inverses of rigid transforms (K, 4, 4)."""
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(T[:, :3, :3], 1, 2)
    Ti[:, :3, :3] = Rt
    Ti[:, :3, 3] = -np.einsum("kij,kj->ki", Rt, T[:, :3, 3])
    Ti[:, 3, 3] = 1.0
    return Ti


def adjoint_batch(T: FloatArray) -> FloatArray:
    """(K, 6, 6) adjoints of rigid transforms (K, 4, 4) in gtsam's tangent order ``[omega, v]``:
    ``Ad_T = [[R, 0], [skew(t) R, R]]``, so that ``T Exp(xi) T^-1 = Exp(Ad_T xi)``."""
    R, t = T[:, :3, :3], T[:, :3, 3]
    S = np.zeros((T.shape[0], 3, 3))
    S[:, 0, 1], S[:, 0, 2], S[:, 1, 2] = -t[:, 2], t[:, 1], -t[:, 0]
    S[:, 1, 0], S[:, 2, 0], S[:, 2, 1] = t[:, 2], -t[:, 1], t[:, 0]
    Ad = np.zeros((T.shape[0], 6, 6))
    Ad[:, :3, :3] = R
    Ad[:, 3:, 3:] = R
    Ad[:, 3:, :3] = S @ R
    return Ad


def _euler_body_rates(r: FloatArray) -> FloatArray:
    """(3, 3) columns ``w_k`` with ``dR/dr_k = R skew(w_k)`` for ``R = Rz Ry Rx`` (body rates of the
    three Euler angles): ``w_x = e_x``, ``w_y = Rx^T e_y``, ``w_z = (Ry Rx)^T e_z``."""
    Rx, Ry = rot_x(r[0]), rot_y(r[1])
    return np.column_stack([E_X, Rx.T @ np.array([0.0, 1.0, 0.0]), (Ry @ Rx).T @ E_Z])


def _tau_twists(tau: FloatArray) -> FloatArray:
    """(6, 6) columns: the right-perturbation twists ``[omega, v]`` of ``se3_from_tau(tau)`` per
    entry of ``tau``: rotations ``[w_k, 0]``, translations ``[0, R^T e_k]``."""
    X = np.zeros((6, 6))
    X[:3, :3] = _euler_body_rates(tau[:3])
    X[3:, 3:] = se3_from_tau(tau)[:3, :3].T
    return X


def _dh_twists(dh_l: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Right-perturbation twists of ``A_l``: ``(xi_theta (6,), Xi (6, 3))`` with columns for
    ``[d, a, alpha]``, i.e. ``A_l(p + dp) = A_l Exp(xi dp)``:
    ``xi_theta = [0, sin al, cos al, 0, a cos al, -a sin al]``, ``xi_d = [0, 0, 0, 0, sin al, cos al]``,
    ``xi_a = [0, 0, 0, 1, 0, 0]``, ``xi_alpha = [1, 0, 0, 0, 0, 0]``."""
    _, a, al = dh_l
    s, c = np.sin(al), np.cos(al)
    xi_theta = np.array([0.0, s, c, 0.0, a * c, -a * s])
    Xi = np.zeros((6, 3))
    Xi[4, 0], Xi[5, 0] = s, c
    Xi[3, 1] = 1.0
    Xi[0, 2] = 1.0
    return xi_theta, Xi


def T_ds_batch(kin: FloatArray, thetas: FloatArray, n_joints: int) -> FloatArray:
    """(K, 4, 4) ``T_ds(theta_i)`` (paper eq. 5) for the joint angles ``thetas`` (K, L), radians."""
    return _chain_products(kin, thetas, n_joints)[0]


def _chain_products(kin: FloatArray, thetas: FloatArray, n_joints: int) -> tuple[FloatArray, list[FloatArray]]:
    """``T_ds`` (K, 4, 4) and the partial products ``Q_l = inv(A_{l-1}) ... inv(A_1) T_bs`` for
    l = 1 .. L + 1 (``Q_1 = T_bs``, ``Q_{L+1} = T_eb T_bs``), each (K, 4, 4)."""
    tau_s, tau_d, dh = split_kin(kin, n_joints)
    thetas = np.asarray(thetas, dtype=float)
    if thetas.ndim != 2 or thetas.shape[1] != n_joints:
        raise ValueError(f"thetas must be (K, {n_joints}), got {thetas.shape}")
    K = thetas.shape[0]
    Q = [np.broadcast_to(se3_from_tau(tau_s), (K, 4, 4))]
    for l in range(n_joints):
        Q.append(_inv_dh_links(dh[l], thetas[:, l]) @ Q[-1])
    return se3_from_tau(tau_d) @ Q[-1], Q


def d_T_ds_tangent_batch(
    kin: FloatArray, thetas: FloatArray, n_joints: int
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`d_T_ds_tangent` for K joint-angle vectors at once, by the adjoint of each factor.

    With ``T_ds = T_de inv(A_L) ... inv(A_1) T_bs`` and right perturbations
    ``T(x + dx) ~= T Exp(J dx)``:

    * ``T_bs`` (last factor): its own twist, ``J = xi``;
    * ``T_de``: ``J = Ad(inv(Q_{L+1})) xi`` with ``Q_{L+1} = T_eb T_bs``;
    * link l: ``inv(A_l Exp(xi dp)) = Exp(-xi dp) inv(A_l)``, so ``J = -Ad(inv(Q_{l+1})) xi``.

    Args:
        kin: kinematic parameters (12 + 3L).
        thetas: (K, L) joint angles, radians.

    Returns:
        ``(T_ds (K, 4, 4), J_kin (K, 6, 12 + 3L), J_theta (K, 6, L))``, rows ``[omega (rad), v (m)]``.
    """
    tau_s, tau_d, dh = split_kin(kin, n_joints)
    T, Q = _chain_products(kin, thetas, n_joints)
    K, L = T.shape[0], n_joints
    J_kin = np.zeros((K, 6, n_kin(L)))
    J_theta = np.zeros((K, 6, L))
    J_kin[:, :, 0:6] = _tau_twists(tau_s)
    Ad = [adjoint_batch(_inv_se3_batch(q)) for q in Q]  # Ad[l] = Ad(inv(Q_{l+1})), l = 0 .. L
    J_kin[:, :, 6:12] = Ad[L] @ _tau_twists(tau_d)
    for l in range(L):
        xi_theta, Xi = _dh_twists(dh[l])
        J_theta[:, :, l] = -Ad[l + 1] @ xi_theta
        J_kin[:, :, 12 + 3 * l : 15 + 3 * l] = -Ad[l + 1] @ Xi
    return T, J_kin, J_theta
