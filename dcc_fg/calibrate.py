"""Build and solve the DCC calibration graph (paper sections III-A/B), with gauge handling.

Modes:

* ``encoders``: joint angles are given per snapshot (the paper's prior work, eq. 4);
* ``encoderless``: joint angles are estimated per snapshot (the paper's eq. 8);
* ``validate``: the kinematics are held at a calibration's values and only the joint angles
  (and target poses) are estimated (the paper's validation procedure).

Formulations: ``bundle`` (maximum likelihood, target pose per snapshot, the default) and
``two_way`` (the paper's eqs. 1, 2, 6 on PnP points). See :mod:`factors.calibration`.

Gauge. The parameterization is not minimal (docs/architecture.md). We hold these entries at their
initial values, which removes exactly the unobservable directions:

* L = 0: all of ``tau_s`` (only the product ``T_de T_bs`` is observable);
* encoderless, L >= 1: ``tau_s.rz`` and ``tau_s.tz`` (they absorb a constant offset of
  theta_1 and the DH ``d_1``), ``d_L, a_L, alpha_L`` (absorbed by ``tau_d``), and the mean of
  theta_L over the reference snapshots (a prior on the mean: the offset of theta_L is absorbed by
  ``tau_d``). The reference snapshots are all of them up to
  ``dcc_fg.calibration_graph.GAUGE_REFERENCE_SNAPSHOTS``, else that many spread evenly over the data
  set: the prior links its snapshots into one dense block of the elimination, whose cost would
  otherwise grow with the cube of the number of snapshots;
* encoders, L = 1: ``tau_s.rz, tau_s.tz, d_1, a_1, alpha_1``; encoders, L >= 2:
  ``tau_s.tz, d_L, a_L, alpha_L``.

The observability report is computed independently of these rules, from the eigenvectors of the
information matrix of the *full* parameterization (Schur complement onto the kinematics); a
parameter is observable when it has no component along the null space. Directions the data leave
undetermined beyond the gauge (a mechanism whose axes intersect) are held by weak priors and
reported (:mod:`dcc_fg.degeneracy`); a joint whose given angles never move is refused, naming the
parameters involved.

The steps of :func:`calibrate`: initial values (:func:`initial_problem`: PnP, joint angles,
joint-motion check, pose-level fit), the data check against the gauge (:func:`hold_degenerate_directions`),
the graph and its solve (:mod:`dcc_fg.calibration_graph`), residual statistics, observability and
covariances at the solution (:mod:`dcc_fg.covariance`), and the result.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X
from numpy.typing import NDArray

from dcc_fg.calibration_graph import (
    CalibrationProblem,
    GraphSolution,
    SolutionArrays,
    build_graph,
    gauge_fixed_joint_offsets,
    gauge_fixed_kin,
    pixel_residuals,
    snapshot_measurements,
    solution_arrays,
    solve_graph,
    variable_dims,
)
from dcc_fg.covariance import (
    COVARIANCE_UNAVAILABLE,
    Covariances,
    dense_covariances,
    graph_marginals,
    information_schur,
    marginal_covariances,
    null_space,
    observable_mask,
)
from dcc_fg.data import CalibrationDataset, with_joints
from dcc_fg.degeneracy import NOMINALS, HeldDirections, held_directions
from dcc_fg.init import joint_angles_from_T_ds, pnp_pose, robust_pose_level_init, zero_joint_init
from dcc_fg.joint_motion import FLAT_JOINT_SPAN_RAD, check_joint_motion, never_moves
from dcc_fg.model import GimbalCalibration
from dcc_fg.noise_floor import noise_floor, relative_image_noise
from dcc_fg.projection import MAX_STEPS, projected_solve
from dcc_fg.util.errors import EstimatorError, stage
from factors import chain
from factors.calibration import RobustLoss, SnapshotMeasurements

FloatArray = NDArray[np.float64]
MODES = ("encoderless", "encoders", "validate")
# The pose-level fit that starts the corner-level solve runs to a relative cost decrease of 1e-12 or 200
# iterations. Along the flat directions of a nearly degenerate L = 3 mechanism it creeps (cost 313.7
# after 2 iterations, 308.6 after 115 on a spherical wrist), but stopping it early (1e-6 / 40) moved
# where the corner-level solve of the pinned L = 3 scene stops in its own flat valley, enough to push
# its joint-angle errors past the test's sampling bound; the automatic starts use the early stop
# (dcc_fg.auto_init.CANDIDATE_MAX_ITERATIONS), since the global search compares their final costs.
POSE_LEVEL_REL_TOL = 1e-12
POSE_LEVEL_MAX_ITERATIONS = 200
FORMULATIONS = ("bundle", "two_way")
#: How the corner noise of the two cameras is modelled when ``pixel_sigma`` is estimated:
#: ``per-image`` weights each image by its own noise floor (:func:`dcc_fg.noise_floor.relative_image_noise`),
#: ``shared`` whitens all with one sigma.
CORNER_NOISE = ("per-image", "shared")
logger = logging.getLogger(__name__)
#: The held directions' prior (dcc_fg.degeneracy) is weakened by this factor in sigma for the final
#: polish and the reported covariances: the solve first runs with the prior at full strength (it keeps
#: the Levenberg-Marquardt steps well posed), then polishes from there with the weakened prior, and the
#: covariances are taken at that polished solution with the same graph. The prior sits at an arbitrary
#: start value and only keeps the solve well posed, so neither the estimate nor its uncertainty may
#: borrow certainty from it: T_ds does not move along a truly undetermined direction, but it does along
#: a weakly determined one that fell below the threshold, and there the full-strength prior biased
#: T_ds towards the start (random L = 3 mechanisms of the family, seeds 11 / 29 / 32: T_ds error over
#: the Cramer-Rao bound 1.08 / 1.27 / 1.40 with the polish, NEES 7.8 / 8.8 / 8.7; without it 16.1 NEES
#: and 1.73x the bound on seed 29, NEES 11.7 on seed 32).
COVARIANCE_PRIOR_WEAKENING = 100.0


@dataclass(frozen=True)
class CalibrationOptions:
    """Solver options.

    Attributes:
        mode: ``encoderless`` | ``encoders`` | ``validate``.
        formulation: ``bundle`` | ``two_way``.
        pixel_sigma: corner noise, pixels (1 sigma per axis); None estimates it from the residuals
            (a-posteriori variance factor) for the reported covariances.
        corner_noise: with ``pixel_sigma=None``, ``per-image`` (default) weights each image's corners
            by its own noise, measured before the solve from per-image target poses (the noise floor,
            shrunk towards its camera's; :func:`dcc_fg.noise_floor.relative_image_noise`): cameras of
            different resolution or blur, and images at different distance, detect corners with
            different noise, and one shared sigma overstates some images and understates others, in
            the estimate's weights and in its covariance. ``shared``: one sigma for all. A given
            ``pixel_sigma`` is used for all images.
        robust: None, ``huber`` or ``cauchy``; robust_k: its threshold in pixels.
        max_iterations: Levenberg-Marquardt iterations (see :func:`dcc_fg.calibration_graph.lm_params`).
        compute_covariance: compute Marginals, standard deviations and T_ds covariances.
        nominal: None, or a nominal geometry held by priors (:mod:`dcc_fg.degeneracy`: ``intersecting``,
            ``orthogonal``, ``yaw-roll-pitch``, ...), for users who know their gimbal.
        gauss_newton: also run the dense line-search Gauss-Newton (:mod:`dcc_fg.gauss_newton`) next
            to Levenberg-Marquardt in each solve and keep the lower error (off by default: it ends
            lower where Levenberg-Marquardt crawls on nearly degenerate 3-joint chains, but changed
            none of the four L = 3 study members that miss the global minimum; see the README).
        project_held: when directions are held by the weak prior, finish with the projected solve
            (:func:`projected_polish`): Levenberg-Marquardt on the kinematics with the per-snapshot
            variables re-solved at every step, on the data without the weak prior, which reaches the
            bottom of the curved valley the joint solve crawls along (off by default: ~0.1 s per step,
            up to 300 steps; :func:`dcc_fg.global_fit.calibrate_global` runs it on its best solution).
    """

    mode: str = "encoderless"
    formulation: str = "bundle"
    pixel_sigma: float | None = None
    corner_noise: str = "per-image"
    robust: str | None = None
    robust_k: float = 2.0
    max_iterations: int = 500
    compute_covariance: bool = True
    nominal: str | None = None
    gauss_newton: bool = False
    project_held: bool = False

    def __post_init__(self) -> None:
        if self.nominal is not None and self.nominal not in NOMINALS:
            raise ValueError(f"nominal '{self.nominal}' is not one of {', '.join(NOMINALS)}")
        if self.mode not in MODES:
            raise ValueError(f"mode '{self.mode}' is not one of {', '.join(MODES)}")
        if self.corner_noise not in CORNER_NOISE:
            raise ValueError(f"corner_noise '{self.corner_noise}' is not one of {', '.join(CORNER_NOISE)}")
        if self.formulation not in FORMULATIONS:
            raise ValueError(f"formulation '{self.formulation}' is not one of {', '.join(FORMULATIONS)}")
        if self.pixel_sigma is not None and not (np.isfinite(self.pixel_sigma) and self.pixel_sigma > 0):
            raise ValueError(f"pixel_sigma must be a positive number of pixels, got {self.pixel_sigma}")
        if not (isinstance(self.max_iterations, int | np.integer) and self.max_iterations >= 1):
            raise ValueError(
                f"max_iterations must be an integer >= 1, got {self.max_iterations!r} (with 0 Levenberg-Marquardt "
                "would write the initial values as the calibration)"
            )


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
            if np.max(np.abs(s.joints)) > 2.0 * np.pi:
                raise ValueError(
                    f"{tag}: joint reading {float(np.max(np.abs(s.joints))):.4g} is beyond a full turn: the readings "
                    "look like degrees, but radians are needed"
                )
    need = minimum_snapshots(n_joints, mode)
    if len(data.snapshots) < need:
        raise ValueError(
            f"{src}: {len(data.snapshots)} snapshots are fewer than the unknowns allow: a {mode} calibration "
            f"of L={n_joints} joints needs at least {need}"
        )


# ------------------------------------------------------------------ initial values


def pnp_initial_values(
    data: CalibrationDataset, meas: list[SnapshotMeasurements], initial: GimbalCalibration, mode: str
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """PnP target poses ``T_st0``, ``T_dt0`` (K, 4, 4) in both cameras, and joint angles (K, L) in rad:
    the snapshot's readings/guesses, else the IK of the PnP ``T_ds`` on ``initial``'s kinematics."""
    L = initial.n_joints
    cams = (data.static_camera, data.dynamic_camera)
    with stage("PnP", hint="check the camera intrinsics (--camchain) and the target description (--target)"):
        T_st0 = np.array([pnp_pose(cams[0], m.p_t_static, m.z_static) for m in meas])
        T_dt0 = np.array([pnp_pose(cams[1], m.p_t_dynamic, m.z_dynamic) for m in meas])
    thetas0 = np.zeros((len(meas), L))
    with stage("joint-angle initialization (IK)", hint="give initial joint angles (joints.csv) or use --init auto"):
        for i, s in enumerate(data.snapshots):
            if mode == "encoders" or (s.joints is not None and L > 0):
                thetas0[i] = np.asarray(s.joints, float)
            elif L > 0:
                thetas0[i] = joint_angles_from_T_ds(initial, T_dt0[i] @ chain.inv_se3(T_st0[i]), None)
    return T_st0, T_dt0, thetas0


def initial_problem(
    data: CalibrationDataset, initial: GimbalCalibration, opt: CalibrationOptions, pose_level: bool = True
) -> CalibrationProblem:
    """The graph's measurements, gauge and initial values: PnP in both cameras (target pose initial
    values, two-way points, joint-angle initialization), the joint-motion check (encoderless), then
    the pose-level fit of the chain to the PnP ``T_ds`` (L >= 1) or the closed-form ``tau_d`` (L = 0).
    ``pose_level=False`` skips that fit: the kinematics start at ``initial`` and the joint angles at
    the snapshots' guesses (a solve continued from a solution, :func:`continue_projected`).

    Raises ValueError for data in which a joint never moves (:func:`dcc_fg.joint_motion.check_joint_motion`).
    """
    L = initial.n_joints
    sigma = opt.pixel_sigma if opt.pixel_sigma is not None else 1.0
    robust = RobustLoss(opt.robust, opt.robust_k / sigma) if opt.robust else None
    meas = [snapshot_measurements(data, s) for s in data.snapshots]
    T_st0, T_dt0, thetas_given = pnp_initial_values(data, meas, initial, opt.mode)
    fixed = gauge_fixed_kin(L, opt.mode)
    offsets = gauge_fixed_joint_offsets(L, opt.mode)
    estimate_theta = opt.mode != "encoders" and L > 0
    image_scale, floor = None, None
    if opt.pixel_sigma is None and opt.corner_noise == "per-image":
        hint = "check the camera intrinsics (--camchain); or whiten all images alike (corner_noise shared)"
        with stage("noise floor", hint=hint):
            floor = noise_floor(data, T_st0, T_dt0)
            image_scale = relative_image_noise(floor)
    T_ds_pnp = T_dt0 @ np.linalg.inv(T_st0)
    if opt.mode == "encoderless" and L > 0:
        with stage("joint-motion check"):
            check_joint_motion(data, T_ds_pnp, L, thetas_given.copy(), initial)
    thetas0, kin_start = thetas_given.copy(), initial.kin.copy()
    with stage("pose-level initialization", hint="check the initial kinematics (--gimbal) or use --init auto"):
        if pose_level and opt.mode != "validate" and L > 0:
            kin_start, thetas_fit, _ = robust_pose_level_init(
                initial.kin,
                L,
                T_ds_pnp,
                thetas0,
                ~fixed,
                offsets,
                estimate_theta,
                rel_tol=POSE_LEVEL_REL_TOL,
                max_iterations=POSE_LEVEL_MAX_ITERATIONS,
            )
            if estimate_theta:
                thetas0 = thetas_fit
        elif pose_level and opt.mode != "validate":  # L = 0: T_ds is one constant transform; start tau_d from PnP
            kin_start = zero_joint_init(initial.kin, T_ds_pnp)
    return CalibrationProblem(
        data=data,
        n_joints=L,
        mode=opt.mode,
        formulation=opt.formulation,
        sigma=sigma,
        robust=robust,
        meas=meas,
        T_st0=T_st0,
        T_dt0=T_dt0,
        thetas_given=thetas_given,
        thetas0=thetas0,
        kin_start=kin_start,
        fixed=fixed,
        offsets=offsets,
        image_scale=image_scale,
        floor=floor,
    )


def hold_degenerate_directions(problem: CalibrationProblem, nominal: str | None = None) -> HeldDirections:
    """The directions of the kinematics that the data leave undetermined beyond the gauge, at the
    initial values, to be held by weak priors (:mod:`dcc_fg.degeneracy`; with ``nominal``, the
    nominal-geometry priors too). A mechanism whose axes (nearly) intersect is calibrated this way.

    Raises ValueError when such a direction comes from a joint whose given angles never move (a
    recording problem, not a property of the mechanism: record more varied joint angles)."""
    L = problem.n_joints
    if problem.mode == "validate":
        return HeldDirections(np.zeros((0, 0)), np.zeros(0), np.zeros((0, 0)), np.zeros(0), [])
    scale = np.zeros(len(problem.kin_start))
    with stage("observability check", hint="the data may not excite every joint; record more varied joint angles"):
        S0 = information_schur(
            problem.data,
            problem.kin_start,
            L,
            problem.thetas0,
            problem.T_st0,
            problem.mode,
            problem.formulation,
            problem.sigma,
            problem.pnp_points,
            scale_out=scale,
        )
        held = held_directions(S0, problem.kin_start, L, problem.fixed, problem.offsets, nominal, scale)
    if held.count:
        thetas = problem.thetas_given
        flat = [j for j in range(L) if thetas.shape[0] and float(np.ptp(thetas[:, j])) < FLAT_JOINT_SPAN_RAD]
        if flat:
            N = np.zeros((len(problem.fixed), held.count))
            N[~problem.fixed] = held.directions.T
            raise ValueError(unobservable_message(problem, N))
    return held


def unobservable_message(problem: CalibrationProblem, N: FloatArray) -> str:
    """The error for data that leave the null-space directions ``N`` (n_kin, k) unobservable: the
    joints whose given angles never move and the parameters the directions involve."""
    L, fixed, thetas = problem.n_joints, problem.fixed, problem.thetas_given
    names = chain.kin_names(L)
    moved = [names[k] for k in range(len(names)) if np.max(np.abs(N[k])) > 1e-3 and not fixed[k]]
    hints = []
    for j in range(L):
        spread = float(np.ptp(thetas[:, j])) if thetas.shape[0] else 0.0
        if spread < FLAT_JOINT_SPAN_RAD:
            hints.append(never_moves(j, spread))
    msg = f"{problem.data.source}: the data leave {N.shape[1]} unobservable directions beyond the gauge"
    if hints:
        msg += "; " + "; ".join(hints)
    if moved:
        msg += f"; parameters involved: {', '.join(moved)}"
    return msg


# ------------------------------------------------------------------ at the solution


def variance_factor_of(
    problem: CalibrationProblem,
    res_s: list[FloatArray],
    res_d: list[FloatArray],
    sigma_given: bool,
    n_held: int = 0,
) -> float:
    """A-posteriori variance factor: whitened sum of squares over the degrees of freedom (1 when the
    pixel sigma is given)."""
    K, L = problem.n_snapshots, problem.n_joints
    n_obs = 2 * sum(r.shape[0] for r in res_s + res_d)
    n_unknowns = (
        int((~problem.fixed).sum())
        + (K * L if problem.estimate_theta else 0)
        + (6 * K if problem.formulation == "bundle" else 0)
    )
    n_unknowns -= len(problem.offsets) + n_held
    dof = max(n_obs - n_unknowns, 1)
    whitened_ss = whitened_sum_of_squares(res_s, res_d, problem.image_sigma)
    return 1.0 if sigma_given else whitened_ss / dof


def observability_at(
    problem: CalibrationProblem, sol: SolutionArrays, initial: GimbalCalibration
) -> tuple[NDArray[np.bool_], int]:
    """(observable mask of the kinematic entries, nullity) of the full parameterization at the
    solution; in validation, the validated calibration's mask and 0."""
    if problem.mode == "validate":
        observable = initial.observable if initial.observable is not None else np.zeros(len(sol.kin), dtype=bool)
        return observable, 0
    scale = np.zeros(len(sol.kin))
    with stage("observability at the solution"):
        S = information_schur(
            problem.data,
            sol.kin,
            problem.n_joints,
            sol.thetas,
            sol.T_st,
            problem.mode,
            problem.formulation,
            problem.sigma,
            problem.pnp_points,
            scale_out=scale,
        )
        N = null_space(S, scale=scale)
    observable = observable_mask(N)
    if problem.n_joints == 0:
        # A rigid pair: all of tau_s is the gauge, so with tau_s held, tau_d is T_ds itself
        # (T_ds = T_de(tau_d) T_bs(tau_s)) and every entry is determined by the images.
        observable[6:12] = True
    return observable, N.shape[1] + 0


