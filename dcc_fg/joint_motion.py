"""Does the dynamic camera's motion show every joint moving? Rotation-only tests on PnP poses.

:func:`check_joint_motion` runs before a calibration or an automatic initialization: the relative
rotations must spread along as many directions as the joints need (:func:`rotation_spread`), and for
L >= 3 they must not be those of a two-joint chain (:func:`two_joint_report`). Frames as in
:mod:`factors.chain` (docs/architecture.md):
``s`` static camera, ``d`` dynamic camera, ``t`` target; ``R_sd,i`` is the rotation of snapshot
i's ``T_sd = T_st inv(T_dt)`` from PnP in both cameras.

Two moving joints rotate the dynamic camera about an axis ``u`` fixed in s followed by an axis
``b`` fixed in d, so ``u^T R_sd,i b = cos(twist)`` in every snapshot: the vectors ``R_sd,i^T u``
lie in one plane with normal ``b``. An L = 3 mechanism with one joint that never moves is such a
two-joint chain (joint 1 locked: ``u`` is joint 2's axis and ``b`` joint 3's; joint 2 locked:
joints 1 and 3; joint 3 locked: joints 1 and 2), while three moving joints leave no such plane.
How far off every plane a third joint moves the vectors depends on its range and the geometry, and
at small ranges it is comparable to the PnP noise, so the fit is weighted by each snapshot's PnP
rotation covariance and judged by its chi-square.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import NDArray

from dcc_fg.data import CalibrationDataset
from dcc_fg.init import mean_pose, pnp_pose
from dcc_fg.model import GimbalCalibration
from factors import chain
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]
MIN_ROTATION_SPREAD_RAD = np.deg2rad(0.5)  # RMS rotation spread below which a direction counts as flat
FLAT_JOINT_SPAN_RAD = np.deg2rad(2.0)  # initial angles spanning less than this: the joint never moves
MAX_COS_TWIST = np.cos(np.deg2rad(20.0))  # planes of nearly parallel axis pairs are not searched (see _plane_chi2)
GRID_POINTS = 2000  # hemisphere grid of the axis u
N_REFINED = 4  # well-separated grid minima refined locally
# Two moving joints fit at about 1 per degree of freedom (at most 2.0 over 110 simulated two-joint and
# locked-joint L = 3 data sets); moving L = 3 mechanisms at 2.0 (one random geometry whose third
# rotation is 0.16 deg RMS), 7.7, 8.8 and above (pinned L = 3: 346 and above).
MAX_CHI2_PER_DOF = 3.0


def never_moves(joint: int, span: float) -> str:
    """The message for a joint (0-based) whose initial angles span only ``span`` rad."""
    return (
        f"joint {joint + 1} never moves during the recording (its angles span only {span:.2e} rad): "
        f"joint {joint + 1} is unobservable"
    )


@dataclass
class TwoAxisFit:
    """The best two-joint description of the relative rotations.

    Attributes:
        chi2: weighted sum of squared distances from the plane (PnP noise only: ~dof).
        dof: degrees of freedom, K - 3.
        rms: unweighted RMS distance from the plane, rad (~ the rotation no two-joint chain explains).
        u: first axis, unit, in s.
        b: second axis (the plane normal), unit, in d.
    """

    chi2: float
    dof: int
    rms: float
    u: FloatArray
    b: FloatArray


def _pnp_rotation_covariance(
    camera: CameraModel, p_t: FloatArray, uv: FloatArray, T_ct: FloatArray
) -> tuple[FloatArray, float, int]:
    """Gauss-Newton covariance of a PnP pose's rotation for unit pixel variance.

    Returns (3x3 covariance, rad^2 per px^2, of the right perturbation ``R_ct exp(phi)``, phi in the
    target frame, marginal over the translation; sum of squared pixel residuals; residual rows)."""
    p_c = p_t @ T_ct[:3, :3].T + T_ct[:3, 3]
    uv_hat, J_p = camera.project(p_c, jacobian=True)
    assert J_p is not None
    J_rot = -J_p @ T_ct[:3, :3] @ np.array([chain.skew(p) for p in p_t])
    J = np.concatenate([J_rot, J_p], axis=2).reshape(-1, 6)
    e = (uv_hat - uv).ravel()
    return np.linalg.inv(J.T @ J)[:3, :3], float(e @ e), e.size


def snapshot_rotations(data: CalibrationDataset) -> tuple[FloatArray, FloatArray]:
    """Per snapshot, ``R_sd,i`` (K, 3, 3) from PnP in both cameras and the covariance (K, 3, 3), rad^2,
    of its right perturbation ``R_sd exp(dphi)`` (dphi in d) under pixel noise.

    dphi = R_dt (phi_st - phi_dt) for target-frame perturbations of the two PnP rotations, so its
    covariance is ``R_dt (C_st + C_dt) R_dt^T``; each camera's pixel variance is estimated from its
    PnP residuals over all snapshots.
    """
    P = data.target_points
    R_sd, parts = [], []
    ss = {"s": 0.0, "d": 0.0}
    n = {"s": 0, "d": 0}
    for snap in data.snapshots:
        poses = {}
        for key, cam, obs in (("s", data.static_camera, snap.static), ("d", data.dynamic_camera, snap.dynamic)):
            T_ct = pnp_pose(cam, P[obs.ids], obs.pixels)
            C, e2, m = _pnp_rotation_covariance(cam, P[obs.ids], obs.pixels, T_ct)
            ss[key] += e2
            n[key] += m
            poses[key] = (T_ct[:3, :3], C)
        (R_st, C_s), (R_dt, C_d) = poses["s"], poses["d"]
        R_sd.append(R_st @ R_dt.T)
        parts.append((R_dt, C_s, C_d))
    K = len(R_sd)
    var = {key: ss[key] / max(n[key] - 6 * K, 1) for key in ss}
    cov = np.array([R_dt @ (var["s"] * C_s + var["d"] * C_d) @ R_dt.T for R_dt, C_s, C_d in parts])
    return np.array(R_sd), cov


def _plane_chi2(R_sd: FloatArray, cov: FloatArray, U: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """For candidate first axes U (M, 3) in s: the weighted best plane through ``r_i = R_sd,i^T u``.

    Each distance ``b . (r_i - mean)`` is weighted by its variance ``(r_i x b)^T cov_i (r_i x b)``
    (a rotation error dphi moves r_i by ``r_i x dphi``); the weights follow the normal ``b``, which
    starts unweighted and is re-fitted three times. A plane whose normal is within 20 deg of the
    vectors themselves (a nearly parallel axis pair) gets an infinite chi-square: when the joint
    ranges are small, the vectors' tight cluster always fits such a plane to second order.

    Returns (chi-square (M,), unweighted RMS distance (M,) in rad, normals b (M, 3) in d).
    """
    r = np.einsum("kji,mj->mki", R_sd, U)
    x = r - r.mean(axis=1, keepdims=True)
    b = np.linalg.eigh(np.einsum("mki,mkj->mij", x, x))[1][:, :, 0]
    for it in range(4):
        g = np.cross(r, b[:, None, :])
        w = 1.0 / np.maximum(np.einsum("mki,kij,mkj->mk", g, cov, g), 1e-18)
        mean = np.einsum("mk,mki->mi", w, r) / w.sum(axis=1, keepdims=True)
        x = r - mean[:, None, :]
        if it < 3:
            b = np.linalg.eigh(np.einsum("mk,mki,mkj->mij", w, x, x))[1][:, :, 0]
    dist = np.einsum("mki,mi->mk", x, b)
    chi2 = np.einsum("mk,mk->m", w, dist * dist)
    rms = np.sqrt(np.mean((dist - dist.mean(axis=1, keepdims=True)) ** 2, axis=1))
    flat = np.abs(np.einsum("mi,mi->m", mean / np.linalg.norm(mean, axis=1, keepdims=True), b)) >= MAX_COS_TWIST
    return np.where(flat, np.inf, chi2), rms, b


def two_axis_fit(data: CalibrationDataset) -> TwoAxisFit:
    """The two-joint structure ``u^T R_sd,i b = const`` that best fits the snapshots' PnP rotations
    (module docstring): ``u`` from a hemisphere grid, then shrinking local grids around the best
    few well-separated grid points, by the chi-square of :func:`_plane_chi2`."""
    R_sd, cov = snapshot_rotations(data)
    k = np.arange(GRID_POINTS) + 0.5
    z = k / GRID_POINTS
    phi = np.pi * (1.0 + 5.0**0.5) * k
    U = np.column_stack([np.sqrt(1.0 - z * z) * np.cos(phi), np.sqrt(1.0 - z * z) * np.sin(phi), z])
    step = max(1, 100_000 // R_sd.shape[0])  # candidates per block: (step, K, 3) arrays of ~2.4 MB
    chi2 = np.concatenate([_plane_chi2(R_sd, cov, U[a : a + step])[0] for a in range(0, len(U), step)])
    picked: list[FloatArray] = []
    for idx in np.argsort(chi2):
        if not np.isfinite(chi2[idx]) or len(picked) == N_REFINED:
            break
        if all(abs(float(U[idx] @ p)) < np.cos(np.deg2rad(10.0)) for p in picked):
            picked.append(U[idx])
    best = TwoAxisFit(np.inf, R_sd.shape[0] - 3, np.inf, U[0], U[0])
    g = np.linspace(-1.0, 1.0, 9)
    for u in picked:
        step = 0.06
        for _ in range(5):
            E = np.linalg.svd(u.reshape(1, 3))[2][1:]
            cand = np.vstack([u, (u + step * (g[:, None, None] * E[0] + g[None, :, None] * E[1])).reshape(-1, 3)])
            cand /= np.linalg.norm(cand, axis=1, keepdims=True)
            c, _, _ = _plane_chi2(R_sd, cov, cand)
            u = cand[int(np.argmin(c))]
            step /= 4.0
        c, rms, B = _plane_chi2(R_sd, cov, u.reshape(1, 3))
        if c[0] < best.chi2:
            best = TwoAxisFit(float(c[0]), best.dof, float(rms[0]), u, B[0])
    return best


def locked_joint_of_three(
    fit: TwoAxisFit, T_ds_pnp: FloatArray, kin: FloatArray, thetas0: FloatArray
) -> tuple[int, FloatArray] | None:
    """Which joint of an L = 3 mechanism never moves, from the initial kinematics' joint axes.

    With joint j locked, the two-joint structure's ``u`` (in s) is the first moving joint's axis and
    ``b`` (in d) the second's (module docstring). Per hypothesis j (0-based), the score is the mean
    of ``|u . a_p|`` and ``|b . R_ds a_q|`` over the snapshots, (p, q) the moving pair and ``a`` the
    joint axes in s of ``kin`` at ``thetas0``. Returns (j, the three scores) when the best score is
    at least 0.9 and 0.15 above the others, else None.
    """
    scores = np.zeros(3)
    for T, th in zip(T_ds_pnp, np.asarray(thetas0, float), strict=True):
        Jt = chain.d_T_ds_tangent(kin, th, 3)[1][:3]
        axes = Jt / np.linalg.norm(Jt, axis=0)
        for j in range(3):
            p, q = [k for k in range(3) if k != j]
            scores[j] += 0.5 * (abs(float(fit.u @ axes[:, p])) + abs(float(fit.b @ (T[:3, :3] @ axes[:, q]))))
    scores /= len(T_ds_pnp)
    order = np.argsort(scores)[::-1]
    if scores[order[0]] >= 0.9 and scores[order[0]] - scores[order[1]] >= 0.15:
        return int(order[0]), scores
    return None


def two_joint_report(
    data: CalibrationDataset,
    T_ds_pnp: FloatArray,
    L: int,
    min_rms: float,
    thetas0: FloatArray | None = None,
    initial: GimbalCalibration | None = None,
) -> str | None:
    """The error message for L >= 3 joints whose snapshots' rotations a two-joint chain explains
    (:func:`two_axis_fit`: chi-square per degree of freedom below ``MAX_CHI2_PER_DOF`` and RMS below
    ``min_rms`` rad), or None when the rotations need a third joint.

    The locked joint is named from ``thetas0`` (initial angles (K, L) spanning < 2 deg) or, for
    L = 3, from ``initial``'s joint axes (:func:`locked_joint_of_three`); otherwise the message says
    that the images alone do not tell which joint.
    """
    fit = two_axis_fit(data)
    per_dof = fit.chi2 / max(fit.dof, 1)
    if not (per_dof < MAX_CHI2_PER_DOF and fit.rms < min_rms):
        return None
    R_sd = np.transpose(T_ds_pnp[:, :3, :3], (0, 2, 1))
    twist = np.mean(np.abs(np.einsum("i,kij,j->k", fit.u, R_sd, fit.b)))
    msg = (
        f"{data.source}: the dynamic camera's rotations relative to the static camera are those of a chain of "
        f"only two joints (an axis fixed in the static camera, then one fixed in the dynamic camera, "
        f"{np.rad2deg(np.arccos(min(float(twist), 1.0))):.0f} deg apart): they fit it to {np.rad2deg(fit.rms):.2f} "
        f"deg RMS, chi-square {per_dof:.2f} per degree of freedom against the PnP noise (below "
        f"{MAX_CHI2_PER_DOF:.0f} and {np.rad2deg(min_rms):.1f} deg counts as two joints), but {L} joints need a "
        "third independent rotation"
    )
    named = ""
    if thetas0 is not None:
        span = np.ptp(np.asarray(thetas0, float), axis=0)
        flat = [j for j in range(L) if span[j] < FLAT_JOINT_SPAN_RAD]
        if len(flat) == L - 2:
            named = "; ".join(never_moves(j, span[j]) for j in flat)
        elif L == 3 and initial is not None:
            found = locked_joint_of_three(fit, T_ds_pnp, initial.kin, thetas0)
            if found is not None:
                j, scores = found
                p, q = [k for k in range(3) if k != j]
                named = (
                    f"joint {j + 1} never moves during the recording (by the initial kinematics the two moving "
                    f"axes are those of joints {p + 1} and {q + 1}: match {scores[j]:.2f}, against "
                    f"{scores[p]:.2f} and {scores[q]:.2f} for the other pairs): joint {j + 1} is unobservable"
                )
    if named:
        return msg + "; " + named
    return msg + (
        "; a joint never moves, or moves too little to show in the images (images alone do not tell which joint: "
        "give joint readings, e.g. joints.csv or a JointState topic, or a gimbal.yaml)"
    )


# ------------------------------------------------------------------ the check before a calibration


def rotation_spread(T_ds: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Principal directions of the K relative rotations ``R_ds,i``: the rotation vectors
    ``Log(R_mean^T R_ds,i)`` about the chordal mean (right perturbations, static-camera frame).

    Returns:
        (RMS spread (3,) in rad, largest first; the directions as the columns of a 3x3 matrix).
    """
    R_mean = mean_pose(T_ds)[:3, :3]
    r = np.array([gtsam.Rot3.Logmap(gtsam.Rot3(R_mean.T @ T[:3, :3])) for T in T_ds])
    r -= r.mean(axis=0)
    _, sv, Vt = np.linalg.svd(r, full_matrices=False)
    return sv / np.sqrt(len(r)), Vt.T


