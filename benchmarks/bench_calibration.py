"""Benchmark: dcc-fg's GTSAM calibration solve against scipy.optimize.least_squares on the same problem.

The problem is the one ``dcc-fg demo`` solves: ``simulate_calibration(seed=0)`` (81 snapshots of a
2-DOF gimbal, 9x7 checkerboard seen by both cameras, 0.4 px noise), ``encoderless`` mode, ``bundle``
formulation. ``--seed`` and ``--snapshots`` change the simulated data set.

What is measured
----------------
1. ``calibrate()`` end to end with ``CalibrationOptions(compute_covariance=False, pixel_sigma=0.4)``:
   PnP in both cameras, the pose-level initialization, the observability checks before and after the
   solve, graph construction, the Levenberg-Marquardt solve and the residual report.

2. The nonlinear least-squares solve alone, apples to apples. The initial values are reproduced here
   with the same public helpers ``calibrate()`` calls (``snapshot_measurements``, ``pnp_pose``,
   ``joint_angles_from_T_ds``, ``gauge_fixed_kin``, ``gauge_fixed_joint_offsets``,
   ``robust_pose_level_init``), so both solvers start from exactly the values ``calibrate()`` hands to
   GTSAM (checked: the initial costs agree with ``CalibrationResult.initial_error``). Unknowns: the free
   kinematic entries, the L joint angles per snapshot and the target pose per snapshot; the gauge-fixed
   kinematic entries are constants and the mean of the last joint angle has a prior (sigma 1e-6 rad).

   a. dcc-fg / GTSAM: the factor graph built as ``calibrate()`` builds it (one ``bundle_factor`` per
      snapshot with analytic Jacobians, one ``mean_prior_factor``), solved by
      ``gtsam.LevenbergMarquardtOptimizer`` with calibrate()'s parameters (``lm_params``: relative
      error tolerance 1e-10, absolute 1e-12, diagonal damping, Nielsen's lambda update, at most 500
      iterations). Only ``optimize()`` is timed;
      graph construction is reported separately.
   b. scipy: ``least_squares(method='trf')`` on the same whitened residual vector (pixel residuals
      ``h(x) - z`` divided by the pixel sigma, computed by the same ``bundle_residuals`` the factors
      call, plus the same gauge row), target poses parameterized as rotation vector + translation,
      Jacobian by 2-point finite differences with the structural sparsity pattern passed as
      ``jac_sparsity`` (so the trust-region subproblems are solved by LSMR), ``ftol=1e-10``; ``xtol``
      and ``gtol`` are set to 1e-12 so that, as in GTSAM, the relative decrease of the cost is what
      stops the solver. Only the ``least_squares`` call is timed. Defaults: ``x_scale=1`` (trf's
      default) and LSMR ``atol = btol = 1e-10``. With LSMR's default tolerances (``--lsmr-tol 0``)
      the inexact steps stall on this problem (the 1e-6 rad gauge prior makes it ill-conditioned):
      hundreds of iterations that end on ftol above the minimum, so that would measure a solver
      that does not reach the same cost; ``--x-scale jac`` converges too, in about twice the
      iterations.

Both final solutions are scored with ONE residual function (the scipy one: GTSAM's Pose3 results are
converted to rotation vector + translation), cost = 0.5 * sum(r^2), the same quantity as GTSAM's
``graph.error``. The ratio printed is scipy time / GTSAM LM time. The last line of output is JSON.

Run: ``python benchmarks/bench_calibration.py [--seed 0] [--snapshots 81] [--x-scale 1|jac]
[--lsmr-tol 1e-10] [--repeat 1]``.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np
import scipy.sparse
from gtsam.symbol_shorthand import J, X
from numpy.typing import NDArray
from scipy.optimize import OptimizeResult, least_squares
from scipy.spatial.transform import Rotation

from dcc_fg.calibrate import CalibrationOptions, calibrate
from dcc_fg.calibration_graph import (
    GAUGE_SIGMA,
    KIN_KEY,
    gauge_fixed_joint_offsets,
    gauge_fixed_kin,
    lm_params,
    snapshot_measurements,
)
from dcc_fg.data import CalibrationDataset
from dcc_fg.init import joint_angles_from_T_ds, pnp_pose, robust_pose_level_init
from dcc_fg.model import GimbalCalibration
from dcc_fg.sim.calibration_scene import SceneConfig, simulate_calibration
from factors import chain
from factors.calibration import (
    KinLayout,
    SnapshotMeasurements,
    bundle_factor,
    bundle_residuals,
    mean_prior_factor,
)
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]
MODE = "encoderless"
PIXEL_SIGMA = 0.4
FTOL = 1e-10


@dataclass
class Problem:
    """The bundle problem at the initial values ``calibrate()`` hands to GTSAM.

    Attributes:
        layout: kinematic layout (free mask, constants = pose-level initialization).
        meas: per-snapshot matched corners.
        cams: static and dynamic camera models.
        kin_free0: (nf,) initial free kinematic entries.
        thetas0: (K, L) initial joint angles.
        T_st0: (K, 4, 4) initial target poses (static-camera PnP).
        offsets: joints whose mean angle has a gauge prior.
        offset_values: the prior's values (the initial means).
        init_time_s: wall time of PnP + joint-angle fit + pose-level initialization.
    """

    layout: KinLayout
    meas: list[SnapshotMeasurements]
    cams: tuple[CameraModel, CameraModel]
    kin_free0: FloatArray
    thetas0: FloatArray
    T_st0: FloatArray
    offsets: list[int]
    offset_values: list[float]
    init_time_s: float

    @property
    def n_snapshots(self) -> int:
        return len(self.meas)

    @property
    def n_joints(self) -> int:
        return self.layout.n_joints

    @property
    def n_free(self) -> int:
        return int(self.layout.free.sum())

    @property
    def n_params(self) -> int:
        return self.n_free + self.n_snapshots * (self.n_joints + 6)

    def rows_per_snapshot(self) -> list[tuple[int, int]]:
        """(static corners, dynamic corners) per snapshot."""
        return [(m.z_static.shape[0], m.z_dynamic.shape[0]) for m in self.meas]

    @property
    def n_residuals(self) -> int:
        return 2 * sum(a + b for a, b in self.rows_per_snapshot()) + len(self.offsets)


def build_problem(data: CalibrationDataset, initial: GimbalCalibration) -> Problem:
    """Reproduce the initial values of ``calibrate()`` (encoderless, bundle) with its public helpers."""
    t0 = time.perf_counter()
    L = initial.n_joints
    cams = (data.static_camera, data.dynamic_camera)
    meas = [snapshot_measurements(data, s) for s in data.snapshots]
    T_st0 = np.array([pnp_pose(cams[0], m.p_t_static, m.z_static) for m in meas])
    T_dt0 = np.array([pnp_pose(cams[1], m.p_t_dynamic, m.z_dynamic) for m in meas])
    thetas0 = np.zeros((len(meas), L))
    for i, s in enumerate(data.snapshots):
        if s.joints is not None and L > 0:
            thetas0[i] = np.asarray(s.joints, float)
        elif L > 0:
            thetas0[i] = joint_angles_from_T_ds(initial, T_dt0[i] @ chain.inv_se3(T_st0[i]), None)
    fixed = gauge_fixed_kin(L, MODE)
    offsets = gauge_fixed_joint_offsets(L, MODE)
    kin_start = initial.kin.copy()
    if L > 0:
        kin_start, thetas0, _ = robust_pose_level_init(
            initial.kin, L, T_dt0 @ np.linalg.inv(T_st0), thetas0, ~fixed, offsets, True
        )
    layout = KinLayout(kin_start, ~fixed, L)
    return Problem(
        layout=layout,
        meas=meas,
        cams=cams,
        kin_free0=kin_start[~fixed].copy(),
        thetas0=thetas0,
        T_st0=T_st0,
        offsets=offsets,
        offset_values=[float(thetas0[:, j].mean()) for j in offsets],
        init_time_s=time.perf_counter() - t0,
    )


# ------------------------------------------------------------------ shared residual (scipy vector)


def pack(kin_free: FloatArray, thetas: FloatArray, T_st: FloatArray) -> FloatArray:
    """Parameter vector ``[kin_free, theta_1..theta_K, (rotvec_i, t_i)_i]``."""
    rv = Rotation.from_matrix(T_st[:, :3, :3]).as_rotvec()
    poses = np.concatenate([rv, T_st[:, :3, 3]], axis=1)
    return np.concatenate([kin_free, thetas.ravel(), poses.ravel()])


def unpack(p: Problem, x: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Inverse of :func:`pack`: (kin_free, thetas (K, L), T_st (K, 4, 4))."""
    nf, K, L = p.n_free, p.n_snapshots, p.n_joints
    kin_free = x[:nf]
    thetas = x[nf : nf + K * L].reshape(K, L)
    poses = x[nf + K * L :].reshape(K, 6)
    T_st = np.tile(np.eye(4), (K, 1, 1))
    T_st[:, :3, :3] = Rotation.from_rotvec(poses[:, :3]).as_matrix()
    T_st[:, :3, 3] = poses[:, 3:]
    return kin_free, thetas, T_st


