"""The projected solve (dcc_fg.projection): Levenberg-Marquardt on the kinematics with the
per-snapshot variables eliminated reaches the joint minimum (checked against scipy's least squares),
its reduced system is the exact Schur complement, and on a nearly intersecting 3-axis gimbal it ends
at or below the joint solve's data cost."""

from __future__ import annotations

import logging

import gtsam
import numpy as np
import pytest
import scipy.optimize
from test_degeneracy import spherical_wrist

import dcc_fg.calibrate as cal
from dcc_fg.calibrate import CalibrationOptions, calibrate, data_cost
from dcc_fg.calibration_graph import GraphSolution
from dcc_fg.data import with_joints
from dcc_fg.gauss_newton import DENSE_LIMIT
from dcc_fg.projection import projected_solve, reduced_system
from dcc_fg.studies.calibration_accuracy import T_ds_errors, cramer_rao_bound

KIN = gtsam.symbol("k", 0)
N_SNAPSHOTS, N_OBS = 8, 6


def _x(i: int) -> int:
    return gtsam.symbol("x", i)


def _model(k: np.ndarray, x: float, t: np.ndarray) -> np.ndarray:
    """Observations of snapshot variable x at times t under the 'kinematics' k: curved in both."""
    return np.sin(k[0] + x * t) + k[1] * x**2 * t


def _jacobians(k: np.ndarray, x: float, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = np.cos(k[0] + x * t)
    return np.column_stack([c, x**2 * t]), (c * t + 2.0 * k[1] * x * t)[:, None]


def synthetic_problem(seed: int) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, np.ndarray, np.ndarray]:
    """A random instance: graph, a start ~0.3 away from the truth, the times and the observations."""
    rng = np.random.default_rng(seed)
    k_true = rng.uniform([-1.0, 0.5], [1.0, 1.5])
    x_true = rng.uniform(-1.0, 1.0, N_SNAPSHOTS)
    t = np.linspace(0.2, 2.0, N_OBS)
    y = np.array([_model(k_true, x, t) for x in x_true]) + rng.normal(0.0, 0.05, (N_SNAPSHOTS, N_OBS))
    graph = gtsam.NonlinearFactorGraph()
    for i in range(N_SNAPSHOTS):

        def error(this: gtsam.CustomFactor, v: gtsam.Values, H: list | None, i: int = i) -> np.ndarray:
            k, x = v.atVector(KIN), float(v.atVector(_x(i))[0])
            if H is not None:
                H[0], H[1] = _jacobians(k, x, t)
            return _model(k, x, t) - y[i]

        graph.add(gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(N_OBS, 0.05), [KIN, _x(i)], error))
    values = gtsam.Values()
    values.insert(KIN, k_true + rng.uniform(-0.3, 0.3, 2))
    for i in range(N_SNAPSHOTS):
        values.insert(_x(i), np.array([x_true[i] + rng.uniform(-0.2, 0.2)]))
    return graph, values, t, y


@pytest.mark.parametrize("seed", range(6))
def test_projected_solve_reaches_the_minimum_of_the_joint_problem(seed: int) -> None:
    graph, values, t, y = synthetic_problem(seed)
    dims = [(KIN, 2)] + [(_x(i), 1) for i in range(N_SNAPSHOTS)]
    res = projected_solve(graph, values, dims)
    assert res.converged and res.final_error <= res.initial_error

    def residuals(p: np.ndarray) -> np.ndarray:
        return np.concatenate([(_model(p[:2], p[2 + i], t) - y[i]) / 0.05 for i in range(N_SNAPSHOTS)])

    p0 = np.concatenate([values.atVector(KIN), [values.atVector(_x(i))[0] for i in range(N_SNAPSHOTS)]])
    ref = scipy.optimize.least_squares(residuals, p0, xtol=1e-15, ftol=1e-15, gtol=1e-15, method="lm")
    assert res.final_error == pytest.approx(0.5 * float(ref.fun @ ref.fun), rel=1e-9)
    np.testing.assert_allclose(res.values.atVector(KIN), ref.x[:2], atol=1e-6)
    assert res.final_error == pytest.approx(graph.error(res.values), rel=1e-12)