def check_joint_motion(
    data: CalibrationDataset,
    T_ds_pnp: FloatArray,
    L: int,
    thetas0: FloatArray | None = None,
    initial: GimbalCalibration | None = None,
) -> None:
    """Refuse (ValueError) data in which the dynamic camera does not rotate about enough axes.

    Each moving joint rotates the dynamic camera about its own axis, so L joints with non-parallel
    axes give relative rotations (``T_ds`` from PnP in both cameras) that spread along min(L, 3)
    directions. A joint that never moves leaves a direction flat (RMS spread below
    ``MIN_ROTATION_SPREAD_RAD``; PnP noise is ~0.1-0.3 deg here), and the DH parameters next to it
    become unobservable. In encoderless mode the joint angles are free per snapshot, so the
    degeneracy is only approximate at a fitted start and the information-matrix check can miss it;
    the solve then "succeeds" with meaningless joint angles.

    This sees every locked joint for L <= 2. For L >= 3 two moving joints already spread the
    rotations over 3 directions (the second joint's axis turns with the first), so the rotations are
    also tested for the structure of a two-joint chain (:func:`two_axis_fit`): an axis fixed in s
    followed by one fixed in d. When that fits within the PnP noise (chi-square per degree of
    freedom below ``MAX_CHI2_PER_DOF``) and leaves less than ``MIN_ROTATION_SPREAD_RAD`` RMS
    unexplained, at most two joints move (see :func:`two_joint_report`; a mechanism whose third joint
    moves so little that its rotation is lost in the PnP noise is refused too).

    Which joint is flat is not visible in the images alone (one joint rotating about a fixed axis
    looks the same whichever it is); it is named from ``thetas0`` (initial angles spanning < 2 deg)
    or else from ``initial``'s joint axes (for L <= 2 the axis the observed rotations do not use; for
    L = 3 the pair of axes the two-joint structure matches, :func:`locked_joint_of_three`).
    """
    spread, V = rotation_spread(T_ds_pnp)
    need = min(L, 3)
    n_dirs = int(np.sum(spread > MIN_ROTATION_SPREAD_RAD))
    if n_dirs >= need:
        if L >= 3:
            report = two_joint_report(data, T_ds_pnp, L, MIN_ROTATION_SPREAD_RAD, thetas0, initial)
            if report is not None:
                raise ValueError(report)
        return
    n_flat = need - n_dirs
    msg = (
        f"{data.source}: the dynamic camera rotates about only {n_dirs} independent axis direction(s) relative "
        f"to the static camera (RMS spread {', '.join(f'{np.rad2deg(x):.2f}' for x in spread)} deg along the "
        f"principal directions; below {np.rad2deg(MIN_ROTATION_SPREAD_RAD):.1f} deg counts as none), but {L} "
        f"joint(s) need {need}"
    )
    named: list[str] = []
    if thetas0 is not None:
        named = flat_joints_by_angles(np.asarray(thetas0, float), n_flat)
    if not named and initial is not None and thetas0 is not None:
        named = flat_joints_by_axes(initial, np.asarray(thetas0, float), V[:, :n_dirs], n_flat)
    if named:
        msg += "; " + "; ".join(named)
    else:
        msg += (
            "; a joint never moves or the joints move together (images alone do not tell which joint: give "
            "joint readings, e.g. joints.csv or a JointState topic, or a gimbal.yaml)"
        )
    raise ValueError(msg)