def covariances_at(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    problem: CalibrationProblem,
    sol: SolutionArrays,
    observable: NDArray[np.bool_],
    variance_factor: float,
    initial: GimbalCalibration,
    opt: CalibrationOptions,
) -> Covariances:
    """Marginal covariances at the solution when ``opt.compute_covariance`` (:mod:`dcc_fg.covariance`);
    a validation without them keeps the validated calibration's standard deviations."""
    marginals = None
    if opt.compute_covariance:
        try:
            marginals = graph_marginals(graph, values)
        except EstimatorError:
            pass  # reported in the note: the calibration itself is fine
    if marginals is not None:
        return marginal_covariances(marginals, problem, sol, observable, variance_factor)
    if opt.compute_covariance:
        dense = dense_covariances(graph, values, problem, sol, observable, variance_factor)
        if dense is not None:
            return dense
    out = Covariances(
        np.full(len(sol.kin), np.nan),
        np.full((problem.n_snapshots, problem.n_joints), np.nan),
        None,
        COVARIANCE_UNAVAILABLE if opt.compute_covariance else "not computed",
    )
    if opt.mode == "validate" and initial.kin_std is not None:
        out.kin_std = initial.kin_std
    return out


# ------------------------------------------------------------------ the calibration


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

    Raises:
        ValueError: input that the solver cannot use (named in the message); an N-camera cluster
            (:meth:`GimbalCalibration.require_two_cameras`; ``validate`` uses cam0 and cam1 of one
            whose cam1 is on a chain).
        dcc_fg.util.errors.EstimatorError: a numerical stage failed (PnP, IK, pose-level fit,
            Levenberg-Marquardt solve, observability, marginal covariances).
    """
    opt = options or CalibrationOptions()
    validating = opt.mode == "validate"
    initial.require_two_cameras("validation" if validating else "calibration", allow_subset=validating)
    L = initial.n_joints
    check_dataset(data, L, opt.mode)
    t_start = time.perf_counter()
    problem = initial_problem(data, initial, opt)
    held = hold_degenerate_directions(problem, opt.nominal)
    graphs = SolveGraphs.of(problem, held)
    dims = variable_dims(problem) if opt.gauss_newton else None
    solved = solve_graph(graphs.solve, graphs.values, opt.max_iterations, dims)
    polish_note = ""
    if held.count and problem.kin_key is not None:
        try:
            polished = solve_graph(graphs.weak, solved.values, opt.max_iterations, dims)
            iterations = solved.iterations + polished.iterations
            solved = replace(polished, initial_error=solved.initial_error, iterations=iterations)
        except EstimatorError as exc:  # keep the solution with the full-strength prior, and say so
            polish_note = f"the polish with the weakened prior on the held directions failed ({exc})"
            logger.warning("%s; the result keeps the full-strength prior", polish_note)
    projection: dict[str, Any] | None = None
    if held.count and problem.kin_key is not None and opt.project_held:
        solved, projection = projected_polish(graphs.data, graphs.weak, solved, variable_dims(problem))
    return finish(problem, held, graphs.weak, solved, initial, opt, t_start, polish_note, projection)


def continue_projected(
    data: CalibrationDataset, result: CalibrationResult, max_steps: int = MAX_STEPS
) -> CalibrationResult | None:
    """``result`` (of :func:`calibrate`, encoderless, directions held by prior) solved on from where it
    stopped with the projected solve (:func:`projected_polish`, at most ``max_steps`` steps), without
    repeating its joint solve: the problem is set up at the result's kinematics and joint angles (no
    pose-level fit), the held directions found there. None when that solve fails or does not lower the
    data error, or the result holds no directions. The report's ``total_steps`` adds the projected steps
    ``result`` had already taken (a continuation of a continuation)."""
    opt = result.options
    t_start = time.perf_counter()
    problem = initial_problem(with_joints(data, result.joint_angles), result.calibration, opt, pose_level=False)
    held = hold_degenerate_directions(problem, opt.nominal)
    if not held.count or problem.kin_key is None:
        return None
    graphs = SolveGraphs.of(problem, held)
    values = gtsam.Values(graphs.values)
    for i, T in enumerate(result.T_st):
        if values.exists(X(i)):
            values.update(X(i), gtsam.Pose3(T))
    error = float(graphs.weak.error(values))
    start = GraphSolution(values, result.iterations, result.initial_error, error)
    solved, projection = projected_polish(graphs.data, graphs.weak, start, variable_dims(problem), max_steps)
    if not projection.get("kept") or not projection["data_error_after"] < data_cost(result):
        return None
    earlier = result.extra.get("held_projection") or {}
    projection["total_steps"] = int(projection["steps"]) + int(earlier.get("total_steps", earlier.get("steps", 0)))
    note = "continued from the solution with the projected solve (the weakened-prior polish not repeated)"
    out = finish(problem, held, graphs.weak, solved, result.calibration, opt, t_start, note, projection)
    out.solve_time_s += result.solve_time_s
    return out


def stopped_on_cap(result: CalibrationResult) -> bool:
    """Whether ``result``'s projected solve lowered the data error but stopped on its step cap while still
    descending (short of the bottom of the valley; :func:`continue_projected` can take it further)."""
    projection = result.extra.get("held_projection") or {}
    return bool(projection.get("kept")) and not projection.get("converged", True)


@dataclass
class SolveGraphs:
    """The graphs of one calibration: ``solve`` (the data with the weak prior on the held directions),
    ``weak`` (the prior weakened by ``COVARIANCE_PRIOR_WEAKENING``: polish and covariances), ``data``
    (the data with the nominal priors only: the projected solve), and the initial ``values``."""

    solve: gtsam.NonlinearFactorGraph
    weak: gtsam.NonlinearFactorGraph
    data: gtsam.NonlinearFactorGraph
    values: gtsam.Values

    @classmethod
    def of(cls, problem: CalibrationProblem, held: HeldDirections) -> SolveGraphs:
        graph, values = build_graph(problem)
        weak, data = gtsam.NonlinearFactorGraph(), gtsam.NonlinearFactorGraph()
        for i in range(graph.size()):
            weak.add(graph.at(i))  # the same data factors, shared
            data.add(graph.at(i))
        if problem.kin_key is not None:
            for factor in held.factors(problem.kin_key):
                graph.add(factor)
            for factor in held.factors(problem.kin_key, COVARIANCE_PRIOR_WEAKENING):
                weak.add(factor)
            for factor in held.nominal_factors(problem.kin_key):
                data.add(factor)
        return cls(graph, weak, data, values)


def finish(
    problem: CalibrationProblem,
    held: HeldDirections,
    weak_graph: gtsam.NonlinearFactorGraph,
    solved: GraphSolution,
    initial: GimbalCalibration,
    opt: CalibrationOptions,
    t_start: float,
    polish_note: str,
    projection: dict[str, Any] | None,
) -> CalibrationResult:
    """The result of a solve: residuals, variance factor, observability, covariances (on ``weak_graph``)
    and the report (``initial``: the calibration the solve started from, for the gauge and, in
    validation, the validated values)."""
    data, L, validating = problem.data, problem.n_joints, opt.mode == "validate"
    sol = solution_arrays(problem, solved.values)
    res_s, res_d = pixel_residuals(problem, sol)
    variance_factor = variance_factor_of(problem, res_s, res_d, opt.pixel_sigma is not None, held.count)
    observable, null_dim = observability_at(problem, sol, initial)
    if held.count:  # parameters moved by a held direction are not determined by the data
        observable[np.flatnonzero(~problem.fixed)[held.involved()]] = False

    cov = covariances_at(weak_graph, solved.values, problem, sol, observable, variance_factor, initial, opt)
    cal = GimbalCalibration(
        sol.kin,
        L,
        data.static_camera,
        data.dynamic_camera,
        kin_std=cov.kin_std,
        observable=observable,
        gauge_fixed=initial.gauge_fixed if validating else problem.fixed,
        held_by_prior=initial.held_by_prior if validating else held.report(),
    )
    out = CalibrationResult(
        calibration=cal,
        joint_angles=sol.thetas,
        joint_angle_std=cov.theta_std,
        T_st=sol.T_st,
        timestamps_ns=np.array([s.timestamp_ns for s in data.snapshots], dtype=np.int64),
        residuals_static=res_s,
        residuals_dynamic=res_d,
        null_space_dim=null_dim,
        n_gauge_fixed=0 if validating else problem.n_gauge,
        iterations=solved.iterations,
        initial_error=solved.initial_error,
        final_error=solved.final_error,
        solve_time_s=time.perf_counter() - t_start,
        variance_factor=variance_factor,
        options=opt,
        T_ds_covariances=cov.T_ds,
    )
    out.extra["covariance"] = cov.note
    if held.count:
        out.extra["held_by_prior"] = held.report()
        out.extra["held_by_prior_text"] = held.plain_words()
        out.extra["held_polish"] = polish_note or "polished with the weakened prior"
    if projection is not None:
        out.extra["held_projection"] = projection
    if held.nominal:
        out.extra["nominal"] = opt.nominal
    # for the health checks (dcc_fg.calibration_health): the per-image PnP poses of both cameras and
    # the solver's stopping state
    out.extra["pnp_T_st"], out.extra["pnp_T_dt"] = problem.T_st0, problem.T_dt0
    if problem.floor is not None:  # the noise floor of these PnP poses (the health checks reuse it)
        out.extra["noise_floor"] = problem.floor
    out.extra["solver"] = {
        "max_iterations": int(opt.max_iterations),
        "next_decrease": float(solved.next_decrease),
        "sigma": float(problem.sigma),
        "image_sigma": problem.image_sigma.tolist(),
    }
    cal.statistics = summary_statistics(out)
    return out


def projected_polish(
    data_graph: gtsam.NonlinearFactorGraph,
    weak_graph: gtsam.NonlinearFactorGraph,
    solved: GraphSolution,
    dims: list[tuple[int, int]],
    max_steps: int = MAX_STEPS,
) -> tuple[GraphSolution, dict[str, Any]]:
    """The solution moved to the bottom of the valley of the held directions: the projected solve
    (:func:`dcc_fg.projection.projected_solve`) of ``data_graph`` (the data, the gauge and the nominal
    priors, no weak prior) from ``solved``, at most ``max_steps`` steps; kept when it lowers that error.
    Returns the kept solution and a report (errors in GTSAM units, steps, converged, kept; ``error`` when
    the solve failed)."""
    before = float(data_graph.error(solved.values))
    report: dict[str, Any] = {"data_error_before": before}
    try:
        projected = projected_solve(data_graph, solved.values, dims, max_steps)
    except (ValueError, RuntimeError, np.linalg.LinAlgError) as exc:
        logger.warning("the projected solve along the held directions failed (%s); the polished solution is kept", exc)
        return solved, {**report, "error": str(exc), "kept": False}
    kept = bool(projected.final_error < before)
    report.update(
        data_error_after=float(projected.final_error), steps=projected.steps, converged=projected.converged, kept=kept
    )
    if not kept:
        return solved, report
    if not projected.converged:
        logger.warning(
            "the projected solve along the held directions stopped on its cap of %d steps while still descending "
            "(data error %.6g -> %.6g): the solution may lie short of the bottom of their valley",
            projected.steps, before, projected.final_error,
        )  # fmt: skip
    final_error = float(weak_graph.error(projected.values))
    # a converged projected solve ends where the joint solve's remaining decrease no longer applies
    next_decrease = float("nan") if projected.converged else solved.next_decrease
    return replace(solved, values=projected.values, final_error=final_error, next_decrease=next_decrease), report


def image_sigma_of(res: CalibrationResult) -> FloatArray:
    """(K, 2) whitening sigmas of the solve per image ``[static, dynamic]``, px."""
    solver = res.extra.get("solver", {})
    if "image_sigma" in solver:
        return np.asarray(solver["image_sigma"], float).reshape(-1, 2)
    return np.full((len(res.timestamps_ns), 2), float(solver.get("sigma", 1.0)))  # one sigma for all


def whitened_sum_of_squares(res_s: list[FloatArray], res_d: list[FloatArray], image_sigma: FloatArray) -> float:
    """Sum of the squared pixel residuals (per image (N, 2), px) whitened by each image's sigma."""
    ss = sum(float(np.sum(r * r)) / float(s) ** 2 for r, s in zip(res_s, image_sigma[:, 0], strict=True))
    return ss + sum(float(np.sum(r * r)) / float(s) ** 2 for r, s in zip(res_d, image_sigma[:, 1], strict=True))


