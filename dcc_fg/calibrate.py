"""Build and solve the DCC calibration graph (paper sections III-A/B), with gauge handling.

Modes:

* ``encoders``: joint angles are given per snapshot (the paper's prior work, eq. 4);
* ``encoderless``: joint angles are estimated per snapshot (the paper's eq. 8);
* ``validate``: the kinematics are held at a calibration's values and only the joint angles
  (and target poses) are estimated (the paper's validation procedure).

Formulations: ``bundle`` (maximum likelihood, target pose per snapshot, the default) and
``two_way`` (the paper's eqs. 1, 2, 6 on PnP points). See :mod:`factors.calibration`.

Gauge. The parameterization is not minimal (ARCHITECTURE.md). We hold these entries at their
initial values, which removes exactly the unobservable directions:

* L = 0: all of ``tau_s`` (only the product ``T_de T_bs`` is observable);
* encoderless, L >= 1: ``tau_s.rz`` and ``tau_s.tz`` (they absorb a constant offset of
  theta_1 and the DH ``d_1``), ``d_L, a_L, alpha_L`` (absorbed by ``tau_d``), and the mean of
  theta_L over the reference snapshots (a prior on the mean: the offset of theta_L is absorbed by
  ``tau_d``). The reference snapshots are all of them up to ``GAUGE_REFERENCE_SNAPSHOTS``, else that
  many spread evenly over the data set: the prior links its snapshots into one dense block of the
  elimination, whose cost would otherwise grow with the cube of the number of snapshots;
* encoders, L = 1: ``tau_s.rz, tau_s.tz, d_1, a_1, alpha_1``; encoders, L >= 2:
  ``tau_s.tz, d_L, a_L, alpha_L``.

The observability report is computed independently of these rules, from the eigenvectors of the
information matrix of the *full* parameterization (Schur complement onto the kinematics); a
parameter is observable when it has no component along the null space. The solver refuses to
start when the data leave more directions unobservable than the gauge (for example a joint that
never moves), naming the parameters involved.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np
from numpy.typing import NDArray

from dcc_fg.data import CalibrationDataset, Snapshot
from dcc_fg.init import pnp_pose, pose_level_refine
from dcc_fg.model import GimbalCalibration
from factors import chain
from factors.calibration import (
    KinLayout,
    RobustLoss,
    SnapshotMeasurements,
    bundle_factor,
    bundle_residuals,
    mean_prior_factor,
    two_way_factor,
    two_way_residuals,
)

FloatArray = NDArray[np.float64]
MODES = ("encoderless", "encoders", "validate")
FORMULATIONS = ("bundle", "two_way")
KIN_KEY = gtsam.symbol("k", 0)
COVARIANCE_CHUNK = 200  # snapshots per joint-marginal call (dense block: (nk + 200 L)^2 doubles)
MIN_ROTATION_SPREAD_RAD = np.deg2rad(0.5)  # joint motion check (see check_joint_motion)
GAUGE_SIGMA = 1e-6  # rad, prior on the mean of theta_L (a pure gauge direction: it costs nothing)
GAUGE_REFERENCE_SNAPSHOTS = 100  # at most this many snapshots carry the mean prior (module docstring)


def gauge_reference_snapshots(n_snapshots: int) -> NDArray[np.int64]:
    """Indices of the snapshots whose mean theta_L is held: all, or ``GAUGE_REFERENCE_SNAPSHOTS``
    spread evenly (first and last included)."""
    if n_snapshots <= GAUGE_REFERENCE_SNAPSHOTS:
        return np.arange(n_snapshots)
    return np.unique(np.linspace(0, n_snapshots - 1, GAUGE_REFERENCE_SNAPSHOTS).round().astype(np.int64))


def pose_key(i: int) -> int:
    """Key of the target pose T_st of snapshot i."""
    return gtsam.symbol("x", i)


def theta_key(i: int) -> int:
    """Key of the joint angles of snapshot i."""
    return gtsam.symbol("j", i)


@dataclass(frozen=True)
class CalibrationOptions:
    """Solver options.

    Attributes:
        mode: ``encoderless`` | ``encoders`` | ``validate``.
        formulation: ``bundle`` | ``two_way``.
        pixel_sigma: corner noise, pixels (1 sigma per axis); None estimates it from the residuals
            (a-posteriori variance factor) for the reported covariances.
        robust: None, ``huber`` or ``cauchy``; robust_k: its threshold in pixels.
        max_iterations: Levenberg-Marquardt iterations (see :func:`lm_params`).
        compute_covariance: compute Marginals, standard deviations and T_ds covariances.
    """

    mode: str = "encoderless"
    formulation: str = "bundle"
    pixel_sigma: float | None = None
    robust: str | None = None
    robust_k: float = 2.0
    max_iterations: int = 500
    compute_covariance: bool = True

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode '{self.mode}' is not one of {', '.join(MODES)}")
        if self.formulation not in FORMULATIONS:
            raise ValueError(f"formulation '{self.formulation}' is not one of {', '.join(FORMULATIONS)}")
        if self.pixel_sigma is not None and not self.pixel_sigma > 0:
            raise ValueError("pixel_sigma must be positive")


@dataclass
class CalibrationResult:
    """Everything a calibration run produces.

    Attributes:
        calibration: the estimated kinematics with standard deviations, observability and statistics.
        joint_angles: (K, L) estimated (or, in ``encoders`` mode, given) joint angles, radians.
        joint_angle_std: (K, L) 1-sigma, radians (NaN when not estimated).
        T_st: (K, 4, 4) target poses in the static camera (bundle) or from PnP (two-way).
        timestamps_ns: (K,) snapshot times.
        residuals_static / residuals_dynamic: per snapshot (N, 2) pixel residuals h(x) - z at the
            solution, in the formulation's own sense.
        null_space_dim: nullity of the information matrix of the full parameterization.
        n_gauge_fixed: number of directions fixed by the gauge rules.
        iterations, initial_error, final_error, solve_time_s: solver report (errors are GTSAM's
            0.5 * sum of squared whitened residuals).
        variance_factor: a-posteriori variance factor applied to the covariances (1 if sigma given).
    """

    calibration: GimbalCalibration
    joint_angles: FloatArray
    joint_angle_std: FloatArray
    T_st: FloatArray
    timestamps_ns: NDArray[np.int64]
    residuals_static: list[FloatArray]
    residuals_dynamic: list[FloatArray]
    null_space_dim: int
    n_gauge_fixed: int
    iterations: int
    initial_error: float
    final_error: float
    solve_time_s: float
    variance_factor: float
    options: CalibrationOptions
    T_ds_covariances: FloatArray | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def T_ds(self, i: int) -> FloatArray:
        """Estimated static-to-dynamic transform of snapshot i (4x4)."""
        return self.calibration.T_ds(self.joint_angles[i])

    def reprojection_stats(self) -> dict[str, dict[str, float]]:
        """Per camera and both: mean/std of per-corner error norms, RMS per axis (pixels), counts."""
        out = {}
        for name, res in (("static", self.residuals_static), ("dynamic", self.residuals_dynamic)):
            out[name] = residual_stats(np.concatenate(res) if res else np.zeros((0, 2)))
        out["all"] = residual_stats(np.concatenate(self.residuals_static + self.residuals_dynamic))
        return out


def residual_stats(r: FloatArray) -> dict[str, float]:
    """Statistics of pixel residuals (N, 2)."""
    if r.shape[0] == 0:
        return {"count": 0, "mean": float("nan"), "std": float("nan"), "rms_per_axis": float("nan")}
    norms = np.linalg.norm(r, axis=1)
    return {
        "count": int(r.shape[0]),
        "mean": float(norms.mean()),
        "std": float(norms.std()),
        "rms_per_axis": float(np.sqrt(np.mean(r * r))),
        "max": float(norms.max()),
    }


# ------------------------------------------------------------------ gauge


def gauge_fixed_kin(n_joints: int, mode: str) -> NDArray[np.bool_]:
    """Mask of kinematic entries held fixed in ``mode`` (see the module docstring)."""
    names = chain.kin_names(n_joints)
    fixed = np.zeros(len(names), dtype=bool)
    if mode == "validate":
        fixed[:] = True
        return fixed
    if n_joints == 0:
        fixed[0:6] = True
        return fixed
    last = 12 + 3 * (n_joints - 1)
    fixed[last : last + 3] = True  # d_L, a_L, alpha_L
    fixed[5] = True  # tau_s.tz
    if mode == "encoderless" or n_joints == 1:
        fixed[2] = True  # tau_s.rz
    return fixed


def gauge_fixed_joint_offsets(n_joints: int, mode: str) -> list[int]:
    """Joints whose mean angle is held at its initial value (0-based)."""
    return [n_joints - 1] if (mode == "encoderless" and n_joints >= 1) else []


# ------------------------------------------------------------------ input checks


def minimum_snapshots(n_joints: int, mode: str) -> int:
    """Fewest snapshots whose T_ds constraints (6 each) can determine the unknowns."""
    if mode == "validate":
        return 1
    n_kin_free = chain.n_kin(n_joints) - int(gauge_fixed_kin(n_joints, mode).sum())
    per_snapshot = 6 - (n_joints if mode == "encoderless" else 0)
    if per_snapshot <= 0:
        raise ValueError(f"encoderless calibration of L={n_joints} joints is not possible (at most 5)")
    n_offsets = len(gauge_fixed_joint_offsets(n_joints, mode))
    return int(np.ceil((n_kin_free - n_offsets) / per_snapshot)) if n_kin_free else 1


def check_dataset(data: CalibrationDataset, n_joints: int, mode: str) -> None:
    """Raise ValueError naming the problem for input a solver would choke on."""
    src = data.source
    if not data.snapshots:
        raise ValueError(f"{src}: the snapshot list is empty")
    n_pts = data.target_points.shape[0]
    for i, s in enumerate(data.snapshots):
        tag = f"{src}: snapshot {i} (t={s.timestamp_ns} ns)"
        for cam, obs in (("static", s.static), ("dynamic", s.dynamic)):
            if len(obs) == 0:
                raise ValueError(f"{tag}: no target corners in the {cam} camera")
            if len(obs) < 4:
                raise ValueError(f"{tag}: only {len(obs)} corners in the {cam} camera (need >= 4)")
            if not np.all(np.isfinite(obs.pixels)):
                raise ValueError(f"{tag}: NaN or infinite pixel coordinates in the {cam} camera")
            if obs.ids.min() < 0 or obs.ids.max() >= n_pts:
                raise ValueError(f"{tag}: corner ids outside the target's 0..{n_pts - 1} in the {cam} camera")
        if mode == "encoders":
            if s.joints is None or np.asarray(s.joints).shape != (n_joints,):
                raise ValueError(f"{tag}: encoders mode needs {n_joints} joint angles per snapshot")
            if not np.all(np.isfinite(s.joints)):
                raise ValueError(f"{tag}: NaN joint angles")
    need = minimum_snapshots(n_joints, mode)
    if len(data.snapshots) < need:
        raise ValueError(
            f"{src}: {len(data.snapshots)} snapshots are fewer than the unknowns allow: a {mode} calibration "
            f"of L={n_joints} joints needs at least {need}"
        )


# ------------------------------------------------------------------ measurements


def snapshot_measurements(data: CalibrationDataset, s: Snapshot) -> SnapshotMeasurements:
    """Match a snapshot's corner ids to target points."""
    P = data.target_points
    return SnapshotMeasurements(P[s.static.ids], s.static.pixels, P[s.dynamic.ids], s.dynamic.pixels)