def residuals(p: Problem, x: FloatArray) -> FloatArray:
    """Whitened residual vector: per snapshot the static then the dynamic corners, (u, v) / sigma,
    then the gauge rows."""
    kin_free, thetas, T_st = unpack(p, x)
    out = []
    for i, m in enumerate(p.meas):
        blocks = bundle_residuals(p.layout, kin_free, thetas[i], T_st[i], m, p.cams, False)
        out.append(blocks[0][0].ravel() / PIXEL_SIGMA)
        out.append(blocks[1][0].ravel() / PIXEL_SIGMA)
    for j, value in zip(p.offsets, p.offset_values, strict=True):
        out.append(np.array([(thetas[:, j].mean() - value) / GAUGE_SIGMA]))
    return np.concatenate(out)


def cost(p: Problem, x: FloatArray) -> float:
    """0.5 * sum(r^2) of :func:`residuals` (GTSAM's ``graph.error`` for unit noise models)."""
    r = residuals(p, x)
    return 0.5 * float(r @ r)


def jac_sparsity(p: Problem) -> scipy.sparse.csr_matrix:
    """Structural sparsity of d residuals / d x: static rows see only their pose, dynamic rows
    see the kinematics, their joint angles and their pose, the gauge rows all last-joint angles."""
    nf, K, L = p.n_free, p.n_snapshots, p.n_joints
    S = scipy.sparse.lil_matrix((p.n_residuals, p.n_params), dtype=np.int8)
    row = 0
    for i, (ns, nd) in enumerate(p.rows_per_snapshot()):
        pose_cols = slice(nf + K * L + 6 * i, nf + K * L + 6 * i + 6)
        S[row : row + 2 * ns, pose_cols] = 1
        row += 2 * ns
        S[row : row + 2 * nd, :nf] = 1
        S[row : row + 2 * nd, nf + i * L : nf + (i + 1) * L] = 1
        S[row : row + 2 * nd, pose_cols] = 1
        row += 2 * nd
    for j in p.offsets:
        S[row, nf + j : nf + K * L : L] = 1
        row += 1
    assert row == p.n_residuals
    return S.tocsr()


