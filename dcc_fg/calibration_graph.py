"""The calibration factor graph: keys, gauge rules, the graph itself and its Levenberg-Marquardt solve.

Frames and conventions: docs/architecture.md (``T_ab`` maps points from frame b into frame a;
``T_ds`` static -> dynamic camera). Variables (keys from ``gtsam.symbol_shorthand``):

* ``KIN_KEY`` = ``k0``: the free entries of the kinematic vector ``[tau_s, tau_d, dh]``
  (:class:`factors.calibration.KinLayout`; the gauge-fixed entries are constants);
* ``J(i)``: the L joint angles of snapshot i, rad (not a variable in ``encoders`` mode);
* ``X(i)``: the target pose ``T_st`` of snapshot i (bundle formulation only).

Gauge rules (which entries are held, and why): see :mod:`dcc_fg.calibrate`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from functools import cached_property
from typing import TYPE_CHECKING

import gtsam
import numpy as np
from gtsam.symbol_shorthand import J, X
from gtsam.symbol_shorthand import K as KIN
from numpy.typing import NDArray

from dcc_fg.data import CalibrationDataset, Snapshot
from dcc_fg.gauss_newton import gauss_newton
from dcc_fg.util.errors import stage
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
from factors.camera import CameraModel

if TYPE_CHECKING:  # dcc_fg.noise_floor builds on this module
    from dcc_fg.noise_floor import NoiseFloor

FloatArray = NDArray[np.float64]
KIN_KEY = KIN(0)
GN_MAX_ITERATIONS = 50  # dense Gauss-Newton steps per solve (it converges in ~10 where it helps)
logger = logging.getLogger(__name__)
GAUGE_SIGMA = 1e-6  # rad, prior on the mean of theta_L (a pure gauge direction: it costs nothing)
GAUGE_REFERENCE_SNAPSHOTS = 100  # at most this many snapshots carry the mean prior (dcc_fg.calibrate docstring)


# ------------------------------------------------------------------ gauge


def gauge_reference_snapshots(n_snapshots: int) -> NDArray[np.int64]:
    """Indices of the snapshots whose mean theta_L is held: all, or ``GAUGE_REFERENCE_SNAPSHOTS``
    spread evenly (first and last included)."""
    if n_snapshots <= GAUGE_REFERENCE_SNAPSHOTS:
        return np.arange(n_snapshots)
    return np.unique(np.linspace(0, n_snapshots - 1, GAUGE_REFERENCE_SNAPSHOTS).round().astype(np.int64))


def gauge_fixed_kin(n_joints: int, mode: str) -> NDArray[np.bool_]:
    """Mask of kinematic entries held fixed in ``mode`` (see the :mod:`dcc_fg.calibrate` docstring)."""
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


# ------------------------------------------------------------------ the problem


def snapshot_measurements(data: CalibrationDataset, s: Snapshot) -> SnapshotMeasurements:
    """Match a snapshot's corner ids to target points."""
    P = data.target_points
    return SnapshotMeasurements(P[s.static.ids], s.static.pixels, P[s.dynamic.ids], s.dynamic.pixels)