def _axis_angle_error(T_a: FloatArray, T_b: FloatArray) -> FloatArray:
    """6-vector [omega, v] of Log(T_b^-1 T_a) (gtsam convention)."""
    return gtsam.Pose3(T_b).localCoordinates(gtsam.Pose3(T_a))


def fit_joint_angles(
    cal: GimbalCalibration, T_ds_measured: FloatArray, guess: FloatArray | None, n_starts: int = 12
) -> FloatArray:
    """Joint angles whose chain best matches a measured T_ds (least squares on its tangent error).

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
            e = _axis_angle_error(cal.T_ds(th), T_ds_measured)
            _, J = chain.d_T_ds_tangent(cal.kin, th, L)
            step = np.linalg.lstsq(J, -e, rcond=None)[0]
            th += step
            if np.linalg.norm(step) < 1e-10:
                break
        cost = float(np.sum(_axis_angle_error(cal.T_ds(th), T_ds_measured) ** 2))
        if cost < best_cost:
            best, best_cost = th, cost
    return np.arctan2(np.sin(best), np.cos(best))


# ------------------------------------------------------------------ observability


def information_schur(
    data: CalibrationDataset,
    kin: FloatArray,
    n_joints: int,
    thetas: FloatArray,
    T_st: FloatArray,
    mode: str,
    formulation: str,
    sigma: float,
    pnp: list[tuple[FloatArray, FloatArray]] | None = None,
) -> FloatArray:
    """Information matrix of the *full* kinematic vector (12 + 3L) after eliminating the
    per-snapshot variables (joint angles when estimated, target poses in the bundle)."""
    layout = KinLayout(np.asarray(kin, float), np.ones(chain.n_kin(n_joints), dtype=bool), n_joints)
    cams = (data.static_camera, data.dynamic_camera)
    n = chain.n_kin(n_joints)
    S = np.zeros((n, n))
    for i, s in enumerate(data.snapshots):
        meas = snapshot_measurements(data, s)
        if formulation == "bundle":
            blocks = bundle_residuals(layout, kin, thetas[i], T_st[i], meas, cams, True)
            local = [1, 2] if mode == "encoderless" else [2]
        else:
            assert pnp is not None
            P_s, P_d = pnp[i]
            blocks = two_way_residuals(layout, kin, thetas[i], P_s, meas.z_dynamic, P_d, meas.z_static, cams, True)
            local = [1] if mode == "encoderless" else []
        Jk = np.concatenate([b[1][0].reshape(-1, n) for b in blocks]) / sigma
        if local:
            Jx = (
                np.concatenate(
                    [np.concatenate([b[1][j].reshape(b[1][j].shape[0] * 2, -1) for j in local], axis=1) for b in blocks]
                )
                / sigma
            )
            Hxx = Jx.T @ Jx
            Hxk = Jx.T @ Jk
            S += Jk.T @ Jk - Hxk.T @ np.linalg.solve(Hxx, Hxk)
        else:
            S += Jk.T @ Jk
    return S


def null_space(S: FloatArray, rel_tol: float = 1e-9) -> FloatArray:
    """Orthonormal basis (n, k) of the numerical null space of a PSD matrix, in parameter space
    (Jacobi-scaled first so that metres and radians are treated alike)."""
    d = np.sqrt(np.maximum(np.diag(S), 1e-300))
    Sn = S / np.outer(d, d)
    w, V = np.linalg.eigh(Sn)
    N = V[:, w < rel_tol * w.max()]
    return N


def observable_mask(N: FloatArray, tol: float = 1e-6) -> NDArray[np.bool_]:
    """A parameter is observable when no null-space direction moves it."""
    if N.shape[1] == 0:
        return np.ones(N.shape[0], dtype=bool)
    return np.max(np.abs(N), axis=1) < tol


# ------------------------------------------------------------------ solver


def lm_params(max_iterations: int) -> gtsam.LevenbergMarquardtParams:
    """Levenberg-Marquardt parameters of the calibration solve.

    Relative cost decrease 1e-10 (absolute 1e-12) stops it; the damping is scaled by the diagonal
    of the information matrix (metres and radians alike). The damping update is Nielsen's
    (``useFixedLambdaFactor = False``: after a rejected step lambda grows by a factor that doubles
    each time, after an accepted one it shrinks). With GTSAM's fixed factor of 10 the nearly
    degenerate L = 3 problems alternate between rejected steps at lambda 1e-6 and tiny accepted
    steps at 1e-5 and stop on the iteration cap far from the minimum (joint angles at 2-6x the
    Cramer-Rao bound); with Nielsen's update they converge, in up to ~220 iterations, hence the
    cap of 500. The well-conditioned L = 1, 2 problems converge in a handful of iterations either way.
    """
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(1e-12)
    params.setDiagonalDamping(True)
    params.setUseFixedLambdaFactor(False)
    return params


def calibrate(
    data: CalibrationDataset,
    initial: GimbalCalibration,
    options: CalibrationOptions | None = None,
) -> CalibrationResult:
    """Calibrate (or validate) a DCC from target snapshots.

    Args:
        data: snapshots with corner ids/pixels; ``snapshot.joints`` are encoder readings
            (``encoders``) or initial guesses (``encoderless``/``validate``; fitted from PnP when None).
        initial: initial kinematics (``validate``: the calibration to validate). Gauge-fixed
            entries keep these values.
        options: see :class:`CalibrationOptions`.
    """
    opt = options or CalibrationOptions()
    L = initial.n_joints
    check_dataset(data, L, opt.mode)
    t_start = time.perf_counter()
    cams = (data.static_camera, data.dynamic_camera)
    sigma_w = opt.pixel_sigma if opt.pixel_sigma is not None else 1.0
    robust = RobustLoss(opt.robust, opt.robust_k / sigma_w) if opt.robust else None

    K = len(data.snapshots)
    meas = [snapshot_measurements(data, s) for s in data.snapshots]
    # PnP in both cameras: target pose initial values, two-way points, joint-angle initialization
    T_st0 = np.array([pnp_pose(cams[0], m.p_t_static, m.z_static) for m in meas])
    T_dt0 = np.array([pnp_pose(cams[1], m.p_t_dynamic, m.z_dynamic) for m in meas])
    thetas0 = np.zeros((K, L))
    for i, s in enumerate(data.snapshots):
        if opt.mode == "encoders" or (s.joints is not None and L > 0):
            thetas0[i] = np.asarray(s.joints, float)
        elif L > 0:
            thetas0[i] = fit_joint_angles(initial, T_dt0[i] @ chain.inv_se3(T_st0[i]), None)

    fixed = gauge_fixed_kin(L, opt.mode)
    layout = KinLayout(initial.kin.copy(), ~fixed, L)
    offsets = gauge_fixed_joint_offsets(L, opt.mode)
    estimate_theta = opt.mode != "encoders" and L > 0
    kin_key = KIN_KEY if (~fixed).any() else None

    thetas_before_fit = thetas0.copy()
    if opt.mode == "encoderless" and L > 0:
        check_joint_motion(data, T_dt0 @ np.linalg.inv(T_st0), L, thetas_before_fit, initial)
    kin_start = initial.kin.copy()
    if opt.mode != "validate" and L > 0:
        kin_start, thetas_fit, pose_rms = robust_pose_level_init(
            initial.kin, L, T_dt0 @ np.linalg.inv(T_st0), thetas0, ~fixed, offsets, estimate_theta
        )
        if estimate_theta:
            thetas0 = thetas_fit
        layout = KinLayout(kin_start, ~fixed, L)
    elif opt.mode != "validate":  # L = 0: T_ds is one constant transform; start tau_d from PnP
        kin_start = zero_joint_init(initial.kin, T_dt0 @ np.linalg.inv(T_st0))
        layout = KinLayout(kin_start, ~fixed, L)

    pnp_points = [
        (m.p_t_dynamic @ T_st0[i][:3, :3].T + T_st0[i][:3, 3], m.p_t_static @ T_dt0[i][:3, :3].T + T_dt0[i][:3, 3])
        for i, m in enumerate(meas)
    ]

    # refuse data that leave more than the gauge unobservable
    if opt.mode != "validate":
        S0 = information_schur(data, kin_start, L, thetas0, T_st0, opt.mode, opt.formulation, sigma_w, pnp_points)
        N0 = null_space(S0, rel_tol=1e-7)
        n_gauge = int(fixed.sum()) + len(offsets)
        if N0.shape[1] > n_gauge:
            _raise_unobservable(data, thetas_before_fit, N0, fixed, L)

    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    if kin_key is not None:
        values.insert(kin_key, kin_start[~fixed])
    for i, m in enumerate(meas):
        th_key = theta_key(i) if estimate_theta else None
        if th_key is not None:
            values.insert(th_key, thetas0[i])
        th_const = thetas0[i] if not estimate_theta else None
        if opt.formulation == "bundle":
            values.insert(pose_key(i), gtsam.Pose3(T_st0[i]))
            graph.add(bundle_factor(layout, m, cams, sigma_w, pose_key(i), kin_key, th_key, th_const, robust))
        else:
            P_s, P_d = pnp_points[i]
            graph.add(
                two_way_factor(
                    layout, P_s, m.z_dynamic, P_d, m.z_static, cams, sigma_w, kin_key, th_key, th_const, robust
                )
            )
    ref = gauge_reference_snapshots(K)
    for j in offsets:
        graph.add(mean_prior_factor([theta_key(int(i)) for i in ref], j, float(thetas0[ref, j].mean()), GAUGE_SIGMA))

    params = lm_params(opt.max_iterations)
    initial_error = graph.error(values)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = optimizer.optimize()
    iterations = optimizer.iterations()
    final_error = graph.error(result)

    kin_free = result.atVector(kin_key) if kin_key is not None else None
    kin = layout.expand(kin_free)
    thetas = np.array([result.atVector(theta_key(i)) for i in range(K)]) if estimate_theta else thetas0
    if opt.formulation == "bundle":
        T_st = np.array([result.atPose3(pose_key(i)).matrix() for i in range(K)])
    else:
        T_st = T_st0

    # residuals in pixels at the solution
    res_s, res_d = [], []
    for i, m in enumerate(meas):
        if opt.formulation == "bundle":
            blocks = bundle_residuals(layout, kin_free, thetas[i], T_st[i], m, cams, False)
            res_s.append(blocks[0][0])
            res_d.append(blocks[1][0])
        else:
            P_s, P_d = pnp_points[i]
            blocks = two_way_residuals(layout, kin_free, thetas[i], P_s, m.z_dynamic, P_d, m.z_static, cams, False)
            res_d.append(blocks[0][0])
            res_s.append(blocks[1][0])

    n_obs = 2 * sum(r.shape[0] for r in res_s + res_d)
    n_unknowns = int((~fixed).sum()) + (K * L if estimate_theta else 0) + (6 * K if opt.formulation == "bundle" else 0)
    n_unknowns -= len(offsets)
    dof = max(n_obs - n_unknowns, 1)
    whitened_ss = sum(float(np.sum(r * r)) for r in res_s + res_d) / sigma_w**2
    variance_factor = 1.0 if opt.pixel_sigma is not None else whitened_ss / dof

    # observability of the full parameterization at the solution
    if opt.mode != "validate":
        S = information_schur(data, kin, L, thetas, T_st, opt.mode, opt.formulation, sigma_w, pnp_points)
        N = null_space(S)
        observable = observable_mask(N)
        null_dim = N.shape[1] + 0
        if L == 0:
            # A rigid pair: all of tau_s is the gauge, so with tau_s held, tau_d is T_ds itself
            # (T_ds = T_de(tau_d) T_bs(tau_s)) and every entry is determined by the images.
            observable[6:12] = True
    else:
        observable = initial.observable if initial.observable is not None else np.zeros(len(kin), dtype=bool)
        null_dim = 0

    kin_std = np.full(len(kin), np.nan)
    theta_std = np.full((K, L), np.nan)
    T_ds_cov = None
    marginals = None
    covariance_note = "ok" if opt.compute_covariance else "not computed"
    if opt.compute_covariance:
        try:
            marginals = gtsam.Marginals(graph, result)
        except RuntimeError:
            covariance_note = "unavailable: the information matrix is too ill-conditioned for a Cholesky factorization"
    if marginals is not None:
        if kin_key is not None:
            cov = marginals.marginalCovariance(kin_key) * variance_factor
            kin_std[~fixed] = np.sqrt(np.diag(cov))
        kin_std[~observable] = np.nan
        T_ds_cov = np.zeros((K, 6, 6))
        # One joint marginal per chunk of snapshots instead of two per snapshot: each GTSAM
        # marginal call costs about as much as a joint one over many keys (the mean prior on the
        # reference snapshots' joint angles puts them in one clique), so per-snapshot calls made
        # this O(K^2) (~70 s of covariances at K = 300). Chunks bound the dense block.
        for start in range(0, K, COVARIANCE_CHUNK):
            chunk = range(start, min(K, start + COVARIANCE_CHUNK))
            keys = ([kin_key] if kin_key is not None else []) + (
                [theta_key(i) for i in chunk] if estimate_theta else []
            )
            if not keys:
                break
            kv = gtsam.KeyVector()
            for k in keys:
                kv.append(k)
            joint = marginals.jointMarginalCovariance(kv)
            for i in chunk:
                Jk, Jt = chain.d_T_ds_tangent(kin, thetas[i], L)
                keys_i, blocks_J = [], []
                if kin_key is not None:
                    keys_i.append(kin_key)
                    blocks_J.append(Jk[:, ~fixed])
                if estimate_theta:
                    keys_i.append(theta_key(i))
                    blocks_J.append(Jt)
                C = np.block([[joint.at(a, b) for b in keys_i] for a in keys_i]) * variance_factor
                if estimate_theta:
                    theta_std[i] = np.sqrt(np.diag(joint.at(theta_key(i), theta_key(i))) * variance_factor)
                Jf = np.concatenate(blocks_J, axis=1)
                T_ds_cov[i] = Jf @ C @ Jf.T
    elif opt.mode == "validate":
        kin_std = initial.kin_std if initial.kin_std is not None else kin_std

    cal = GimbalCalibration(
        kin,
        L,
        data.static_camera,
        data.dynamic_camera,
        kin_std=kin_std,
        observable=observable,
        gauge_fixed=fixed if opt.mode != "validate" else initial.gauge_fixed,
    )
    out = CalibrationResult(
        calibration=cal,
        joint_angles=thetas,
        joint_angle_std=theta_std,
        T_st=T_st,
        timestamps_ns=np.array([s.timestamp_ns for s in data.snapshots], dtype=np.int64),
        residuals_static=res_s,
        residuals_dynamic=res_d,
        null_space_dim=null_dim,
        n_gauge_fixed=int(fixed.sum()) + len(offsets) if opt.mode != "validate" else 0,
        iterations=iterations,
        initial_error=initial_error,
        final_error=final_error,
        solve_time_s=time.perf_counter() - t_start,
        variance_factor=variance_factor,
        options=opt,
        T_ds_covariances=T_ds_cov,
    )
    out.extra["covariance"] = covariance_note
    cal.statistics = summary_statistics(out)
    return out


def mean_pose(T: FloatArray) -> FloatArray:
    """Average of K rigid transforms (K, 4, 4): chordal L2 mean rotation (SVD projection of the
    summed rotation matrices onto SO(3)) and arithmetic mean translation."""
    U, _, Vt = np.linalg.svd(T[:, :3, :3].sum(axis=0))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    out = np.eye(4)
    out[:3, :3] = U @ D @ Vt
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
) -> tuple[FloatArray, FloatArray, float]:
    """:func:`~dcc_fg.init.pose_level_refine` with deterministic restarts.

    A fit is accepted when its whitened RMS (1 mrad / 1 mm per unit) is below ``good_rms``
    (PnP noise alone gives ~1-3); otherwise the free kinematic entries are re-drawn around the
    initial values (10 deg / 3 cm) and the best fit is kept.
    """
    best = pose_level_refine(kin0, L, T_ds_pnp, thetas0, free, offsets, estimate_theta)
    rng = np.random.default_rng(12345)
    is_angle = chain.kin_is_angle(L)
    for _ in range(restarts):
        if best[2] < good_rms:
            break
        kin_try = kin0.copy()
        noise = rng.normal(size=kin0.shape) * np.where(is_angle, np.deg2rad(10.0), 0.03)
        kin_try[free] += noise[free]
        cand = pose_level_refine(kin_try, L, T_ds_pnp, thetas0, free, offsets, estimate_theta)
        if cand[2] < best[2]:
            best = cand
    return best


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
    also tested for the structure of a two-joint chain (:func:`dcc_fg.joint_motion.two_axis_fit`):
    an axis fixed in s followed by one fixed in d. When that fits within the PnP noise (chi-square
    per degree of freedom below ``dcc_fg.joint_motion.MAX_CHI2_PER_DOF``) and leaves less than
    ``MIN_ROTATION_SPREAD_RAD`` RMS unexplained, at most two joints move (see
    :func:`dcc_fg.joint_motion.two_joint_report`; a mechanism whose third joint moves so little that
    its rotation is lost in the PnP noise is refused too).

    Which joint is flat is not visible in the images alone (one joint rotating about a fixed axis
    looks the same whichever it is); it is named from ``thetas0`` (initial angles spanning < 2 deg)
    or else from ``initial``'s joint axes (for L <= 2 the axis the observed rotations do not use; for
    L = 3 the pair of axes the two-joint structure matches, :func:`dcc_fg.joint_motion.locked_joint_of_three`).
    """
    spread, V = rotation_spread(T_ds_pnp)
    need = min(L, 3)
    n_dirs = int(np.sum(spread > MIN_ROTATION_SPREAD_RAD))
    if n_dirs >= need:
        if L >= 3:
            from dcc_fg.joint_motion import two_joint_report

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
        span = np.ptp(np.asarray(thetas0, float), axis=0)
        flat = [j for j in np.argsort(span, kind="stable")[:n_flat] if span[j] < np.deg2rad(2.0)]
        if len(flat) == n_flat:
            named = [
                f"joint {j + 1} never moves during the recording (its angles span only {span[j]:.2e} rad): "
                f"joint {j + 1} is unobservable"
                for j in flat
            ]
    if not named and initial is not None and thetas0 is not None:
        # fraction of each joint's axis (static-camera frame) inside the observed rotation directions
        M = V[:, :n_dirs]
        use = np.zeros(L)
        for th in np.asarray(thetas0, float):
            Jt = chain.d_T_ds_tangent(initial.kin, th, L)[1][:3]
            axes = Jt / np.linalg.norm(Jt, axis=0)
            use += np.linalg.norm(M.T @ axes, axis=0) / len(thetas0)
        order = np.argsort(use, kind="stable")
        gap = use[order[n_flat]] - use[order[n_flat - 1]] if n_flat < L else 1.0
        if gap > 0.3:
            named = [
                f"joint {j + 1} never moves during the recording (by the initial kinematics, its axis is "
                f"{np.rad2deg(np.arccos(min(use[j], 1.0))):.0f} deg away from every observed rotation): "
                f"joint {j + 1} is unobservable"
                for j in order[:n_flat]
            ]
    if named:
        msg += "; " + "; ".join(named)
    else:
        msg += (
            "; a joint never moves or the joints move together (images alone do not tell which joint: give "
            "joint readings, e.g. joints.csv or a JointState topic, or a gimbal.yaml)"
        )
    raise ValueError(msg)