# ------------------------------------------------------------------ solvers


@dataclass
class SolveReport:
    """Outcome of one timed solve; ``x`` is the solution packed as in :func:`pack`."""

    name: str
    time_s: float
    setup_time_s: float
    x: FloatArray
    initial_cost: float
    own_final_cost: float
    iterations: int
    nfev: int
    njev: int
    residual_evaluations: int
    status: int = 0


def solve_gtsam(p: Problem, max_iterations: int = 500) -> SolveReport:
    """The graph and Levenberg-Marquardt parameters of ``calibrate()`` (bundle, no robust loss)."""
    t0 = time.perf_counter()
    K = p.n_snapshots
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    values.insert(KIN_KEY, p.kin_free0)
    for i, m in enumerate(p.meas):
        values.insert(J(i), p.thetas0[i])
        values.insert(X(i), gtsam.Pose3(p.T_st0[i]))
        graph.add(bundle_factor(p.layout, m, p.cams, PIXEL_SIGMA, X(i), KIN_KEY, J(i)))
    for j, value in zip(p.offsets, p.offset_values, strict=True):
        graph.add(mean_prior_factor([J(i) for i in range(K)], j, value, GAUGE_SIGMA))
    params = lm_params(max_iterations)
    initial_cost = graph.error(values)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    setup = time.perf_counter() - t0

    t1 = time.perf_counter()
    result = optimizer.optimize()
    elapsed = time.perf_counter() - t1

    kin_free = result.atVector(KIN_KEY)
    thetas = np.array([result.atVector(J(i)) for i in range(K)])
    T_st = np.array([result.atPose3(X(i)).matrix() for i in range(K)])
    iterations = int(optimizer.iterations())
    return SolveReport(
        name="dcc-fg (GTSAM LM)",
        time_s=elapsed,
        setup_time_s=setup,
        x=pack(kin_free, thetas, T_st),
        initial_cost=float(initial_cost),
        own_final_cost=float(graph.error(result)),
        iterations=iterations,
        nfev=-1,
        njev=iterations,
        residual_evaluations=-1,
    )


