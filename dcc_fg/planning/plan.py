"""Next best snapshots: which joint angles (and target poses) most reduce the ``T_ds`` uncertainty over an
operating range, and when to stop.

Frames, symbols and the two prediction modes as in :mod:`dcc_fg.planning.predict`. Angles in rad
(degrees where a name says so), metres.

Expected information gain from simulated measurements with the current estimate. A candidate
snapshot at ``theta_c`` with the target at the pose :func:`~dcc_fg.planning.predict.place_targets`
chooses gives information ``Lambda_c`` on ``xi`` (target pose eliminated); its unknown joint angles are
eliminated too, ``Lambda'_c = Lambda_c - Lambda_c J_t A^-1 J_t^T Lambda_c``, so it adds
``U_c U_c^T`` to the information of the free kinematics, ``U_c = J_k^T W_c`` with ``W_c W_c^T =
Lambda'_c``. The covariance is updated by Woodbury, ``C' = C - C U (I + U^T C U)^-1 U^T C`` (6x6
inverse; it stays in the range of C, so gauge directions stay at zero). After the update the
predicted 1-sigma at every point g of the evaluation grid is ``Sigma_g = F_g C' F_g^T + N_g``
(``F_g = M_g J_k,g`` and ``N_g`` the snapshot's own noise in ``snapshot`` mode, ``N_g = 0`` in
``calibration`` mode (the default: the part of a snapshot's error that more calibration snapshots
reduce); ``F_g = J_k,g``, ``N_g = 0`` in ``kinematics`` mode).

Objective, per grid point the larger tolerance ratio ``q_g = max(sigma_rot / tol_rot, sigma_tra /
tol_tra)``: ``worst`` minimizes a smooth worst case, the power mean ``(mean_g q_g^p)^(1/p)`` with
``p = WORST_POWER`` (a plain max cannot tell two candidates apart while another corner of the range
stays worst), ``mean`` minimizes ``mean_g q_g``. Greedy: K times, the candidate with the lowest
objective after its update is taken and C updated (all candidates are scored at once: one matrix
product per chunk of candidates).

Stopping rule: the predicted worst 1-sigma over the grid (rotation and translation) is within the
tolerance. The plan stops there (fewer than K snapshots; none when the calibration already meets
it). When even perfect kinematics would not meet it (the snapshot mode's own noise ``N_g``, i.e. a
single snapshot's precision) the plan says so: more snapshots cannot help there.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dcc_fg.planning.predict import (
    MODES,
    KinematicsInformation,
    Placement,
    Prediction,
    candidate_poses,
    placement_at,
    predict,
    range_grid,
    snapshot_operators,
    view_information,
)
from dcc_fg.planning.range_spec import Tolerance, format_range
from factors import chain

FloatArray = NDArray[np.float64]

OBJECTIVES = ("worst", "mean")
WORST_POWER = 8.0
EVAL_PER_AXIS = 15  # evaluation grid of the objective: points per joint ...
EVAL_CAP = 1000  # ... capped at this many points
CANDIDATE_PER_AXIS = {1: 41, 2: 15, 3: 8}  # candidate joint angles per joint (limits included)
CHUNK_BYTES = 80e6  # memory of one chunk of candidate scores
VIEW_CHUNK = 2000  # candidate views whose information is computed at once


@dataclass
class PlannedSnapshot:
    """One proposed snapshot: joint angles (L,) rad, where to hold the target (see
    :meth:`~dcc_fg.planning.predict.Placement.describe`) and the predicted worst / mean 1-sigma over
    the range after it (rad, m)."""

    theta: FloatArray
    target: dict[str, Any]
    worst_rotation: float
    worst_translation: float
    mean_rotation: float
    mean_translation: float

    def to_dict(self, index: int) -> dict[str, Any]:
        return {
            "index": index,
            "joint_angles_deg": [round(float(np.degrees(x)), 4) for x in self.theta],
            "joint_angles_rad": [float(x) for x in self.theta],
            "target": self.target,
            "predicted_after": {
                "worst_rotation_mrad": self.worst_rotation * 1e3,
                "worst_translation_mm": self.worst_translation * 1e3,
                "mean_rotation_mrad": self.mean_rotation * 1e3,
                "mean_translation_mm": self.mean_translation * 1e3,
            },
        }


@dataclass
class Plan:
    """The proposed snapshots, the predicted accuracy now, the stopping state and the settings."""

    ranges: FloatArray
    tolerance: Tolerance
    objective: str
    mode: str
    k_requested: int
    now: dict[str, float]
    floor: dict[str, float]
    snapshots: list[PlannedSnapshot]
    reached: bool
    reason: str

    def to_dict(self) -> dict[str, Any]:
        """The ``plan.yaml`` document (schema in the README section; angles deg and rad, metres, mrad, mm)."""
        return {
            "format": "dcc-fg plan 1",
            "range_deg": [[round(float(np.degrees(x)), 9) for x in r] for r in self.ranges],
            "tolerance": {
                "rotation_mrad": self.tolerance.rotation * 1e3,
                "translation_mm": self.tolerance.translation * 1e3,
            },
            "objective": self.objective,
            "prediction": self.mode,
            "k_requested": self.k_requested,
            "predicted_now": self.now,
            "snapshot_noise_floor": self.floor,
            "snapshots": [s.to_dict(i + 1) for i, s in enumerate(self.snapshots)],
            "stop": {"tolerance_reached": self.reached, "reason": self.reason},
        }

    def text(self) -> str:
        """The list a person can follow."""
        L = self.ranges.shape[0]
        lines = [
            f"operating range {format_range(self.ranges)} deg; tolerance {self.tolerance.describe()} (worst 1-sigma of "
            f"T_ds over the range, {self.mode} prediction, objective {self.objective})",
            f"predicted now: worst {self.now['worst_rotation_mrad']:.3g} mrad / {self.now['worst_translation_mm']:.3g} "
            f"mm, mean {self.now['mean_rotation_mrad']:.3g} mrad / {self.now['mean_translation_mm']:.3g} mm",
        ]
        for i, s in enumerate(self.snapshots):
            angles = ", ".join(f"theta_{j + 1} = {np.degrees(s.theta[j]):7.2f} deg" for j in range(L))
            c = s.target["centre_in_static_camera_m"]
            side = "right" if c[0] >= 0 else "left"
            vert = "below" if c[1] >= 0 else "above"
            lines.append(
                f"{i + 1:3d}. {angles}; target {s.target['distance_m']:.2f} m from the static camera, centre "
                f"{abs(c[0]):.2f} m {side} / {abs(c[1]):.2f} m {vert} its optical axis, its face turned "
                f"{_turn(s.target['face_right_deg'], 'right', 'left')} and "
                f"{_turn(s.target['face_up_deg'], 'up', 'down')} "
                f"from facing the static camera squarely -> worst {s.worst_rotation * 1e3:.3g} mrad / "
                f"{s.worst_translation * 1e3:.3g} mm"
            )
        lines.append(("DONE: " if self.reached else "NOT YET: ") + self.reason)
        return "\n".join(lines)


def _turn(deg: float, positive: str, negative: str) -> str:
    return f"{abs(deg):.0f} deg {positive if deg >= 0 else negative}"


def _objective(q: FloatArray, objective: str) -> FloatArray:
    """Objective over the last axis of tolerance ratios ``q`` (module docstring)."""
    if objective == "mean":
        return q.mean(axis=-1)
    scale = np.max(q, axis=-1, keepdims=True)
    scale = np.where(scale > 0, scale, 1.0)
    return scale[..., 0] * np.mean((q / scale) ** WORST_POWER, axis=-1) ** (1.0 / WORST_POWER)


@dataclass
class _Grid:
    """The evaluation grid's operators: ``F`` (G, 6, n_free), ``N`` (G, 6, 6) and which points count."""

    F: FloatArray
    N: FloatArray
    keep: NDArray[np.bool_]


