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
  their covariance and the eigenvalue measures the misfit, so only ``w_1`` is searched. To first
  order in the joint motion ``w_1`` lies in the plane of the two principal rotation directions;
  where in that plane is a second-order effect that PnP noise swamps at small joint ranges, so
  evenly spaced in-plane starts are each completed by the closed form and the pose-level fit
  (which also uses the translations) decides. theta_1 follows from where ``R_sd_i b_2`` lies
  around ``w_1``, theta_2 from the remaining rotation about ``b_2``.

Then, for any L, the translations ``t_sb``, ``d_l, a_l`` (l < L) and ``t_ed`` enter
``t_sd_i`` linearly once the rotations are known: one linear least-squares solve.

L = 3: three non-parallel axes span all rotations, so the rotations alone do not determine
the axes (no closed form here). For given axes ``w_1`` (in s), ``b_3`` (in d) and twists the
joint angles follow from the rotations by closed-form IK (each snapshot on the theta_2 branch
whose lever arms fit: a joint-2 range that crosses the coplanar-axes singularity at 0 or pi
needs both branches) and the translations from the linear solve above, so only these 6
parameters are searched, on the translation misfit that remains
(variable projection, :class:`_ThreeJointProjection`): Levenberg-Marquardt from random starts,
then the pose-level fit (:func:`dcc_fg.init.pose_level_refine`) from the best distinct minima.
Those minima are ranked on a cost that weighs every snapshot alike (1 mrad / 1 mm), which does not
rank the corner-level minima: on nearly degenerate chains the corner-level global minimum can lie in
a basin that no kept axis-search minimum leads to (random L = 3 family, rendered members 11, 14, 29:
the pose-level fit started from the truth had a higher equal-weight RMS than the best candidate,
0.517 / 0.804 / 0.307 vs 0.507 / 0.755 / 0.281, yet led to the lowest corner-level cost). Whitened by
each snapshot's PnP information of ``T_ds`` (:meth:`dcc_fg.noise_floor.NoiseFloor.T_ds_whitening`), the
pose-level cost is the pose-level image of the corner-level cost and ranks its minima (there the truth
start's whitened minimum was the lowest of all on members 11 and 14, and on 29 second, 0.7 above a
minimum that is 1.8 chi-square worse at the corner level). :func:`whitened_hops` therefore refits the
candidates on that cost and explores it by basin hopping (random perturbations of the kinematics, each
refit in ~0.3 s instead of ~10 s for a corner-level solve); whitened minima deeper than every
candidate's become extra starts.

The hops perturb by 0.15 rad and cannot reach a basin whose axes lie far from every candidate's (member
14: joint 2's axis 76 deg away from the best candidate's, twists of 22-24 deg between consecutive axes).
The axis search is therefore also run on the whitened cost (:func:`whitened_axis_starts`): each
snapshot's lever-arm misfit ``t_sd(chain) - t_sd_i`` is weighed by its information with the rotation
marginalized (:func:`dcc_fg.noise_floor.translation_whitening`; with the IK reproducing the measured
rotation exactly, the right perturbation of ``T_ds`` is ``[0, t_sd_i - t_sd(chain)]``), and its best
minima, refit on the full whitened cost, join the hops' pool. On member 14 its best minimum (0.5 chi-square
23.8) lies below the truth's own whitened minimum (25.2) and the equal-weight candidates' best (33.8), and
the corner-level solve from it ends below the truth start; likewise on member 11 (29.6 vs 30.3). Starting
the equal-weight search at the truth's axes leaves that basin (it is not a minimum of the 1 mm cost).

Everything is refined afterwards: the pose-level LM fit, then the corner-level graph.
Frames and conventions: docs/architecture.md.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from dcc_fg.data import CalibrationDataset
from dcc_fg.init import (
    PoseLevelProblem,
    chordal_mean_rotation,
    levenberg_marquardt,
    mean_pose,
    pnp_pose,
    pose_level_refine,
)
from dcc_fg.joint_motion import check_joint_motion
from dcc_fg.model import GimbalCalibration
from dcc_fg.noise_floor import noise_floor, translation_whitening
from dcc_fg.util.errors import stage
from factors import chain