def solve_scipy(p: Problem, x_scale: str, lsmr_tol: float) -> SolveReport:
    """``least_squares(method='trf')`` with a finite-difference Jacobian on the sparsity pattern.

    ``lsmr_tol`` > 0 sets LSMR's ``atol`` and ``btol`` (the trust-region subproblem solver that
    scipy uses with ``jac_sparsity``); 0 keeps scipy's defaults.
    """
    t0 = time.perf_counter()
    sparsity = jac_sparsity(p)
    x0 = pack(p.kin_free0, p.thetas0, p.T_st0)
    initial_cost = cost(p, x0)
    tr_options = {"atol": lsmr_tol, "btol": lsmr_tol} if lsmr_tol > 0 else {}
    setup = time.perf_counter() - t0
    calls = [0]

    def fun(x: FloatArray) -> FloatArray:
        calls[0] += 1
        return residuals(p, x)

    t1 = time.perf_counter()
    res: OptimizeResult = least_squares(
        fun,
        x0,
        jac="2-point",
        method="trf",
        jac_sparsity=sparsity,
        x_scale="jac" if x_scale == "jac" else 1.0,
        tr_options=tr_options,
        ftol=FTOL,
        xtol=1e-12,
        gtol=1e-12,
    )
    elapsed = time.perf_counter() - t1
    lsmr = f"{lsmr_tol:g}" if lsmr_tol > 0 else "default"
    return SolveReport(
        name=f"scipy trf FD (x_scale={x_scale}, lsmr tol={lsmr})",
        time_s=elapsed,
        setup_time_s=setup,
        x=np.asarray(res.x, dtype=float),
        initial_cost=initial_cost,
        own_final_cost=float(res.cost),
        iterations=int(res.nfev),
        nfev=int(res.nfev),
        njev=int(res.njev) if res.njev is not None else -1,
        residual_evaluations=calls[0],
        status=int(res.status),
    )


# ------------------------------------------------------------------ main