def _eval_grid(pred: Prediction, mode: str) -> _Grid:
    if mode in ("snapshot", "calibration"):
        M, N = snapshot_operators(pred.J_theta, pred.view_info)
        keep = pred.placement.ok
        if mode == "calibration":
            N = np.zeros_like(N)
        return _Grid((M @ pred.J_kin)[keep], N[keep], keep)
    G = len(pred.thetas)
    return _Grid(pred.J_kin, np.zeros((G, 6, 6)), np.ones(G, dtype=bool))


def _factors(Lam: FloatArray, Jt: FloatArray, Jk: FloatArray) -> FloatArray:
    """(N, n_free, 6) ``U`` for views of information ``Lam`` (N, 6, 6) on ``xi`` with ``T_ds`` Jacobians
    ``Jt`` (N, 6, L) and ``Jk`` (N, 6, n_free): the joint angles eliminated (module docstring)."""
    A = np.swapaxes(Jt, 1, 2) @ Lam @ Jt
    LJ = Lam @ Jt
    Lp = Lam - LJ @ np.linalg.pinv(A) @ np.swapaxes(LJ, 1, 2)
    w, V = np.linalg.eigh(0.5 * (Lp + np.swapaxes(Lp, 1, 2)))
    W = V * np.sqrt(np.maximum(w, 0.0))[:, None, :]
    return np.swapaxes(Jk, 1, 2) @ W