@dataclass
class CalibrationProblem:
    """What one calibration graph is built from: measurements, gauge and initial values.

    Attributes:
        data: the snapshots (cameras and target points).
        n_joints: L.
        mode / formulation: as in :class:`dcc_fg.calibrate.CalibrationOptions`.
        sigma: pixel sigma that whitens the residuals (1 when it is estimated afterwards).
        image_scale: (K, 2) factors on ``sigma`` per image ``[static, dynamic]`` (the relative corner
            noise of each image, :func:`dcc_fg.noise_floor.relative_image_noise`); None: 1 for all.
        floor: the noise floor ``image_scale`` was taken from (None when one sigma whitens all).
        robust: per-corner robust loss on the whitened residuals, or None.
        meas: per snapshot, the corners matched to target points.
        T_st0 / T_dt0: (K, 4, 4) PnP target poses in the static / dynamic camera.
        thetas_given: (K, L) joint angles before the pose-level fit (readings, guesses or IK), rad.
        thetas0: (K, L) initial joint angles of the graph, rad.
        kin_start: (12 + 3L,) initial kinematics; its gauge-fixed entries are held.
        fixed: mask of the gauge-fixed kinematic entries.
        offsets: joints whose mean angle is held (0-based).
    """

    data: CalibrationDataset
    n_joints: int
    mode: str
    formulation: str
    sigma: float
    robust: RobustLoss | None
    meas: list[SnapshotMeasurements]
    T_st0: FloatArray
    T_dt0: FloatArray
    thetas_given: FloatArray
    thetas0: FloatArray
    kin_start: FloatArray
    fixed: NDArray[np.bool_]
    offsets: list[int]
    image_scale: FloatArray | None = None
    floor: NoiseFloor | None = None

    @property
    def image_sigma(self) -> FloatArray:
        """(K, 2) pixel sigmas that whiten each image's residuals, ``[static, dynamic]``."""
        scale = self.image_scale if self.image_scale is not None else np.ones((len(self.meas), 2))
        return self.sigma * np.asarray(scale, float)

    @property
    def cams(self) -> tuple[CameraModel, CameraModel]:
        return (self.data.static_camera, self.data.dynamic_camera)

    @property
    def n_snapshots(self) -> int:
        return len(self.meas)

    @property
    def estimate_theta(self) -> bool:
        return self.mode != "encoders" and self.n_joints > 0

    @property
    def kin_key(self) -> int | None:
        """``KIN_KEY``, or None when every kinematic entry is held (validation)."""
        return KIN_KEY if (~self.fixed).any() else None

    @property
    def layout(self) -> KinLayout:
        return KinLayout(self.kin_start, ~self.fixed, self.n_joints)

    @property
    def n_gauge(self) -> int:
        """Directions the gauge rules fix: held kinematic entries and held mean joint angles."""
        return int(self.fixed.sum()) + len(self.offsets)

    @cached_property
    def pnp_points(self) -> list[tuple[FloatArray, FloatArray]]:
        """Per snapshot, the target points seen by camera d in frame s and those seen by s in frame d
        (through the PnP poses): the points of the two-way formulation, metres."""
        T_st0, T_dt0 = self.T_st0, self.T_dt0
        return [
            (m.p_t_dynamic @ T_st0[i][:3, :3].T + T_st0[i][:3, 3], m.p_t_static @ T_dt0[i][:3, :3].T + T_dt0[i][:3, 3])
            for i, m in enumerate(self.meas)
        ]


# ------------------------------------------------------------------ graph and solve


def build_graph(problem: CalibrationProblem) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """The factor graph (one factor per snapshot, plus the mean priors of the gauge) and its initial values."""
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    kin_key, layout, cams = problem.kin_key, problem.layout, problem.cams
    image_sigma = problem.image_sigma
    if kin_key is not None:
        values.insert(kin_key, problem.kin_start[~problem.fixed])
    for i, m in enumerate(problem.meas):
        th_key = J(i) if problem.estimate_theta else None
        if th_key is not None:
            values.insert(th_key, problem.thetas0[i])
        th_const = problem.thetas0[i] if not problem.estimate_theta else None
        sigma = (float(image_sigma[i, 0]), float(image_sigma[i, 1]))
        if problem.formulation == "bundle":
            values.insert(X(i), gtsam.Pose3(problem.T_st0[i]))
            graph.add(bundle_factor(layout, m, cams, sigma, X(i), kin_key, th_key, th_const, problem.robust))
        else:
            P_s, P_d = problem.pnp_points[i]
            graph.add(
                two_way_factor(
                    layout, P_s, m.z_dynamic, P_d, m.z_static, cams, sigma, kin_key, th_key, th_const, problem.robust
                )
            )
    ref = gauge_reference_snapshots(problem.n_snapshots)
    for j in problem.offsets:
        mean = float(problem.thetas0[ref, j].mean())
        graph.add(mean_prior_factor([J(int(i)) for i in ref], j, mean, GAUGE_SIGMA))
    return graph, values


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


@dataclass
class GraphSolution:
    """The optimized values and the solver report (errors are GTSAM's 0.5 * sum of squared
    whitened residuals).

    ``iterations`` counts the Levenberg-Marquardt iterations of the kept solve (when the dense
    Gauss-Newton ended lower, those of the confirming solve from its end; its own steps are
    ``gauss_newton_iterations``), so ``iterations >= max_iterations`` still means "stopped on the cap".

    ``next_decrease``: when the solve stopped on the iteration cap, the error decrease one more
    Levenberg-Marquardt iteration would have made (GTSAM error units; the convergence health check
    compares it with the noise); NaN when it stopped on its tolerances.
    """

    values: gtsam.Values
    iterations: int
    initial_error: float
    final_error: float
    next_decrease: float = float("nan")
    gauss_newton_iterations: int = 0


def variable_dims(problem: CalibrationProblem) -> list[tuple[int, int]]:
    """The variables of :func:`build_graph` as ``(key, tangent dimension)`` pairs, in a fixed order:
    the free kinematic entries, the joint angles ``J(i)``, then the target poses ``X(i)``."""
    K, L = problem.n_snapshots, problem.n_joints
    dims: list[tuple[int, int]] = []
    if problem.kin_key is not None:
        dims.append((problem.kin_key, int((~problem.fixed).sum())))
    if problem.estimate_theta:
        dims += [(J(i), L) for i in range(K)]
    if problem.formulation == "bundle":
        dims += [(X(i), 6) for i in range(K)]
    return dims