def flat_joints_by_angles(thetas0: FloatArray, n_flat: int) -> list[str]:
    """Messages naming the ``n_flat`` joints whose initial angles (K, L) span least, when each spans
    under ``FLAT_JOINT_SPAN_RAD``; else none."""
    span = np.ptp(thetas0, axis=0)
    flat = [j for j in np.argsort(span, kind="stable")[:n_flat] if span[j] < FLAT_JOINT_SPAN_RAD]
    if len(flat) != n_flat:
        return []
    return [never_moves(j, span[j]) for j in flat]


def flat_joints_by_axes(initial: GimbalCalibration, thetas0: FloatArray, M: FloatArray, n_flat: int) -> list[str]:
    """Messages naming the ``n_flat`` joints whose axes (by ``initial``'s kinematics at ``thetas0``, in
    the static-camera frame) lie least inside the observed rotation directions ``M`` (3, n_dirs),
    when they stand apart from the others (mean direction cosine gap > 0.3); else none."""
    L = initial.n_joints
    use = np.zeros(L)
    for th in thetas0:
        Jt = chain.d_T_ds_tangent(initial.kin, th, L)[1][:3]
        axes = Jt / np.linalg.norm(Jt, axis=0)
        use += np.linalg.norm(M.T @ axes, axis=0) / len(thetas0)
    order = np.argsort(use, kind="stable")
    gap = use[order[n_flat]] - use[order[n_flat - 1]] if n_flat < L else 1.0
    if gap <= 0.3:
        return []
    return [
        f"joint {j + 1} never moves during the recording (by the initial kinematics, its axis is "
        f"{np.rad2deg(np.arccos(min(use[j], 1.0))):.0f} deg away from every observed rotation): "
        f"joint {j + 1} is unobservable"
        for j in order[:n_flat]
    ]