def data_cost(result: CalibrationResult) -> float:
    """0.5 * sum of the whitened squared pixel residuals (no priors, no robust loss): GTSAM's error
    of the data factors alone, in the units of ``final_error`` (each image whitened by its sigma,
    ``extra["solver"]["image_sigma"]``, measured before the solve: the same for every start)."""
    return 0.5 * whitened_sum_of_squares(result.residuals_static, result.residuals_dynamic, image_sigma_of(result))


def corner_sigma(res: CalibrationResult) -> dict[str, float]:
    """A-posteriori corner noise of each camera, px (1 sigma per axis, RMS over its images): the
    whitening sigmas of the solve times the square root of the variance factor (the given sigma when
    ``pixel_sigma`` is set)."""
    s = image_sigma_of(res)
    f = float(np.sqrt(res.variance_factor))
    return {"static": float(np.sqrt(np.mean(s[:, 0] ** 2))) * f, "dynamic": float(np.sqrt(np.mean(s[:, 1] ** 2))) * f}


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
        "corner_sigma_px": corner_sigma(res),
        "null_space_dim": int(res.null_space_dim),
        "gauge_directions_fixed": int(res.n_gauge_fixed),
        "covariance": res.extra.get("covariance", "ok"),
        "held_by_prior": len(res.extra.get("held_by_prior", [])),
        "nominal": res.extra.get("nominal"),
    }