def test_reduced_system_is_the_exact_elimination() -> None:
    """The kinematic step of the reduced system and the predicted per-snapshot step together solve
    the full normal equations."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(40, 12))
    H, eta = A.T @ A, rng.normal(size=12)
    S, g, A_rk, b = reduced_system(H, eta, 4)
    dk = np.linalg.solve(S, g)
    np.testing.assert_allclose(np.concatenate([dk, b - A_rk @ dk]), np.linalg.solve(H, eta), rtol=1e-9, atol=1e-12)


def test_projected_solve_refuses_a_problem_above_the_dense_limit() -> None:
    graph, values, _, _ = synthetic_problem(0)
    with pytest.raises(ValueError, match="dense limit"):
        projected_solve(graph, values, [(KIN, 2), (_x(0), DENSE_LIMIT)])


@pytest.mark.slow
def test_projected_polish_ends_at_or_below_the_joint_solve_on_a_nearly_intersecting_gimbal() -> None:
    """Started at the truth, with directions held by the weak prior: the projected polish lowers (never
    raises) the data cost, reports what it did, and keeps T_ds at the bound (2.5x for one draw, as in
    tests/test_degeneracy.py)."""
    sim = spherical_wrist(2, 20, offset_m=0.005)  # axes that miss each other by up to 5 mm
    d = sim.calibration_set
    data = with_joints(d, sim.joints_calibration)
    plain = calibrate(data, sim.truth, CalibrationOptions())
    projected = calibrate(data, sim.truth, CalibrationOptions(project_held=True))
    assert plain.extra.get("held_by_prior"), "the scene must leave weakly determined directions"
    report = projected.extra["held_projection"]
    # this scene: 4 held directions; 217.905 -> 217.855 (1.1 chi-square units), converged in 187 steps
    assert report["kept"] and report["converged"]
    assert report["data_error_after"] < report["data_error_before"]
    assert data_cost(projected) <= data_cost(plain) * (1.0 + 1e-12)
    crb = cramer_rao_bound(d, sim.truth, sim.joints_calibration, sim.T_st_calibration, 0.3)
    e = T_ds_errors(sim.truth, sim.joints_calibration, projected.calibration, projected.joint_angles)
    rot, tr = np.sqrt(np.mean(np.sum(e[:, :3] ** 2, 1))), np.sqrt(np.mean(np.sum(e[:, 3:] ** 2, 1)))
    assert rot <= 2.5 * crb.rotation_rms and tr <= 2.5 * crb.translation_rms, (rot, crb.rotation_rms, tr)
    # continued from the joint solve's result (dcc_fg.global_fit does this) instead of solved again: the
    # same projected solve from the same point, so the same solution without the joint solve's cost
    cont = cal.continue_projected(data, plain)
    assert cont is not None and cont.extra["held_projection"]["kept"]
    assert "continued" in cont.extra["held_polish"]  # not labelled as the weakened-prior polish
    assert data_cost(cont) == pytest.approx(data_cost(projected), rel=1e-9)
    dT = np.array([gtsam.Pose3(projected.T_ds(i)).localCoordinates(gtsam.Pose3(cont.T_ds(i))) for i in range(len(e))])
    assert np.max(np.abs(dT)) < 1e-3 * min(crb.rotation_rms, crb.translation_rms)
    assert cont.T_ds_covariances is not None and np.all(np.isfinite(cont.T_ds_covariances))
    again = cal.continue_projected(data, projected)  # at the bottom already: nothing (or round-off) to gain
    assert again is None or data_cost(again) == pytest.approx(data_cost(projected), rel=1e-9)


def test_a_projected_solve_stopped_on_its_cap_is_kept_with_a_warning(caplog) -> None:  # noqa: ANN001
    """Two steps are not enough here: the lower solution is kept, the report says it did not converge,
    a warning says so, and the joint solve's remaining decrease stays (the convergence health check
    reads it); a converged solve clears it."""
    graph, values, _, _ = synthetic_problem(1)
    dims = [(KIN, 2)] + [(_x(i), 1) for i in range(N_SNAPSHOTS)]
    solved = GraphSolution(values, 500, graph.error(values), graph.error(values), next_decrease=0.5)
    with caplog.at_level(logging.WARNING, logger="dcc_fg.calibrate"):
        kept, report = cal.projected_polish(graph, graph, solved, dims, max_steps=2)
    assert report["kept"] and not report["converged"] and report["steps"] == 2
    assert kept.final_error < solved.final_error and kept.next_decrease == 0.5
    assert "stopped on its cap of 2 steps" in caplog.text
    kept, report = cal.projected_polish(graph, graph, solved, dims)
    assert report["kept"] and report["converged"] and np.isnan(kept.next_decrease)