def _candidate_factors(pred: Prediction) -> FloatArray:
    """(Nc, n_free, 6) ``U_c`` of every view of a prediction (module docstring)."""
    return _factors(pred.view_info, pred.J_theta, pred.J_kin)


@dataclass
class _Candidates:
    """Candidate snapshots: (P, L) joint angles, their target poses (P), ``U`` (P, n_free, 6) and (P,)
    the index of each one's joint-angle vector among the candidate joint angles."""

    thetas: FloatArray
    placement: Placement
    U: FloatArray
    owner: NDArray[np.int64]


def candidate_views(info: KinematicsInformation, thetas: FloatArray) -> _Candidates:
    """Every target pose :func:`~dcc_fg.planning.predict.candidate_poses` offers at each joint-angle
    vector ``thetas`` (G, L) rad, with its rank update ``U`` (information computed in chunks of
    ``VIEW_CHUNK`` views)."""
    thetas = np.asarray(thetas, dtype=float).reshape(-1, info.n_joints)
    T, Jk_full, Jt = chain.d_T_ds_tangent_batch(info.kin, thetas, info.n_joints)
    Jk = Jk_full[:, :, info.free]
    placement, owner = candidate_poses(info.view, T)
    U = np.zeros((len(owner), int(info.free.sum()), 6))
    for a in range(0, len(owner), VIEW_CHUNK):
        idx = np.arange(a, min(a + VIEW_CHUNK, len(owner)))
        o = owner[idx]
        Lam = view_information(info.view, T[o], placement.take(idx))
        U[idx] = _factors(Lam, Jt[o], Jk[o])
    return _Candidates(thetas[owner], placement, U, owner)


def view_factors(info: KinematicsInformation, thetas: FloatArray, T_st: FloatArray) -> FloatArray:
    """(G, n_free, 6) ``U`` of snapshots at joint angles ``thetas`` (G, L) rad with the target at ``T_st``
    (G, 4, 4) in the static camera frame, m: what the planner adds for a pick (module docstring)."""
    thetas = np.asarray(thetas, dtype=float).reshape(-1, info.n_joints)
    T, Jk_full, Jt = chain.d_T_ds_tangent_batch(info.kin, thetas, info.n_joints)
    Lam = view_information(info.view, T, placement_at(info.view, T_st, T))
    return _factors(Lam, Jt, Jk_full[:, :, info.free])