def _levenberg_marquardt(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, max_iterations: int) -> GraphSolution:
    initial_error = graph.error(values)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, lm_params(max_iterations))
    result = gtsam.Values(optimizer.optimize())
    iterations, final_error = optimizer.iterations(), graph.error(result)
    next_decrease = float("nan")
    if iterations >= max_iterations:  # stopped on the cap: how much was still to gain?
        optimizer.iterate()
        next_decrease = max(final_error - optimizer.error(), 0.0)
    return GraphSolution(result, iterations, initial_error, final_error, next_decrease)


def solve_graph(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    max_iterations: int,
    dims: list[tuple[int, int]] | None = None,
) -> GraphSolution:
    """Levenberg-Marquardt (:func:`lm_params`) from ``values``; with ``dims`` (:func:`variable_dims`)
    and at most :data:`dcc_fg.gauss_newton.DENSE_LIMIT` unknowns, also the dense line-search
    Gauss-Newton (:func:`dcc_fg.gauss_newton.gauss_newton`) from the same start, confirmed by a
    Levenberg-Marquardt solve from its end; the lower error is kept.

    Why both: on nearly degenerate 3-joint mechanisms Levenberg-Marquardt crawls along a curved, flat
    valley and stops on its cap short of the minimum, where Gauss-Newton reaches it in ~10 steps;
    far from a minimum the damped steps are the safer ones. A gtsam failure becomes an
    :class:`~dcc_fg.util.errors.EstimatorError` of the stage "Levenberg-Marquardt solve" (a failed
    Gauss-Newton solve only leaves the Levenberg-Marquardt result).
    """
    with stage(
        "Levenberg-Marquardt solve",
        hint="check the initial kinematics (--gimbal) or start from --init auto; a robust loss (--robust) "
        "helps against outlier corners",
    ):
        lm = _levenberg_marquardt(graph, values, max_iterations)
        if dims is None:
            return lm
        try:  # ValueError also for a problem above the dense limit
            gn = gauss_newton(graph, values, dims, min(GN_MAX_ITERATIONS, max_iterations))
        except (RuntimeError, ValueError, np.linalg.LinAlgError) as exc:
            logger.debug("dense Gauss-Newton failed (%s); keeping Levenberg-Marquardt", exc)
            return lm
        if not gn.final_error < lm.final_error:
            return lm
        confirm = _levenberg_marquardt(graph, gn.values, max_iterations)  # never raises the error
        return replace(confirm, initial_error=lm.initial_error, gauss_newton_iterations=gn.iterations)


@dataclass
class SolutionArrays:
    """The optimized variables as arrays: free kinematic entries (None when all are held), the full
    kinematic vector, joint angles (K, L) in rad and target poses ``T_st`` (K, 4, 4)."""

    kin_free: FloatArray | None
    kin: FloatArray
    thetas: FloatArray
    T_st: FloatArray


def solution_arrays(problem: CalibrationProblem, result: gtsam.Values) -> SolutionArrays:
    """Read the variables of :func:`build_graph` back from the optimized values (the joint angles and
    target poses that are not variables keep their initial values)."""
    K = problem.n_snapshots
    kin_free = result.atVector(problem.kin_key) if problem.kin_key is not None else None
    kin = problem.layout.expand(kin_free)
    thetas = np.array([result.atVector(J(i)) for i in range(K)]) if problem.estimate_theta else problem.thetas0
    if problem.formulation == "bundle":
        T_st = np.array([result.atPose3(X(i)).matrix() for i in range(K)])
    else:
        T_st = problem.T_st0
    return SolutionArrays(kin_free, kin, thetas, T_st)


def pixel_residuals(problem: CalibrationProblem, sol: SolutionArrays) -> tuple[list[FloatArray], list[FloatArray]]:
    """Per snapshot, the (N, 2) pixel residuals h(x) - z of the static and of the dynamic camera at the
    solution, in the formulation's own sense (unwhitened, no robust loss)."""
    res_s, res_d = [], []
    layout, cams = problem.layout, problem.cams
    for i, m in enumerate(problem.meas):
        if problem.formulation == "bundle":
            blocks = bundle_residuals(layout, sol.kin_free, sol.thetas[i], sol.T_st[i], m, cams, False)
            res_s.append(blocks[0][0])
            res_d.append(blocks[1][0])
        else:
            P_s, P_d = problem.pnp_points[i]
            blocks = two_way_residuals(
                layout, sol.kin_free, sol.thetas[i], P_s, m.z_dynamic, P_d, m.z_static, cams, False
            )
            res_d.append(blocks[0][0])
            res_s.append(blocks[1][0])
    return res_s, res_d