def _raise_unobservable(
    data: CalibrationDataset, thetas0: FloatArray, N: FloatArray, fixed: NDArray[np.bool_], L: int
) -> None:
    names = chain.kin_names(L)
    moved = [names[k] for k in range(len(names)) if np.max(np.abs(N[k])) > 1e-3 and not fixed[k]]
    hints = []
    for j in range(L):
        spread = float(np.ptp(thetas0[:, j])) if thetas0.shape[0] else 0.0
        if spread < np.deg2rad(2.0):
            hints.append(
                f"joint {j + 1} never moves during the recording (its angles span only {spread:.2e} rad): "
                f"joint {j + 1} is unobservable"
            )
    msg = f"{data.source}: the data leave {N.shape[1]} unobservable directions, more than the gauge fixes"
    if hints:
        msg += "; " + "; ".join(hints)
    if moved:
        msg += f"; parameters involved: {', '.join(moved)}"
    raise ValueError(msg)


def summary_statistics(res: CalibrationResult) -> dict[str, Any]:
    """The statistics block of ``calibration.yaml`` / ``summary.json``."""
    stats = res.reprojection_stats()
    return {
        "mode": res.options.mode,
        "formulation": res.options.formulation,
        "snapshots": int(len(res.timestamps_ns)),
        "reprojection_error_px": stats,
        "iterations": int(res.iterations),
        "initial_error": float(res.initial_error),
        "final_error": float(res.final_error),
        "solve_time_s": float(res.solve_time_s),
        "variance_factor": float(res.variance_factor),
        "null_space_dim": int(res.null_space_dim),
        "gauge_directions_fixed": int(res.n_gauge_fixed),
        "covariance": res.extra.get("covariance", "ok"),
    }