def _best_pose_each(c: _Candidates, C: FloatArray) -> NDArray[np.int64]:
    """Per candidate joint-angle vector, the index of its pose with the largest information gain on the
    kinematics, ``log det(I + U^T C U)`` (the pre-selection before the objective is scored)."""
    S = np.eye(6) + np.swapaxes(c.U, 1, 2) @ C @ c.U
    gain = np.linalg.slogdet(S)[1]
    order = np.lexsort((-gain, c.owner))
    first = np.ones(order.size, dtype=bool)
    first[1:] = c.owner[order[1:]] != c.owner[order[:-1]]
    return order[first]


def _sigmas(F: FloatArray, C: FloatArray, N: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(rot, tra) 1-sigma at the grid points for kinematics covariance C."""
    d = np.einsum("gij,jk,gik->gi", F, C, F) + np.einsum("gii->gi", N)
    d = np.maximum(d, 0.0)
    return np.sqrt(d[:, :3].sum(axis=1)), np.sqrt(d[:, 3:].sum(axis=1))


def _scores(
    F: FloatArray, C: FloatArray, N: FloatArray, U: FloatArray, tol: Tolerance, objective: str
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Objective after each candidate's update, and the (rot, tra) variances at the grid points for
    each (Nc, G)."""
    G, nf = F.shape[0], F.shape[2]
    Nc = U.shape[0]
    base = np.einsum("gij,jk,gik->gi", F, C, F) + np.einsum("gii->gi", N)  # (G, 6)
    B = (F @ C).reshape(G * 6, nf)
    out = np.zeros(Nc)
    var_r, var_t = np.zeros((Nc, G)), np.zeros((Nc, G))
    chunk = max(1, int(CHUNK_BYTES / (G * 36 * 8)))
    for a in range(0, Nc, chunk):
        Uc = U[a : a + chunk]  # (n, nf, 6)
        n = Uc.shape[0]
        S = np.eye(6) + np.swapaxes(Uc, 1, 2) @ C @ Uc  # (n, 6, 6)
        Sinv = np.linalg.inv(S)
        D = (B @ np.swapaxes(Uc, 0, 1).reshape(nf, n * 6)).reshape(G, 6, n, 6).transpose(2, 0, 1, 3)  # (n, G, 6, 6)
        red = np.einsum("cgij,cjk,cgik->cgi", D, Sinv, D)
        d = np.maximum(base[None] - red, 0.0)
        vr, vt = d[..., :3].sum(axis=2), d[..., 3:].sum(axis=2)
        q = np.maximum(np.sqrt(vr) / tol.rotation, np.sqrt(vt) / tol.translation)
        out[a : a + n] = _objective(q, objective)
        var_r[a : a + n], var_t[a : a + n] = vr, vt
    return out, var_r, var_t


def _woodbury(C: FloatArray, U: FloatArray) -> FloatArray:
    """``(C^+ + U U^T)^+`` restricted to the range of C: ``C - C U (I + U^T C U)^-1 U^T C``."""
    CU = C @ U
    C2 = C - CU @ np.linalg.solve(np.eye(U.shape[1]) + U.T @ CU, CU.T)
    return 0.5 * (C2 + C2.T)


def _stats(rot: FloatArray, tra: FloatArray) -> dict[str, float]:
    return {
        "worst_rotation_mrad": float(rot.max() * 1e3),
        "worst_translation_mm": float(tra.max() * 1e3),
        "mean_rotation_mrad": float(rot.mean() * 1e3),
        "mean_translation_mm": float(tra.mean() * 1e3),
    }


def _meets(rot: FloatArray, tra: FloatArray, tol: Tolerance) -> bool:
    return bool(rot.max() <= tol.rotation and tra.max() <= tol.translation)


def plan_snapshots(
    info: KinematicsInformation,
    ranges: FloatArray,
    tolerance: Tolerance,
    k: int,
    objective: str = "worst",
    mode: str = "calibration",
    candidates: FloatArray | None = None,
) -> Plan:
    """Propose up to ``k`` snapshots over ``ranges`` (L, 2) rad (module docstring).

    ``candidates``: (Nc, L) joint angles to choose from (default: a regular grid of
    ``CANDIDATE_PER_AXIS`` points per joint over the range); only those at which the placed target has
    every corner inside both images count (a checkerboard detector needs the whole board).
    Raises ValueError for a bad ``k``, ``objective`` or ``mode``, or when no candidate has a view both
    cameras share.
    """
    if objective not in OBJECTIVES:
        raise ValueError(f"--objective must be one of {', '.join(OBJECTIVES)}, got {objective!r}")
    if mode not in MODES:
        raise ValueError(f"--predict must be one of {', '.join(MODES)}, got {mode!r}")
    if k < 1:
        raise ValueError(f"--k must be at least 1, got {k}")
    ranges = np.asarray(ranges, dtype=float).reshape(info.n_joints, 2)
    L = info.n_joints
    eval_pts, _ = range_grid(ranges, EVAL_PER_AXIS, EVAL_CAP)
    eval_pred = predict(info, eval_pts)
    grid = _eval_grid(eval_pred, mode)
    own = _eval_grid(eval_pred, "snapshot")
    if not grid.keep.any():
        raise ValueError(
            f"no joint angles in the range {format_range(ranges)} deg give a view of the target both cameras share"
        )
    if candidates is None:
        n = CANDIDATE_PER_AXIS.get(L, max(3, int(round(400 ** (1.0 / L)))))
        candidates, _ = range_grid(ranges, n, n**L)
    C = info.covariance.copy()
    rot, tra = _sigmas(grid.F, C, grid.N)
    now = _stats(rot, tra)
    floor_r, floor_t = _sigmas(own.F, np.zeros_like(C), own.N)  # a snapshot's own noise, perfect kinematics
    floor = _stats(floor_r, floor_t)
    picks: list[PlannedSnapshot] = []
    reached = _meets(rot, tra, tolerance)
    if reached:
        reason = "the calibration already meets the tolerance over the range: no more snapshots needed"
    elif mode == "snapshot" and (floor_r.max() > tolerance.rotation or floor_t.max() > tolerance.translation):
        reason = (
            f"the tolerance is below a single snapshot's own precision ({floor['worst_rotation_mrad']:.3g} mrad / "
            f"{floor['worst_translation_mm']:.3g} mm at the worst point): more snapshots cannot reach it; "
            "use --predict kinematics, a larger tolerance, a larger target or a closer distance"
        )
    else:
        reason = ""
    if not reached and not reason:
        cand = candidate_views(info, candidates)  # only when snapshots are to be proposed (the costly part)
        if cand.owner.size == 0:
            raise ValueError("no candidate joint angles give a view of the whole target to both cameras")
        for _ in range(k):
            pool = _best_pose_each(cand, C)
            scores, var_r, var_t = _scores(grid.F, C, grid.N, cand.U[pool], tolerance, objective)
            best = int(np.argmin(scores))
            g = int(pool[best])
            C = _woodbury(C, cand.U[g])
            rot, tra = np.sqrt(var_r[best]), np.sqrt(var_t[best])
            picks.append(
                PlannedSnapshot(
                    cand.thetas[g].copy(),
                    cand.placement.describe(g),
                    float(rot.max()),
                    float(tra.max()),
                    float(rot.mean()),
                    float(tra.mean()),
                )
            )
            if _meets(rot, tra, tolerance):
                reached = True
                break
        if reached:
            reason = f"predicted to meet the tolerance over the range after {len(picks)} more snapshot(s)"
        else:
            reason = (
                f"after {len(picks)} snapshot(s) the predicted worst is {rot.max() * 1e3:.3g} mrad / "
                f"{tra.max() * 1e3:.3g} mm: calibrate with them and plan again (or ask for more with --k)"
            )
    return Plan(ranges, tolerance, objective, mode, k, now, floor, picks, reached, reason)