FloatArray = NDArray[np.float64]
log = logging.getLogger("dcc_fg.auto_init")
N_AXIS_STARTS = 4  # L = 2: starting joint-1 axes in the principal rotation plane
SCREEN_ITERATIONS = 30  # L = 2: pose-level LM iterations of the short fit that ranks the starts
N_SCREEN_KEEP = 2  # L = 2: starts carried on to the full pose-level fit
SCREEN_SNAPSHOTS = 40  # L = 2: at most this many snapshots rank the starts (random-geometry study: 25 suffice)
N_L3_STARTS = 24  # L = 3: random starts of the axis search
N_L3_KEEP = 6  # L = 3: best distinct axis-search minima carried on to the pose-level fit and the corner-level solve
# Pose-level fits of the candidates stop early: the corner-level solve of dcc_fg.global_fit decides
# between them (a full fit crept for 200 iterations along the flat directions of nearly degenerate
# L = 3 mechanisms).
CANDIDATE_MAX_ITERATIONS = 40
CANDIDATE_REL_TOL = 1e-6
SAME_MINIMUM = 1e-4  # rad, m: candidates predicting the same T_ds this closely are one start
SAME_AXIS_MINIMUM = 1e-5  # L = 3: axis-search minima whose costs agree this closely (relative) are one
N_HOPS = 60  # L = 3: basin-hopping refits on the whitened pose-level cost
HOP_FROM = 3  # L = 3: hops start from the best this many whitened minima found so far, in turn
HOP_ROTATION_SIGMA = 0.15  # rad: perturbation of the rotational kinematic entries (Euler angles, twists)
HOP_TRANSLATION_SIGMA = 0.01  # m: perturbation of the translational entries (mount offsets, d, a)
N_HOP_KEEP = 2  # L = 3: at most this many hop minima become extra starts
N_WHITENED_AXIS_KEEP = 3  # L = 3: minima of the whitened axis search that seed the hops
# A hop minimum becomes a start (one more corner-level solve, ~10 s) when its whitened cost (0.5 chi-square)
# is below every candidate's by more than this. The whitened cost ranks the corner-level minima only
# roughly (rendered members 11, 14, 29: the truth start's minimum lowest or second; on member 14 two
# candidates 8.8 chi-square apart at the corner level were ranked the other way, 8 apart in the whitened
# cost), so a hop minimum not clearly deeper than a candidate is most likely that candidate's basin again.
HOP_MARGIN = 0.25
HOP_DISTINCT = 0.05  # two hop minima whose whitened costs agree this closely (0.5 chi-square) are one
HOP_ITERATIONS = 300  # LM iterations of each whitened refit (~0.3 s for 25 snapshots)
HOP_REL_TOL = 1e-10  # relative cost decrease that ends a whitened refit


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


def rotation_vectors(R: FloatArray) -> FloatArray:
    """Axis-angle vectors (K, 3), rad, of rotation matrices (K, 3, 3)."""
    return Rotation.from_matrix(R).as_rotvec()


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


def _rot_z_batch(a: FloatArray) -> FloatArray:
    """Rotations about z by the angles ``a`` (rad), shape ``a.shape + (3, 3)``."""
    c, sn = np.cos(a), np.sin(a)
    R = np.zeros(np.shape(a) + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1], R[..., 2, 2] = c, -sn, sn, c, 1.0
    return R


def _prefix_rotations(thetas: FloatArray, alphas: FloatArray) -> FloatArray:
    """Per snapshot, ``G_l = prod_{k<l} (Rz(theta_k) Rx(alpha_k)) Rz(theta_l)`` for l = 1..L: (K, L, 3, 3)."""
    K, L = thetas.shape
    out = np.zeros((K, L, 3, 3))
    P = np.broadcast_to(np.eye(3), (K, 3, 3))
    for lnk in range(L):
        out[:, lnk] = P @ _rot_z_batch(thetas[:, lnk])
        P = out[:, lnk] @ chain.rot_x(alphas[lnk])
    return out


# ------------------------------------------------------------------ closed forms


