"""GTSAM calibration factors: linearized Jacobians against central differences through Values.retract."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import J, X

from dcc_fg.calibration_graph import KIN_KEY, gauge_fixed_kin, snapshot_measurements
from dcc_fg.init import pnp_pose
from dcc_fg.sim.calibration_scene import SceneConfig, simulate_calibration
from factors import chain
from factors.calibration import KinLayout, RobustLoss, bundle_factor, mean_prior_factor, two_way_factor


def numeric_jacobian(
    factor: gtsam.NonlinearFactor, values: gtsam.Values, dims: list[tuple[int, int]], h: float = 1e-6
) -> np.ndarray:
    cols = []
    for key, dim in dims:
        for k in range(dim):
            out = []
            for sign in (1.0, -1.0):
                dx = gtsam.VectorValues()
                for key2, dim2 in dims:
                    z = np.zeros(dim2)
                    if key2 == key:
                        z[k] = sign * h
                    dx.insert(key2, z)
                out.append(factor.whitenedError(values.retract(dx)))
            cols.append((out[0] - out[1]) / (2 * h))
    return np.array(cols).T


def analytic_jacobian(factor: gtsam.NonlinearFactor, values: gtsam.Values, keys: list[int]) -> np.ndarray:
    ordering = gtsam.Ordering()
    for k in keys:
        ordering.push_back(k)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(factor)
    A, _ = graph.linearize(values).jacobian(ordering)
    return A


def assert_blocks_match(A: np.ndarray, N: np.ndarray, dims: list[tuple[int, int]]) -> None:
    """Every key's Jacobian block matches central differences to a relative error < 1e-6
    (relative to that block's largest entry, so a small block cannot hide behind a large one)."""
    col = 0
    for key, dim in dims:
        a, n = A[:, col : col + dim], N[:, col : col + dim]
        rel = np.max(np.abs(a - n)) / np.max(np.abs(n))
        assert rel < 1e-6, (gtsam.DefaultKeyFormatter(key), rel)
        col += dim


def setup(L: int, robust: RobustLoss | None):
    sim = simulate_calibration(1, SceneConfig(n_joints=L, n_calibration=4, n_validation=1))
    data = sim.calibration_set
    fixed = gauge_fixed_kin(L, "encoderless")
    layout = KinLayout(sim.initial.kin.copy(), ~fixed, L)
    m = snapshot_measurements(data, data.snapshots[2])
    cams = (data.static_camera, data.dynamic_camera)
    values = gtsam.Values()
    values.insert(KIN_KEY, sim.initial.kin[~fixed])
    values.insert(J(0), sim.joints_calibration[2] + 0.05)
    values.insert(X(0), gtsam.Pose3(sim.T_st_calibration[2]))
    return sim, layout, m, cams, values, int((~fixed).sum())


@pytest.mark.parametrize("L", [0, 1, 2, 3])
@pytest.mark.parametrize(
    "robust", [None, RobustLoss("huber", 1.0), RobustLoss("cauchy", 1.0)], ids=["l2", "huber", "cauchy"]
)
def test_bundle_factor_jacobians(L: int, robust: RobustLoss | None) -> None:
    sim, layout, m, cams, values, nf = setup(L, robust)
    keys = [KIN_KEY, X(0)] if L == 0 else [KIN_KEY, J(0), X(0)]
    f = bundle_factor(layout, m, cams, 0.4, X(0), KIN_KEY, J(0) if L else None, None if L else np.zeros(0), robust)
    dims = [(KIN_KEY, nf)] + ([(J(0), L)] if L else []) + [(X(0), 6)]
    A = analytic_jacobian(f, values, keys)
    N = numeric_jacobian(f, values, dims)
    assert_blocks_match(A, N, dims)


@pytest.mark.parametrize("L", [0, 1, 2, 3])
def test_two_way_factor_jacobians(L: int) -> None:
    sim, layout, m, cams, values, nf = setup(L, None)
    T_st = pnp_pose(cams[0], m.p_t_static, m.z_static)
    T_dt = pnp_pose(cams[1], m.p_t_dynamic, m.z_dynamic)
    P_s = m.p_t_dynamic @ T_st[:3, :3].T + T_st[:3, 3]
    P_d = m.p_t_static @ T_dt[:3, :3].T + T_dt[:3, 3]
    f = two_way_factor(
        layout,
        P_s,
        m.z_dynamic,
        P_d,
        m.z_static,
        cams,
        0.4,
        KIN_KEY,
        J(0) if L else None,
        None if L else np.zeros(0),
        RobustLoss("huber", 1.5),
    )
    keys = [KIN_KEY] + ([J(0)] if L else [])
    dims = [(KIN_KEY, nf)] + ([(J(0), L)] if L else [])
    A = analytic_jacobian(f, values, keys)
    N = numeric_jacobian(f, values, dims)
    assert_blocks_match(A, N, dims)


def test_mean_prior_factor() -> None:
    keys = [J(i) for i in range(5)]
    values = gtsam.Values()
    rng = np.random.default_rng(0)
    for k in keys:
        values.insert(k, rng.normal(size=2))
    f = mean_prior_factor(keys, 1, 0.3, 1e-3)
    A = analytic_jacobian(f, values, keys)
    N = numeric_jacobian(f, values, [(k, 2) for k in keys])
    np.testing.assert_allclose(A, N, rtol=1e-6, atol=1e-6)


def test_robust_loss_is_exact_cost() -> None:
    """The transformed residual's squared norm equals rho(|r|^2) per corner."""
    r = np.random.default_rng(0).normal(size=(100, 2)) * 3
    for kind in ("huber", "cauchy"):
        loss = RobustLoss(kind, 1.345)
        rn, _ = loss.apply(r, np.zeros((100, 2, 1)))
        np.testing.assert_allclose(np.sum(rn**2, axis=1), loss.rho(np.sum(r**2, axis=1))[0], rtol=1e-12)


def test_kin_names_cover_vector() -> None:
    for L in range(4):
        assert len(chain.kin_names(L)) == chain.n_kin(L) == chain.kin_is_angle(L).size


@pytest.mark.parametrize("formulation", ["bundle", "two_way"])
def test_sigma_pair_whitens_each_camera_by_its_own_sigma(formulation: str) -> None:
    """``sigma=(static, dynamic)``: the static image's rows divided by the first, the dynamic image's by
    the second, in both formulations (the two-way factor's rows start with the dynamic image), and the
    Jacobians still match numerical differentiation."""
    sim, layout, m, cams, values, nf = setup(2, None)
    ns, nd = 2 * m.z_static.shape[0], 2 * m.z_dynamic.shape[0]
    if formulation == "bundle":

        def make(sigma):  # type: ignore[no-untyped-def]
            return bundle_factor(layout, m, cams, sigma, X(0), KIN_KEY, J(0), None)

        keys, dims, rows = [KIN_KEY, J(0), X(0)], [(KIN_KEY, nf), (J(0), 2), (X(0), 6)], (slice(0, ns), slice(ns, None))
    else:
        T_st = pnp_pose(cams[0], m.p_t_static, m.z_static)
        T_dt = pnp_pose(cams[1], m.p_t_dynamic, m.z_dynamic)
        P_s = m.p_t_dynamic @ T_st[:3, :3].T + T_st[:3, 3]
        P_d = m.p_t_static @ T_dt[:3, :3].T + T_dt[:3, 3]

        def make(sigma):  # type: ignore[no-untyped-def]
            return two_way_factor(layout, P_s, m.z_dynamic, P_d, m.z_static, cams, sigma, KIN_KEY, J(0))

        keys, dims, rows = [KIN_KEY, J(0)], [(KIN_KEY, nf), (J(0), 2)], (slice(nd, None), slice(0, nd))
    unit = make(1.0).unwhitenedError(values)
    pair = make((0.3, 0.7)).unwhitenedError(values)
    np.testing.assert_allclose(pair[rows[0]], unit[rows[0]] / 0.3, rtol=1e-12)
    np.testing.assert_allclose(pair[rows[1]], unit[rows[1]] / 0.7, rtol=1e-12)
    f = make((0.3, 0.7))
    assert_blocks_match(analytic_jacobian(f, values, keys), numeric_jacobian(f, values, dims), dims)
