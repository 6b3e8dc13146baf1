"""Dense Gauss-Newton with a backtracking line search, for small, nearly degenerate least squares.

Why it exists: on nearly degenerate mechanisms (3-joint chains whose axes almost intersect) the
calibration's cost has a long, curved, almost flat valley. Levenberg-Marquardt's damping grows in it
and the solve crawls along the valley until its iteration cap, short of the minimum (issue 14: four
of fifty random L = 3 members stopped 1e-5 to 3e-3 relative above the truth start's cost). The
undamped Gauss-Newton step, solved with the Jacobi-scaled normal equations (a pseudo-inverse drops the
directions whose scaled information is below :data:`REL_TOL` of the largest), goes straight to the
bottom of such a valley; a backtracking line search on the nonlinear error keeps every step a
descent. GTSAM's own Gauss-Newton and Dogleg optimizers stop at once on these graphs ("indeterminate
system": the unscaled normal equations are numerically singular), hence this dense solver.

Units: the error is GTSAM's ``0.5 * sum of squared whitened residuals``; steps are in each variable's
tangent space (``gtsam.Values.retract``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

REL_TOL = 1e-12  # scaled eigenvalues below REL_TOL * largest are dropped by the pseudo-inverse
MIN_STEP = 2.0**-12  # the line search gives up below this fraction of the Gauss-Newton step
REL_DECREASE_TOL = 1e-13  # converged when an iteration lowers the error by less than this, relatively
DENSE_LIMIT = 2000  # unknowns up to which the dense solve is affordable (an eigendecomposition per step)


@dataclass
class GaussNewtonResult:
    """Where the solve stopped: values, iterations, initial and final error (GTSAM units) and whether
    it stopped on convergence (the error stopped decreasing) rather than on the iteration cap."""

    values: gtsam.Values
    iterations: int
    initial_error: float
    final_error: float
    converged: bool


def ordering_of(dims: Sequence[tuple[int, int]]) -> gtsam.Ordering:
    """The elimination ordering of the ``(key, dimension)`` pairs, in their order (the column order
    of ``GaussianFactorGraph.hessian``)."""
    ordering = gtsam.Ordering()
    for key, _ in dims:
        ordering.push_back(key)
    return ordering


def scaled_pseudo_inverse(H: FloatArray, rel_tol: float = REL_TOL) -> FloatArray:
    """The pseudo-inverse of the information matrix ``H`` taken in Jacobi-scaled coordinates: scaled
    eigenvalues below ``rel_tol`` of the largest are dropped (directions the data and priors do not
    determine), so the result stays finite on nearly singular problems."""
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    w, V = np.linalg.eigh(H / np.outer(d, d))
    keep = w > rel_tol * w.max()
    return ((V[:, keep] / w[keep]) @ V[:, keep].T) / np.outer(d, d)


def gauss_newton_step(H: FloatArray, eta: FloatArray) -> FloatArray:
    """The minimum-norm solution (in Jacobi-scaled coordinates) of ``H dx = eta``.

    ``H`` is the information matrix, ``eta`` the information vector of the linearized graph
    (``GaussianFactorGraph.hessian``), so ``dx`` is the Gauss-Newton step
    (:func:`scaled_pseudo_inverse` with :data:`REL_TOL`).
    """
    return scaled_pseudo_inverse(H) @ eta


def retract(values: gtsam.Values, dims: Sequence[tuple[int, int]], dx: FloatArray) -> gtsam.Values:
    """``values`` moved by the stacked tangent step ``dx`` (in the order of ``dims``)."""
    delta = gtsam.VectorValues()
    at = 0
    for key, dim in dims:
        delta.insert(key, dx[at : at + dim])
        at += dim
    return values.retract(delta)


def gauss_newton(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    dims: Sequence[tuple[int, int]],
    max_iterations: int = 50,
) -> GaussNewtonResult:
    """Gauss-Newton from ``values`` over the variables ``dims`` (``(key, tangent dimension)`` pairs,
    every variable of ``graph``), each step shortened by halving until the error decreases.

    Stops when an iteration lowers the error by less than :data:`REL_DECREASE_TOL` relatively, when no
    step down to :data:`MIN_STEP` of the Gauss-Newton step decreases it, or after ``max_iterations``.
    Raises ValueError when the problem has more than :data:`DENSE_LIMIT` unknowns.
    """
    n = sum(dim for _, dim in dims)
    if n > DENSE_LIMIT:
        raise ValueError(f"dense Gauss-Newton: {n} unknowns, more than its limit of {DENSE_LIMIT}")
    ordering = ordering_of(dims)
    error = initial_error = graph.error(values)
    converged = False
    iterations = 0
    while iterations < max_iterations:
        iterations += 1
        H, eta = graph.linearize(values).hessian(ordering)
        dx = gauss_newton_step(H, eta)
        step, trial, trial_error = 1.0, values, error
        while step >= MIN_STEP:
            trial = retract(values, dims, step * dx)
            trial_error = graph.error(trial)
            if np.isfinite(trial_error) and trial_error < error:
                break
            step *= 0.5
        if not (np.isfinite(trial_error) and trial_error < error):
            converged = True  # no descent along the Gauss-Newton direction: a minimum to working precision
            break
        decrease = error - trial_error
        values, error = trial, trial_error
        if decrease < REL_DECREASE_TOL * max(error, 1e-300):
            converged = True
            break
    return GaussNewtonResult(values, iterations, initial_error, error, converged)
