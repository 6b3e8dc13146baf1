"""The dense line-search Gauss-Newton solver (dcc_fg.gauss_newton) on problems with known minima."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from dcc_fg.calibrate import CalibrationOptions, calibrate
from dcc_fg.calibration_graph import solve_graph
from dcc_fg.gauss_newton import DENSE_LIMIT, gauss_newton, gauss_newton_step
from dcc_fg.sim.calibration_scene import SimulatedCalibration

KEY = 0


def residual_factor(fn, jac, key: int = KEY, dim: int = 2) -> gtsam.CustomFactor:
    """A factor with residual fn(x) and Jacobian jac(x) on one vector variable (unit noise)."""

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        x = values.atVector(this.keys()[0])
        if H is not None:
            H[0] = jac(x)
        return fn(x)

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(len(fn(np.zeros(dim)))), [key], error)


def rosenbrock_graph(a: float, b: float) -> gtsam.NonlinearFactorGraph:
    """0.5 * [(a - x)^2 + b (y - x^2)^2]: a curved valley with its minimum (a, a^2) at zero error."""
    s = np.sqrt(b)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(
        residual_factor(
            lambda x: np.array([a - x[0], s * (x[1] - x[0] ** 2)]),
            lambda x: np.array([[-1.0, 0.0], [-2.0 * s * x[0], s]]),
        )
    )
    return graph


def start(x: np.ndarray) -> gtsam.Values:
    values = gtsam.Values()
    values.insert(KEY, x)
    return values


@pytest.mark.parametrize("seed", range(10))
def test_reaches_the_bottom_of_random_curved_valleys(seed: int) -> None:
    """Rosenbrock valleys of random position and steepness (b up to 1e4), random starts: the minimum
    to 1e-8, in far fewer steps than a crawl would need."""
    rng = np.random.default_rng(seed)
    a, b = rng.uniform(-2.0, 2.0), 10.0 ** rng.uniform(1.0, 4.0)
    graph = rosenbrock_graph(a, b)
    x0 = np.array([rng.uniform(-2.0, 2.0), rng.uniform(-1.0, 3.0)])
    res = gauss_newton(graph, start(x0), [(KEY, 2)], max_iterations=100)
    x = res.values.atVector(KEY)
    assert res.converged
    np.testing.assert_allclose(x, [a, a * a], atol=1e-8)
    assert res.final_error < 1e-16 and res.final_error <= res.initial_error
    assert res.iterations < 60


def test_step_is_the_least_squares_solution_when_determined() -> None:
    rng = np.random.default_rng(3)
    A = rng.normal(size=(40, 7)) * 10.0 ** rng.uniform(-3, 3, size=7)  # badly scaled columns
    b = rng.normal(size=40)
    np.testing.assert_allclose(gauss_newton_step(A.T @ A, A.T @ b), np.linalg.lstsq(A, b, rcond=None)[0], rtol=1e-7)


def test_step_leaves_undetermined_directions_alone() -> None:
    """A direction with no information (the residuals see x0 + x1 only) gets no step: the
    minimum-norm solution in Jacobi-scaled coordinates."""
    A = np.array([[1.0, 1.0, 0.0], [0.0, 0.0, 2.0], [2.0, 2.0, 1.0]])
    b = np.array([1.0, -2.0, 0.5])
    dx = gauss_newton_step(A.T @ A, A.T @ b)
    assert abs(dx[0] - dx[1]) < 1e-12  # nothing along the null direction (1, -1, 0)
    np.testing.assert_allclose(A @ dx, A @ np.linalg.lstsq(A, b, rcond=None)[0], atol=1e-10)


def test_singular_problem_converges_without_raising() -> None:
    """Residuals that depend on x0 + x1 only (one direction undetermined): GTSAM's own Gauss-Newton
    raises an indeterminate-system error here; this one converges to a minimum."""
    graph = gtsam.NonlinearFactorGraph()
    graph.add(
        residual_factor(
            lambda x: np.array([np.sin(x[0] + x[1]) - 0.5, (x[0] + x[1]) ** 2 - 0.25]),
            lambda x: np.array([[np.cos(x[0] + x[1])] * 2, [2.0 * (x[0] + x[1])] * 2]),
        )
    )
    with pytest.raises(RuntimeError):
        gtsam.GaussNewtonOptimizer(graph, start(np.array([0.1, 0.2]))).optimize()
    res = gauss_newton(graph, start(np.array([0.1, 0.2])), [(KEY, 2)])
    x = res.values.atVector(KEY)
    assert res.converged and res.final_error < 1e-3
    assert abs(x[0] - x[1] - (0.1 - 0.2)) < 1e-12  # the undetermined direction did not move


def test_solve_graph_keeps_the_lower_of_both_solvers() -> None:
    """On a steep valley with an iteration cap of 40 (each solver's), Levenberg-Marquardt alone stops short; with the
    variables given, the solve reaches the minimum and never ends above Levenberg-Marquardt."""
    graph = rosenbrock_graph(1.0, 1e4)
    values = start(np.array([-1.5, 2.0]))
    lm_only = solve_graph(graph, values, 40)
    both = solve_graph(graph, values, 40, [(KEY, 2)])
    assert both.final_error <= lm_only.final_error
    assert both.final_error < 1e-16 < lm_only.final_error
    assert lm_only.iterations == 40 and 0 < both.gauss_newton_iterations <= 40
    assert both.iterations < 40  # the confirming Levenberg-Marquardt solve did not stop on its cap
    np.testing.assert_allclose(both.values.atVector(KEY), [1.0, 1.0], atol=1e-8)


def test_refuses_problems_above_its_dense_limit() -> None:
    with pytest.raises(ValueError, match="more than its limit"):
        gauss_newton(gtsam.NonlinearFactorGraph(), gtsam.Values(), [(KEY, DENSE_LIMIT + 1)])


def test_calibration_with_gauss_newton_ends_no_higher(demo_sim: SimulatedCalibration) -> None:
    """The demo calibration with ``gauss_newton=True``: the same minimum as Levenberg-Marquardt alone
    (error within 1e-9 relative, or lower), and the cap semantics kept (iterations below the cap)."""
    data = demo_sim.calibration_set
    lm = calibrate(data, demo_sim.initial, CalibrationOptions(compute_covariance=False))
    both = calibrate(data, demo_sim.initial, CalibrationOptions(compute_covariance=False, gauss_newton=True))
    assert both.final_error <= lm.final_error * (1.0 + 1e-9)
    assert both.iterations < both.options.max_iterations
    np.testing.assert_allclose(both.calibration.kin, lm.calibration.kin, atol=1e-6)
