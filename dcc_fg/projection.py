"""Variable-projection solve: Levenberg-Marquardt on the kinematics alone, the per-snapshot variables
re-solved at every step.

Why it exists: on 3-joint chains whose axes nearly intersect, the directions held by the weak prior
(:mod:`dcc_fg.degeneracy`) form a long, curved valley of the data cost. The joint angles follow a
move of the kinematics along it nonlinearly, so a step of the joint problem (kinematics, joint angles,
target poses together) leaves the valley and Levenberg-Marquardt crawls along it at ~1e-8 of the cost
per iteration (random L = 3 family, seed 26: 500 iterations on the iteration cap, 2e-5 relative above
the truth start). Here each step moves only the free kinematic entries ``k``, with the per-snapshot
variables ``r`` (joint angles ``J(i)``, target poses ``X(i)``) eliminated (Schur complement of the
information matrix)::

    S = H_kk - H_kr H_rr^-1 H_rk,   g = eta_k - H_kr H_rr^-1 eta_r,   (S + lambda diag(S)) dk = g,

then ``r`` is moved by its linear prediction ``H_rr^-1 (eta_r - H_rk dk)`` and re-solved with ``k``
held (a stiff prior), so every trial point lies at the bottom of the per-snapshot problems. The step is
accepted when the error decreases (lambda shrinks 5x) and retried with a larger lambda (8x) otherwise.
(seed 26: 3.6291859 -> 3.6291048 in 299 steps, below the truth start's 3.6291053; seed 11: converged
at 2.3896535, 0.2 chi-square above the truth start's minimum, which is another one.)

Units: GTSAM's error ``0.5 * sum of squared whitened residuals``; steps in the tangent spaces of the
variables (``gtsam.Values.retract``; the kinematic key is a vector, metres and radians).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from dcc_fg.gauss_newton import DENSE_LIMIT, ordering_of, retract

FloatArray = NDArray[np.float64]

MAX_STEPS = 300  # outer steps (~0.1 s each for 25 snapshots)
REL_DECREASE_TOL = 1e-12  # converged when a step lowers the error by less than this, relatively
LAMBDA_START = 1e-3
LAMBDA_MIN = 1e-12
LAMBDA_MAX = 1e8  # no descent even with this damping: a minimum to working precision
HOLD_SIGMA = 1e-10  # stiff prior that holds the kinematics while the per-snapshot variables are re-solved
INNER_ITERATIONS = 50


@dataclass
class ProjectionResult:
    """Where the projected solve stopped: values, outer steps, initial and final error (GTSAM units)
    and whether it converged (rather than stopping on :data:`MAX_STEPS`)."""

    values: gtsam.Values
    steps: int
    initial_error: float
    final_error: float
    converged: bool


def resolve_per_snapshot(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, kin_key: int) -> gtsam.Values:
    """``values`` with every variable but ``kin_key`` re-solved (Levenberg-Marquardt) while the
    kinematics are held at their value by a stiff prior (1-sigma :data:`HOLD_SIGMA`)."""
    held = gtsam.NonlinearFactorGraph(graph)
    kin = values.atVector(kin_key)
    held.add(gtsam.PriorFactorVector(kin_key, kin, gtsam.noiseModel.Isotropic.Sigma(len(kin), HOLD_SIGMA)))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(INNER_ITERATIONS)
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-14)
    out = gtsam.Values(gtsam.LevenbergMarquardtOptimizer(held, values, params).optimize())
    out.update(kin_key, kin)  # exactly the held value (the prior leaves ~1e-10 of play)
    return out


def reduced_system(H: FloatArray, eta: FloatArray, n_kin: int) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Schur complement of the information matrix ``H`` (information vector ``eta``) onto its first
    ``n_kin`` variables: ``(S, g, H_rr^-1 H_rk, H_rr^-1 eta_r)``."""
    Hkk, Hkr, Hrr = H[:n_kin, :n_kin], H[:n_kin, n_kin:], H[n_kin:, n_kin:]
    factor = scipy.linalg.cho_factor(Hrr)
    solved = scipy.linalg.cho_solve(factor, np.column_stack([Hkr.T, eta[n_kin:]]))
    A, b = solved[:, :n_kin], solved[:, n_kin]
    return Hkk - Hkr @ A, eta[:n_kin] - Hkr @ b, A, b


def projected_solve(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    dims: Sequence[tuple[int, int]],
    max_steps: int = MAX_STEPS,
) -> ProjectionResult:
    """Levenberg-Marquardt on the kinematics with the per-snapshot variables eliminated (module
    docstring), from ``values``.

    ``dims``: ``(key, tangent dimension)`` pairs of every variable of ``graph``, the kinematic key
    first (:func:`dcc_fg.calibration_graph.variable_dims`). Raises ValueError above
    :data:`dcc_fg.gauss_newton.DENSE_LIMIT` unknowns (the elimination is dense) and
    ``numpy.linalg.LinAlgError`` when the per-snapshot block is not positive definite.
    """
    n = sum(dim for _, dim in dims)
    if n > DENSE_LIMIT:
        raise ValueError(f"projected solve: {n} unknowns, more than its dense limit of {DENSE_LIMIT}")
    kin_key, n_kin = dims[0]
    ordering = ordering_of(dims)
    values = resolve_per_snapshot(graph, values, kin_key)
    error = initial_error = graph.error(values)
    lam, steps, converged = LAMBDA_START, 0, False
    while steps < max_steps and not converged:
        steps += 1
        H, eta = graph.linearize(values).hessian(ordering)
        S, g, A, b = reduced_system(H, eta, n_kin)
        d = np.sqrt(np.maximum(np.diag(S), 1e-300))
        S_scaled, g_scaled = S / np.outer(d, d), g / d
        while True:
            dk = np.linalg.solve(S_scaled + lam * np.diag(np.diag(S_scaled)), g_scaled) / d
            trial = retract(values, dims, np.concatenate([dk, b - A @ dk]))
            trial = resolve_per_snapshot(graph, trial, kin_key)
            trial_error = graph.error(trial)
            if np.isfinite(trial_error) and trial_error < error:
                decrease = error - trial_error
                values, error = trial, trial_error
                lam = max(lam / 5.0, LAMBDA_MIN)
                converged = decrease < REL_DECREASE_TOL * max(error, 1e-300)
                break
            lam *= 8.0
            if lam > LAMBDA_MAX:
                converged = True
                break
    return ProjectionResult(values, steps, initial_error, error, converged)