def _median_run(reports: list[SolveReport]) -> SolveReport:
    """The repeat with the median solve time (all repeats are deterministic and equal otherwise)."""
    return sorted(reports, key=lambda r: r.time_s)[len(reports) // 2]


def run(
    seed: int = 0,
    snapshots: int = 81,
    x_scale: str = "1",
    lsmr_tol: float = 1e-10,
    repeat: int = 1,
    verbose: bool = True,
) -> dict[str, Any]:
    """Run the whole benchmark and return the numbers (also printed when ``verbose``).

    Every timing is the median over ``repeat`` runs.
    """
    sim = simulate_calibration(seed=seed, config=SceneConfig(n_calibration=snapshots))
    data, initial = sim.calibration_set, sim.initial
    options = CalibrationOptions(compute_covariance=False, pixel_sigma=PIXEL_SIGMA)

    calibrate_times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        full = calibrate(data, initial, options)
        calibrate_times.append(time.perf_counter() - t0)
    calibrate_time = float(np.median(calibrate_times))

    problem = build_problem(data, initial)
    g = _median_run([solve_gtsam(problem) for _ in range(repeat)])
    s = _median_run([solve_scipy(problem, x_scale, lsmr_tol) for _ in range(repeat)])

    shared_initial = cost(problem, pack(problem.kin_free0, problem.thetas0, problem.T_st0))
    cost_g = cost(problem, g.x)
    cost_s = cost(problem, s.x)
    out: dict[str, Any] = {
        "seed": seed,
        "snapshots": snapshots,
        "repeat": repeat,
        "n_params": problem.n_params,
        "n_residuals": problem.n_residuals,
        "calibrate_time_s": calibrate_time,
        "calibrate_iterations": int(full.iterations),
        "calibrate_initial_cost": float(full.initial_error),
        "calibrate_final_cost": float(full.final_error),
        "init_time_s": problem.init_time_s,
        "initial_cost_shared": shared_initial,
        "gtsam_initial_cost": g.initial_cost,
        "gtsam_setup_time_s": g.setup_time_s,
        "gtsam_time_s": g.time_s,
        "gtsam_iterations": g.iterations,
        "gtsam_final_cost": cost_g,
        "gtsam_final_cost_graph": g.own_final_cost,
        "scipy_x_scale": x_scale,
        "scipy_lsmr_tol": lsmr_tol,
        "scipy_time_s": s.time_s,
        "scipy_setup_time_s": s.setup_time_s,
        "scipy_nfev": s.nfev,
        "scipy_njev": s.njev,
        "scipy_residual_evaluations": s.residual_evaluations,
        "scipy_status": s.status,
        "scipy_final_cost": cost_s,
        "ratio_scipy_over_gtsam": s.time_s / g.time_s,
        "ratio_scipy_over_calibrate": s.time_s / calibrate_time,
        "final_cost_rel_diff": (cost_s - cost_g) / max(abs(cost_g), 1e-300),
    }
    if verbose:
        print_table(out, g, s)
        print(json.dumps(out, sort_keys=True))
    return out


def print_table(out: dict[str, Any], g: SolveReport, s: SolveReport) -> None:
    """Human-readable report (the JSON line follows it)."""
    print(
        f"problem: simulate_calibration(seed={out['seed']}), {out['snapshots']} snapshots, {MODE}, bundle; "
        f"{out['n_params']} unknowns, {out['n_residuals']} residuals; times are medians of {out['repeat']}"
    )
    print(
        f"initial cost 0.5*sum(r^2): shared function {out['initial_cost_shared']:.6f}, "
        f"GTSAM graph {g.initial_cost:.6f}, calibrate() {out['calibrate_initial_cost']:.6f}"
    )
    print(
        f"calibrate() end to end: {out['calibrate_time_s']:.3f} s "
        f"({out['calibrate_iterations']} LM iterations, final cost {out['calibrate_final_cost']:.8f})"
    )
    print(f"initialization (PnP + pose-level) as reproduced here: {out['init_time_s']:.3f} s")
    print()
    cols = f"{'solver':<46} {'solve s':>9} {'setup s':>8} {'iters':>6} {'njev':>5} {'f evals':>8}"
    header = f"{cols} {'final cost (shared)':>20}"
    print(header)
    print("-" * len(header))
    for rep, c in ((g, out["gtsam_final_cost"]), (s, out["scipy_final_cost"])):
        fev = "-" if rep.residual_evaluations < 0 else str(rep.residual_evaluations)
        print(
            f"{rep.name:<46} {rep.time_s:>9.3f} {rep.setup_time_s:>8.3f} {rep.iterations:>6d} "
            f"{rep.njev:>5d} {fev:>8} {c:>20.8f}"
        )
    print()
    print(f"ratio scipy / GTSAM LM solve:       {out['ratio_scipy_over_gtsam']:.1f}")
    print(f"ratio scipy / calibrate() total:    {out['ratio_scipy_over_calibrate']:.1f}")
    print(f"final cost (scipy - GTSAM) / GTSAM: {out['final_cost_rel_diff']:.2e}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description="dcc-fg calibration solve vs scipy.optimize.least_squares")
    ap.add_argument("--seed", type=int, default=0, help="simulation seed (default 0, the demo)")
    ap.add_argument("--snapshots", type=int, default=81, help="calibration snapshots (default 81, the demo)")
    ap.add_argument("--x-scale", choices=("1", "jac"), default="1", help="scipy x_scale (default 1)")
    ap.add_argument(
        "--lsmr-tol",
        type=float,
        default=1e-10,
        help="LSMR atol/btol inside scipy's trf (default 1e-10; 0 = scipy's defaults, which stall here)",
    )
    ap.add_argument("--repeat", type=int, default=1, help="repeat timed runs, report medians")
    args = ap.parse_args(argv)
    if args.snapshots < 1 or args.repeat < 1:
        ap.error("--snapshots and --repeat must be positive")
    run(args.seed, args.snapshots, args.x_scale, args.lsmr_tol, args.repeat)


if __name__ == "__main__":
    main()