def _rotation_one_joint(R_sd: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Joint axis w1 (in s) and relative angles theta_i - theta_0 of an L = 1 mechanism."""
    logs = rotation_vectors(R_sd @ R_sd[0].T)
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


def principal_rotation_directions(R_sd: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Principal directions (in s) of the rotations ``R_sd_i`` about their chordal mean.

    The rotation vectors are those of the left perturbations ``R_sd_i R_mean^T`` (static-camera
    frame), centred on their mean. Returns (RMS spread (3,) in rad, largest first; the directions
    as the columns of a 3x3 matrix).
    """
    R_mean = chordal_mean_rotation(R_sd)
    r = rotation_vectors(R_sd @ R_mean.T)
    r -= r.mean(axis=0)
    _, sv, Vt = np.linalg.svd(r, full_matrices=False)
    return sv / np.sqrt(len(r)), Vt.T


def _pair_from_axis(R_sd: FloatArray, u: FloatArray) -> tuple[FloatArray, FloatArray, float]:
    """(w1, b2, cos alpha_1) for a candidate joint-1 axis ``u`` (in s): ``b2`` (in d) is the normal
    of the best plane through the vectors ``R_sd_i^T u``, cos alpha_1 their mean offset along it."""
    _, V = _axis_pair_cost(R_sd, u.reshape(1, 3))
    b2 = V[0]
    c = float(np.mean(np.einsum("kji,j,i->k", R_sd, u, b2)))
    return u, b2, float(np.clip(c, -1.0, 1.0))


def _two_joint_axis_candidates(R_sd: FloatArray, n: int = N_AXIS_STARTS) -> list[tuple[FloatArray, FloatArray, float]]:
    """``n`` starting axes ``w1`` (in s), evenly spread over the plane of the two principal
    rotation directions, each with its ``b2`` (in d) and cos(alpha_1) (see :func:`_pair_from_axis`).

    To first order in the joint motion, every rotation is about a combination of joint 1's axis
    and joint 2's (mid-range) axis, so ``w1`` lies in the principal plane; where in it is a
    second-order effect that PnP noise swamps at joint ranges of +-10 deg (the minimum of the
    rotation-only cost was 5-21 deg from the true axis on 6 random geometries, often at a
    near-parallel pair). The pose-level fit has two basins here (joint 1's axis taken for joint 1
    or for joint 2), so the starts cover the whole plane and the fit decides.
    """
    _, V = principal_rotation_directions(R_sd)
    phis = np.pi * (np.arange(n) + 0.5) / n
    return [_pair_from_axis(R_sd, np.cos(p) * V[:, 0] + np.sin(p) * V[:, 1]) for p in phis]


def _rotation_two_joints(R_sd: FloatArray) -> tuple[FloatArray, FloatArray, float]:
    """Closed-form axes of an L = 2 mechanism: the ``w1`` in the principal rotation plane (1 deg
    grid) with the lowest rotation-only misfit, with its ``b2`` and cos(alpha_1)."""
    _, V = principal_rotation_directions(R_sd)
    phis = np.deg2rad(np.arange(180.0))
    U = np.outer(np.cos(phis), V[:, 0]) + np.outer(np.sin(phis), V[:, 1])
    cost, _ = _axis_pair_cost(R_sd, U)
    return _pair_from_axis(R_sd, U[int(np.argmin(cost))])


def _translation_design(R_sb: FloatArray, thetas: FloatArray, alphas: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Design of the linear translation model of :func:`_translation_fit`: ``(A (K, 3, n), P (3, 2))``
    with ``t_sd_i = A_i x``, ``x = [t_sb in the plane normal to joint 1's axis (2), (d_l, a_l) for
    l < L, t_ed (3)]`` and ``P`` the basis of that plane."""
    K, L = thetas.shape
    w1 = R_sb[:, 2]
    # basis of the plane perpendicular to w1
    P = np.linalg.svd(w1.reshape(1, 3))[2][1:].T  # (3, 2)
    G = R_sb @ _prefix_rotations(thetas, alphas)  # (K, L, 3, 3), frame l's axes in s
    n = 2 + 2 * (L - 1) + 3
    A = np.zeros((K, 3, n))
    A[:, :, 0:2] = P
    for lnk in range(L - 1):
        A[:, :, 2 + 2 * lnk] = G[:, lnk, :, 2]  # d_l along z_{l-1}
        A[:, :, 3 + 2 * lnk] = G[:, lnk, :, 0]  # a_l along x_l
    A[:, :, n - 3 :] = G[:, L - 1]
    return A, P


def _weighted(weights: FloatArray | None, A: FloatArray, target: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The translation model's design ``A`` (K, 3, n) and ``target`` (K, 3) with each snapshot's rows
    multiplied by ``weights`` (K, 3, 3); unchanged when ``weights`` is None."""
    if weights is None:
        return A, target
    return weights @ A, np.einsum("kij,kj->ki", weights, target)


def _translation_fit(
    T_sd: FloatArray, R_sb: FloatArray, thetas: FloatArray, alphas: FloatArray, weights: FloatArray | None = None
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Linear least squares for ``t_sb`` (perpendicular to joint 1's axis: ``tau_s.tz = 0``),
    ``(d_l, a_l)`` for l < L and ``t_ed``, given all rotations (``T_sd`` (K, 4, 4), ``R_sb``, joint
    angles (K, L) and twists, rad), each snapshot's misfit multiplied by ``weights`` (K, 3, 3) when given
    (:func:`dcc_fg.noise_floor.translation_whitening`). Returns (t_sb, da (L-1, 2), t_ed, residual (3K,)
    in m, or whitened with ``weights``)."""
    K, L = thetas.shape
    A, P = _translation_design(R_sb, thetas, alphas)
    n = A.shape[2]
    A, target = _weighted(weights, A, T_sd[:, :3, 3])
    A2, b = A.reshape(3 * K, n), target.ravel()
    x = np.linalg.lstsq(A2, b, rcond=None)[0]
    return P @ x[0:2], x[2 : 2 + 2 * (L - 1)].reshape(L - 1, 2), x[n - 3 :], A2 @ x - b


def _branch_translation_fit(
    T_sd: FloatArray,
    R_sb: FloatArray,
    branches: tuple[FloatArray, FloatArray],
    alphas: FloatArray,
    weights: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """:func:`_translation_fit` with each snapshot's theta_2 branch chosen by the fit (L = 3).

    The two closed-form IK branches (``theta_2`` and the mirror solution) reproduce the same
    rotation; only the lever arms tell them apart. A joint-2 range that crosses 0 or pi (where the
    three axes are coplanar) needs both. Alternation from the better single branch: fit the
    translations, give each snapshot the branch whose translation misfit is smaller under that fit,
    refit, until no snapshot changes (at most 4 rounds). ``weights``: as in :func:`_translation_fit`.

    Returns (t_sb, da, t_ed, residual (3K,) in m or whitened, joint angles (K, 3) of the chosen branches).
    """
    weighted = [_weighted(weights, _translation_design(R_sb, th, alphas)[0], T_sd[:, :3, 3]) for th in branches]
    designs, target = [A for A, _ in weighted], weighted[0][1]
    P = _translation_design(R_sb, branches[0][:1], alphas)[1]

    def solve(A: FloatArray) -> tuple[FloatArray, FloatArray]:
        A2 = A.reshape(-1, A.shape[2])
        x = np.linalg.lstsq(A2, target.ravel(), rcond=None)[0]
        return x, A2 @ x - target.ravel()

    solutions = [solve(A) for A in designs]
    k = int(np.argmin([float(r @ r) for _, r in solutions]))
    choice = np.full(target.shape[0], k)
    x, r = solutions[k]
    for _ in range(4):
        miss = [np.sum((A @ x - target) ** 2, axis=1) for A in designs]
        new_choice = (miss[1] < miss[0]).astype(int)
        if np.array_equal(new_choice, choice):
            break
        x_new, r_new = solve(np.where(new_choice[:, None, None] == 1, designs[1], designs[0]))
        if float(r_new @ r_new) >= float(r @ r):
            break
        choice, x, r = new_choice, x_new, r_new
    thetas = np.where(choice[:, None] == 1, branches[1], branches[0])
    n, L = x.size, thetas.shape[1]
    return P @ x[0:2], x[2 : 2 + 2 * (L - 1)].reshape(L - 1, 2), x[n - 3 :], r, thetas


def _translation_solve(
    T_sd: FloatArray, R_sb: FloatArray, thetas: FloatArray, alphas: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`_translation_fit` without the residual: (t_sb, da (L-1, 2), t_ed)."""
    t_sb, da, t_ed, _ = _translation_fit(T_sd, R_sb, thetas, alphas)
    return t_sb, da, t_ed


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
    dh[:, 2] = _wrap(np.asarray(alphas, dtype=float))
    dh[-1] = 0.0
    return np.concatenate([tau_s, tau_d, dh.ravel()])


def _end_mount(W: FloatArray, rel_last: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Given ``W_i = Rz(theta_L,i) R_ed`` up to a common offset of theta_L, choose the offset so that
    tau_d's Euler pitch is 0 and return (theta_L (K,), R_ed)."""
    th = _wrap(rel_last - np.angle(np.mean(np.exp(1j * rel_last))))
    R_ed = chordal_mean_rotation(np.array([chain.rot_z(-t) @ Wi for t, Wi in zip(th, W, strict=True)]))
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
        w1, b2, c = axes if axes is not None else _rotation_two_joints(R_sd)
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


def rotation_ik_three_joints(Q: FloatArray, alphas: FloatArray, th2_sign: float = 1.0) -> tuple[FloatArray, FloatArray]:
    """Joint angles with ``Rz(t1) Rx(a1) Rz(t2) Rx(a2) Rz(t3) = Q_i`` (three joints, closed form).

    Args:
        Q: (K, 3, 3) rotations ``R_bs R_sd_i R_ed^T``.
        alphas: twists (alpha_1, alpha_2, ...), rad.
        th2_sign: branch of theta_2 (the other branch is the same fit with the signs of theta_2,
            alpha_1, alpha_2 and the link offsets changed, so one branch is enough for a search).

    Returns:
        (angles (K, 3) in rad, misfit (K, 3): ``vee(skew(model^T Q))``, sin of the rotation error
        times its axis, nonzero only where ``Q`` is out of reach of the twists).
    """
    a1, a2 = float(alphas[0]), float(alphas[1])
    denom = np.sin(a1) * np.sin(a2)
    c2 = (np.cos(a1) * np.cos(a2) - Q[:, 2, 2]) / denom if abs(denom) > 1e-9 else np.ones(Q.shape[0])
    t2 = th2_sign * np.arccos(np.clip(c2, -1.0, 1.0))
    M = chain.rot_x(a1) @ _rot_z_batch(t2) @ chain.rot_x(a2)  # (K, 3, 3)
    u = M[:, :, 2]  # Q e_z = Rz(t1) u
    t1 = np.arctan2(Q[:, 1, 2], Q[:, 0, 2]) - np.arctan2(u[:, 1], u[:, 0])
    r = M[:, 2, :]  # e_z^T Q = r Rz(t3): the row vector turned by -t3
    t3 = np.arctan2(r[:, 1], r[:, 0]) - np.arctan2(Q[:, 2, 1], Q[:, 2, 0])
    E = np.einsum("kji,kjl->kil", _rot_z_batch(t1) @ M @ _rot_z_batch(t3), Q)
    misfit = 0.5 * np.stack([E[:, 2, 1] - E[:, 1, 2], E[:, 0, 2] - E[:, 2, 0], E[:, 1, 0] - E[:, 0, 1]], axis=-1)
    return _wrap(np.column_stack([t1, t2, t3])), misfit


def _unit_offset(v0: FloatArray, p: FloatArray) -> FloatArray:
    """Unit vector ``v0 + p[0] e_1 + p[1] e_2`` (normalized), e_1, e_2 spanning the plane normal to v0."""
    B = np.linalg.svd(v0.reshape(1, 3))[2][1:]
    v = v0 + p @ B
    return v / np.linalg.norm(v)


class _ThreeJointProjection:
    """L = 3 pose-level fit with everything but the joint axes eliminated (variable projection).

    For joint-1 axis ``w1`` (in s), joint-3 axis ``b3`` (in d) and twists alpha_1, alpha_2 (the
    6 rotational degrees of freedom of the chain that the gauge leaves), the joint angles follow
    from the rotations by closed-form IK (exactly, where reachable) and the translations
    (``t_sb``, ``d_l, a_l`` for l < 3, ``t_ed``) from one linear least-squares solve. The residual
    is the translation misfit over 1 mm and the unreachable rotation misfit over 1 mrad, the
    whitening of :func:`dcc_fg.init.pose_level_refine`. Three non-parallel axes reproduce any
    rotation, so the translations (lever arms of a few cm) carry all the information about the
    axes; this 6-parameter problem is cheap enough for many random starts.

    ``translation_whitening`` (K, 3, 3), when given, replaces the 1 mm of the translation misfit by
    each snapshot's information of its lever arm (:func:`dcc_fg.noise_floor.translation_whitening`):
    the axis search on the whitened pose-level cost (module docstring).
    """

    def __init__(self, T_ds: FloatArray, translation_whitening: FloatArray | None = None) -> None:
        self.T_sd = np.array([chain.inv_se3(T) for T in T_ds])
        self.R_sd = self.T_sd[:, :3, :3]
        self.weights = translation_whitening
        self.translation_unit = 1e-3 if translation_whitening is None else 1.0

    def solve(
        self, w1: FloatArray, b3: FloatArray, alphas: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
        """(R_bs, R_ed, angles (K, 3), whitened residual, translation solution (t_sb, da, t_ed) stacked)."""
        R_bs, R_ed = base_rotation(w1), base_rotation(b3)  # R_ed maps b3 (in d) onto the e z axis
        al = np.array([alphas[0], alphas[1], 0.0])
        Q = R_bs @ self.R_sd @ R_ed.T
        thetas_p, misfit = rotation_ik_three_joints(Q, al, 1.0)
        thetas_m, _ = rotation_ik_three_joints(Q, al, -1.0)
        t_sb, da, t_ed, r_t, thetas = _branch_translation_fit(self.T_sd, R_bs.T, (thetas_p, thetas_m), al, self.weights)
        r = np.concatenate([r_t / self.translation_unit, misfit.ravel() / 1e-3])
        return R_bs, R_ed, thetas, r, np.concatenate([t_sb, da.ravel(), t_ed])

    def residual(self, p: FloatArray, w1_0: FloatArray, b3_0: FloatArray) -> FloatArray:
        return self.solve(_unit_offset(w1_0, p[0:2]), _unit_offset(b3_0, p[2:4]), p[4:6])[3]

    def kin(self, w1: FloatArray, b3: FloatArray, alphas: FloatArray) -> tuple[FloatArray, FloatArray]:
        """kin (21) and joint angles (K, 3) in the auto-init gauge (module docstring)."""
        R_bs, R_ed, thetas, _, _ = self.solve(w1, b3, alphas)
        W = _rot_z_batch(thetas[:, 2]) @ R_ed  # = Rz(theta_3) R_ed
        thetas[:, 2], R_ed = _end_mount(W, thetas[:, 2])
        al = np.array([alphas[0], alphas[1], 0.0])
        t_sb, da, t_ed, _ = _translation_fit(self.T_sd, R_bs.T, thetas, al, self.weights)
        return _assemble(R_bs.T, t_sb, R_ed, t_ed, al, da), thetas


def multistart_three_joints(
    T_ds: FloatArray, free: NDArray[np.bool_], n_starts: int = N_L3_STARTS, seed: int = 0
) -> tuple[FloatArray, FloatArray, float]:
    """L = 3: the best of :func:`three_joint_candidates`. Returns (kin, joint angles (K, 3), fit RMS)."""
    return three_joint_candidates(T_ds, free, n_starts, seed)[0]


def three_joint_candidates(
    T_ds: FloatArray, free: NDArray[np.bool_], n_starts: int = N_L3_STARTS, seed: int = 0
) -> list[tuple[FloatArray, FloatArray, float]]:
    """L = 3: the 6-parameter axis search of :class:`_ThreeJointProjection` (Levenberg-Marquardt)
    from ``n_starts`` random axes and twists, then the full pose-level fit from its ``N_L3_KEEP``
    best distinct minima (costs within ``SAME_AXIS_MINIMUM`` relative count once: the same minimum
    reached from several starts), lowest fit RMS first: [(kin, joint angles (K, 3), fit RMS)]."""
    proj = _ThreeJointProjection(T_ds)
    out = []
    for w1, b3, alphas in axis_search(proj, n_starts, seed)[:N_L3_KEEP]:
        kin0, th0 = proj.kin(w1, b3, alphas)
        out.append(
            pose_level_refine(
                kin0, 3, T_ds, th0, free, [2], True, max_iterations=CANDIDATE_MAX_ITERATIONS, rel_tol=CANDIDATE_REL_TOL
            )
        )
    return sorted(out, key=lambda c: c[2])


def axis_search(
    proj: _ThreeJointProjection, n_starts: int = N_L3_STARTS, seed: int = 0
) -> list[tuple[FloatArray, FloatArray, FloatArray]]:
    """L = 3: Levenberg-Marquardt on the 6 parameters of ``proj`` from ``n_starts`` random axes and
    twists (in (0.3, pi - 0.3) rad); its distinct minima (costs within ``SAME_AXIS_MINIMUM`` relative
    count once: the same minimum reached from several starts, or its mirror image), lowest cost first,
    as ``(w1 in s, b3 in d, twists (2,) rad)``."""
    rng = np.random.default_rng(seed)
    minima: list[tuple[float, FloatArray, FloatArray, FloatArray]] = []
    for _ in range(n_starts):
        w1_0, b3_0 = rng.normal(size=(2, 3))
        w1_0 /= np.linalg.norm(w1_0)
        b3_0 /= np.linalg.norm(b3_0)
        p0 = np.concatenate([np.zeros(4), rng.uniform(0.3, np.pi - 0.3, size=2)])
        sol = least_squares(proj.residual, p0, method="lm", args=(w1_0, b3_0), max_nfev=400)
        w1, b3 = _unit_offset(w1_0, sol.x[0:2]), _unit_offset(b3_0, sol.x[2:4])
        minima.append((float(np.mean(sol.fun**2)), w1, b3, sol.x[4:6]))
    minima.sort(key=lambda m: m[0])
    kept: list[tuple[float, FloatArray, FloatArray, FloatArray]] = []
    for m in minima:  # the same minimum reached from several starts (or its mirror image) counts once
        if all(abs(m[0] - k[0]) > SAME_AXIS_MINIMUM * max(k[0], 1e-12) for k in kept):
            kept.append(m)
    return [(w1, b3, alphas) for _, w1, b3, alphas in kept]


def whitened_axis_starts(
    T_ds: FloatArray, whitening: FloatArray, n_starts: int = N_L3_STARTS, seed: int = 0
) -> list[tuple[FloatArray, FloatArray]]:
    """L = 3: the axis search (:func:`axis_search`) on the whitened pose-level cost: each snapshot's
    lever-arm misfit weighed by its information (:func:`dcc_fg.noise_floor.translation_whitening` of
    ``whitening``, (K, 6, 6)) instead of 1 mm. Returns the :data:`N_WHITENED_AXIS_KEEP` best distinct
    minima as ``(kin, joint angles (K, 3))`` in the auto-init gauge, not refit (module docstring)."""
    proj = _ThreeJointProjection(T_ds, translation_whitening(whitening))
    return [proj.kin(w1, b3, alphas) for w1, b3, alphas in axis_search(proj, n_starts, seed)[:N_WHITENED_AXIS_KEEP]]


def _rotational_entries(n_joints: int) -> NDArray[np.bool_]:
    """Mask of the rotational kinematic entries (the Euler angles of both mounts, the twists)."""
    mask = np.zeros(chain.n_kin(n_joints), dtype=bool)
    mask[[0, 1, 2, 6, 7, 8]] = True
    mask[14::3] = True
    return mask


def whitened_hops(
    fits: list[tuple[FloatArray, FloatArray, float]],
    T_ds: FloatArray,
    whitening: FloatArray,
    free: NDArray[np.bool_],
    n_hops: int = N_HOPS,
    seed: int = 0,
    seeds: Sequence[tuple[FloatArray, FloatArray]] = (),
) -> list[tuple[FloatArray, FloatArray, float]]:
    """L = 3: pose-level minima of the *whitened* cost deeper than every one of ``fits`` (module docstring).

    Each fit is refit on ``sum_i |W_i Log(T_ds_i^-1 T_ds(kin, theta_i))|^2`` (``whitening`` W, (K, 6, 6)),
    and so is each of ``seeds`` (``(kin, joint angles)``, e.g. :func:`whitened_axis_starts`: they join the
    minima found but not the reference "best refit of ``fits``"),
    then ``n_hops`` times one of the :data:`HOP_FROM` best minima so far (in turn) has its free
    kinematic entries perturbed (:data:`HOP_ROTATION_SIGMA`, :data:`HOP_TRANSLATION_SIGMA`) and is
    refit from its joint angles. Returns up to :data:`N_HOP_KEEP` minima (lowest first, whitened costs
    at least :data:`HOP_DISTINCT` apart) whose whitened cost is below the best refit of ``fits`` by more
    than :data:`HOP_MARGIN`, as ``(kin, joint angles (K, 3), equal-weight RMS)`` like ``fits``.
    """

    def refit(kin: FloatArray, th: FloatArray) -> tuple[FloatArray, FloatArray, float]:
        problem = PoseLevelProblem(kin, 3, T_ds, th, free, [2], True, 1e-3, 1e-3, whitening)
        x, r = levenberg_marquardt(problem, HOP_ITERATIONS, HOP_REL_TOL)
        k, t = problem.unpack(x)
        data = r[: 6 * problem.K]
        return k, t.copy(), 0.5 * float(data @ data)

    pool = sorted((refit(kin, th) for kin, th, _ in fits), key=lambda m: m[2])
    if not pool:
        return []
    best_start = pool[0][2]
    pool = sorted(pool + [refit(kin, th) for kin, th in seeds], key=lambda m: m[2])
    rng = np.random.default_rng(seed)
    rot = _rotational_entries(3) & free
    trans = ~_rotational_entries(3) & free
    for h in range(n_hops):
        kin, th, _ = pool[h % min(HOP_FROM, len(pool))]
        kin = kin.copy()
        kin[rot] += rng.normal(0.0, HOP_ROTATION_SIGMA, int(rot.sum()))
        kin[trans] += rng.normal(0.0, HOP_TRANSLATION_SIGMA, int(trans.sum()))
        pool.append(refit(kin, th))
        pool.sort(key=lambda m: m[2])
    out: list[tuple[FloatArray, FloatArray, float]] = []
    costs: list[float] = []
    for kin, th, cost in pool:
        if not (np.isfinite(cost) and cost < best_start - HOP_MARGIN) or len(out) >= N_HOP_KEEP:
            break
        if all(abs(cost - c) > HOP_DISTINCT for c in costs):
            equal = PoseLevelProblem(kin, 3, T_ds, th, free, [2], True, 1e-3, 1e-3)
            r = equal.residual(equal.x0(), False)[0][: 6 * equal.K]
            out.append((kin, th, float(np.sqrt(r @ r / r.size))))
            costs.append(cost)
    return out


def _axes_of(kin: FloatArray, T_ds: FloatArray) -> tuple[FloatArray, FloatArray, float]:
    """(w1 in s, b2 in d, cos alpha_1) of L = 2 kinematics in the auto-init gauge (``A_2 = Rz``)."""
    w1 = chain.se3_from_tau(kin[0:6])[2, :3]  # R_bs^T e_z
    b2 = chain.se3_from_tau(kin[6:12])[:3, 2]  # R_de e_z: joint 2's axis is the e frame's z
    R_sd = np.transpose(T_ds[:, :3, :3], (0, 2, 1))
    return w1, b2, float(np.clip(np.mean(np.einsum("i,kij,j->k", w1, R_sd, b2)), -1.0, 1.0))


def _two_joint_candidates(T: FloatArray, free: NDArray[np.bool_]) -> tuple[FloatArray, FloatArray, float]:
    """L = 2: the best of :func:`two_joint_candidates`."""
    return two_joint_candidates(T, free)[0]


def two_joint_candidates(T: FloatArray, free: NDArray[np.bool_]) -> list[tuple[FloatArray, FloatArray, float]]:
    """L = 2: the closed form from each start of :func:`_two_joint_axis_candidates`, a short
    pose-level fit of each (``SCREEN_ITERATIONS``), then the full fit of the ``N_SCREEN_KEEP`` best;
    lowest fit RMS first.

    (A short fit does not rank the two basins reliably, since both can still be descending a flat
    valley, so more than one is carried to the full fit. Over 250 random geometries of
    :func:`dcc_fg.sim.calibration_scene.random_mechanism` (25 snapshots) this reached the optimum of
    the fit started from the truth in every case; the previous search, over the minima of the
    rotation-only cost with an early exit below a fixed RMS, missed it in 2.)

    With more than ``SCREEN_SNAPSHOTS`` snapshots the starts are ranked on that many evenly spread
    ones, and the winner's axes start the closed form and the fit on all of them (the cost of the
    fit grows with the snapshots; 500 snapshots took 16 s instead of 3 s without this).
    """
    K = T.shape[0]
    sub = np.unique(np.linspace(0, K - 1, min(K, SCREEN_SNAPSHOTS)).round().astype(int))
    T_sub = T[sub]
    screened = []
    for axes in _two_joint_axis_candidates(np.array([chain.inv_se3(x)[:3, :3] for x in T])):
        kin0, th0 = closed_form_low_dof(T_sub, 2, axes)
        screened.append(pose_level_refine(kin0, 2, T_sub, th0, free, [1], True, max_iterations=SCREEN_ITERATIONS))
    screened.sort(key=lambda c: c[2])
    limits = {"max_iterations": CANDIDATE_MAX_ITERATIONS, "rel_tol": CANDIDATE_REL_TOL}
    fits = sorted(
        (pose_level_refine(k, 2, T_sub, th, free, [1], True, **limits) for k, th, _ in screened[:N_SCREEN_KEEP]),  # type: ignore[arg-type]
        key=lambda c: c[2],
    )
    if sub.size == K:
        return fits
    out = []
    for fit in fits:
        kin0, th0 = closed_form_low_dof(T, 2, _axes_of(fit[0], T))
        out.append(pose_level_refine(kin0, 2, T, th0, free, [1], True, **limits))  # type: ignore[arg-type]
    return sorted(out, key=lambda c: c[2])


def distinct(
    fits: list[tuple[FloatArray, FloatArray, float]], n_joints: int
) -> list[tuple[FloatArray, FloatArray, float]]:
    """The fits (lowest RMS first) without repeats: two starts whose chains predict the same ``T_ds``
    for every snapshot (within ``SAME_MINIMUM`` rad and m) ended in the same pose-level minimum, also
    when their parameters differ by a symmetry of the DH parameterization (e.g. an axis and its
    negative with the angles' signs changed), and count once."""
    out: list[tuple[FloatArray, FloatArray, float]] = []
    predictions: list[FloatArray] = []
    for kin, th, rms in sorted(fits, key=lambda c: c[2]):
        T = chain.T_ds_batch(kin, th, n_joints)
        if not any(np.max(np.abs(T[:, :3, :] - P[:, :3, :])) < SAME_MINIMUM for P in predictions):
            out.append((kin, th, rms))
            predictions.append(T)
    return out


def auto_initialize(
    data: CalibrationDataset, n_joints: int, T_ds: FloatArray | None = None
) -> tuple[GimbalCalibration, FloatArray, float]:
    """Initial kinematics and joint angles with no gimbal.yaml: the best of :func:`auto_initial_candidates`.

    Returns:
        (initial calibration, joint angles (K, L) in rad, whitened RMS of the pose-level fit with
        1 mrad / 1 mm per unit). The gauge-fixed entries (module docstring) define the gauge the
        calibration keeps.
    """
    return auto_initial_candidates(data, n_joints, T_ds)[0]


def auto_initial_candidates(
    data: CalibrationDataset, n_joints: int, T_ds: FloatArray | None = None
) -> list[tuple[GimbalCalibration, FloatArray, float]]:
    """Distinct starting points of the calibration with no gimbal.yaml, best pose-level fit first.

    L = 0, 1: one (closed form); L = 2: the ``N_SCREEN_KEEP`` fits of the axis-plane starts; L = 3:
    the ``N_L3_KEEP`` best minima of the axis search, then up to ``N_HOP_KEEP`` minima of the whitened
    pose-level cost deeper than all of them (:func:`whitened_hops`). :func:`dcc_fg.global_fit.calibrate_global`
    solves the corner-level problem from each and keeps the lowest cost.

    Args:
        data: the calibration snapshots (snapshot ``joints`` are ignored).
        n_joints: L (0 to 3).
        T_ds: per-snapshot PnP ``T_ds`` (K, 4, 4) when already computed.

    Returns:
        [(initial calibration, joint angles (K, L) in rad, whitened RMS of the pose-level fit with
        1 mrad / 1 mm per unit)], lowest RMS first.
    """
    if n_joints < 0 or n_joints > 3:
        raise ValueError(f"automatic initialization supports 0 to 3 joints, got --joints {n_joints}")
    if not data.snapshots:
        raise ValueError(f"{data.source}: the snapshot list is empty")
    with stage("PnP", hint="check the camera intrinsics (--camchain) and the target description (--target)"):
        T = pnp_T_ds(data) if T_ds is None else T_ds
    K = T.shape[0]
    if n_joints > 0:
        with stage("joint-motion check"):
            check_joint_motion(data, T, n_joints)  # a joint that never moves: say so before fitting noise
    cams = {"static_camera": data.static_camera, "dynamic_camera": data.dynamic_camera}
    if n_joints == 0:
        kin = np.concatenate([np.zeros(6), chain.tau_from_se3(mean_pose(T))])
        return [(GimbalCalibration(kin, 0, **cams), np.zeros((K, 0)), float("nan"))]
    free = np.ones(chain.n_kin(n_joints), dtype=bool)
    last = 12 + 3 * (n_joints - 1)
    free[[2, 5, last, last + 1, last + 2]] = False
    with stage("automatic initialization", hint="give hand-measured initial kinematics (--gimbal G.yaml)"):
        if n_joints == 1:
            kin0, th0 = closed_form_low_dof(T, 1)
            fits = [pose_level_refine(kin0, 1, T, th0, free, [0], True)]
        elif n_joints == 2:
            fits = two_joint_candidates(T, free)
        else:
            fits = three_joint_candidates(T, free)
            floor = noise_floor(data)
            T_floor = floor.T_dt @ np.linalg.inv(floor.T_st)
            try:  # extra starts only: without a usable whitening the axis-search candidates remain
                W = floor.T_ds_whitening()
                fits += whitened_hops(fits, T_floor, W, free, seeds=whitened_axis_starts(T_floor, W))
            except np.linalg.LinAlgError as exc:
                log.warning("no basin hopping on the whitened pose-level cost (%s): the PnP information of "
                            "some image pair is singular; the axis-search starts remain", exc)  # fmt: skip
    return [(GimbalCalibration(kin, n_joints, **cams), th, rms) for kin, th, rms in distinct(fits, n_joints)]
