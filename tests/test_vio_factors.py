"""VIO reprojection factors (paper eq. 14-15): analytic Jacobians against central finite differences."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from dcc_fg.sim.trajectory import default_static_mount, flight_calibration
from factors.vio import (
    ChainCache,
    ProjectionFactory,
    gimbal_camera_pose_factor,
    gimbal_reprojection_factor,
    gimbal_residuals,
    static_projection_factor,
)

X, TH = gtsam.symbol("x", 0), gtsam.symbol("t", 0)
DIMS = {"x": 6, "t": 2, "l": 3, "c": 6}


def _lm(i: int) -> int:
    return gtsam.symbol("l", i)


def _scene(seed: int, n: int, static: bool = False) -> tuple[gtsam.Values, np.ndarray, np.ndarray, np.ndarray, object]:
    """Random body pose, joint angles and landmarks 3-15 m in front of the gimbal (or static) camera."""
    rng = np.random.default_rng(seed)
    cal = flight_calibration()
    T_sI = default_static_mount()
    theta = np.array([np.deg2rad(90.0), 0.0]) + rng.normal(size=2) * 0.3
    T_WI = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), rng.normal(size=3) * 5.0)
    T_cW = (np.eye(4) if static else cal.T_ds(theta)) @ T_sI @ T_WI.inverse().matrix()
    p_c = np.column_stack([rng.uniform(-0.5, 0.5, (n, 2)), np.ones(n)]) * rng.uniform(3.0, 15.0, (n, 1))
    T_Wc = np.linalg.inv(T_cW)
    p_W = p_c @ T_Wc[:3, :3].T + T_Wc[:3, 3]
    values = gtsam.Values()
    values.insert(X, T_WI)
    values.insert(TH, theta)
    for i in range(n):
        values.insert(_lm(i), p_W[i])
    z = p_c[:, :2] / p_c[:, 2:3] + rng.normal(size=(n, 2)) * 2e-3
    return values, z, theta, T_sI, cal


def _retract(values: gtsam.Values, key: int, delta: np.ndarray) -> gtsam.Values:
    out = gtsam.Values(values)
    sym = chr(gtsam.Symbol(key).chr())
    if sym in "xc":
        out.update(key, values.atPose3(key).retract(delta))
    elif sym == "t":
        out.update(key, values.atVector(key) + delta)
    else:
        out.update(key, values.atPoint3(key) + delta)
    return out


def _numeric(fun, values: gtsam.Values, key: int, h: float = 1e-6) -> np.ndarray:
    dim = DIMS[chr(gtsam.Symbol(key).chr())]
    cols = []
    for d in range(dim):
        e = np.zeros(dim)
        e[d] = h
        cols.append((fun(_retract(values, key, e)) - fun(_retract(values, key, -e))) / (2 * h))
    return np.stack(cols, axis=-1)


def _rel(J: np.ndarray, J_num: np.ndarray) -> float:
    return float(np.linalg.norm(J - J_num) / max(np.linalg.norm(J_num), 1e-12))


def _check_factor(factor: gtsam.NonlinearFactor, values: gtsam.Values) -> None:
    A, _ = factor.linearize(values).jacobian()
    col = 0
    for key in factor.keys():
        J_num = _numeric(factor.whitenedError, values, key)
        dim = J_num.shape[1]
        rel = _rel(A[:, col : col + dim], J_num)
        assert rel < 1e-6, f"key {gtsam.Symbol(key).string()}: relative error {rel:.2e}"
        col += dim


def test_gimbal_factor_jacobians() -> None:
    values, z, _, T_sI, cal = _scene(0, 6)
    cache = ChainCache(cal.kin, 2)
    for i in range(6):
        f = gimbal_reprojection_factor(z[i], 1e-3, X, _lm(i), TH, cache, T_sI)
        assert [gtsam.Symbol(k).string() for k in f.keys()] == ["x0", f"l{i}", "t0"]
        _check_factor(f, values)


def test_gimbal_residuals_vectorised_jacobians() -> None:
    values, z, _, T_sI, cal = _scene(3, 5)
    keys = [_lm(i) for i in range(5)]

    def res(v: gtsam.Values, jac: bool = False):
        p_W = np.array([v.atPoint3(k) for k in keys])
        return gimbal_residuals(v.atPose3(X).matrix(), p_W, v.atVector(TH), cal.kin, 2, T_sI, z, jac)

    J = res(values, True)
    assert _rel(J.d_pose, _numeric(lambda v: res(v).r, values, X)) < 1e-6
    assert _rel(J.d_theta, _numeric(lambda v: res(v).r, values, TH)) < 1e-6
    for i, k in enumerate(keys):
        assert _rel(J.d_point[i], _numeric(lambda v: res(v).r, values, k)[i]) < 1e-6
    # the single-observation factor is the same model
    cache = ChainCache(cal.kin, 2)
    for i, k in enumerate(keys):
        f = gimbal_reprojection_factor(z[i], 1.0, X, k, TH, cache, T_sI)
        np.testing.assert_allclose(f.unwhitenedError(values), J.r[i], atol=1e-14)


def test_gimbal_factor_zero_at_truth_and_huber() -> None:
    values, _, theta, T_sI, cal = _scene(1, 5)
    T_dW = cal.T_ds(theta) @ T_sI @ values.atPose3(X).inverse().matrix()
    p = np.array([values.atPoint3(_lm(i)) for i in range(5)]) @ T_dW[:3, :3].T + T_dW[:3, 3]
    z_exact = p[:, :2] / p[:, 2:3]
    cache = ChainCache(cal.kin, 2)
    f = gimbal_reprojection_factor(z_exact[0], 1e-3, X, _lm(0), TH, cache, T_sI)
    assert f.error(values) < 1e-18
    far = gimbal_reprojection_factor(z_exact[0] + 0.05, 1e-3, X, _lm(0), TH, cache, T_sI, huber_k=2.0)
    plain = gimbal_reprojection_factor(z_exact[0] + 0.05, 1e-3, X, _lm(0), TH, cache, T_sI)
    assert far.error(values) < 0.1 * plain.error(values)  # Huber grows linearly for a 70-sigma outlier


def test_static_factor_matches_numpy_model() -> None:
    values, z, _, T_sI, _ = _scene(2, 4, static=True)
    sigma = 2e-3
    for i in range(4):
        f = static_projection_factor(z[i], sigma, X, _lm(i), T_sI)
        _check_factor(f, values)
        r = gimbal_residuals(values.atPose3(X).matrix(), values.atPoint3(_lm(i)), None, None, 0, T_sI, z[i : i + 1])
        np.testing.assert_allclose(f.unwhitenedError(values), r.r[0], atol=1e-12)


def test_camera_pose_constraint_jacobians() -> None:
    values, _, theta, T_sI, cal = _scene(4, 1)
    C = gtsam.symbol("c", 0)
    DIMS["c"] = 6
    cache = ChainCache(cal.kin, 2)
    T_Wd = values.atPose3(X).compose(gtsam.Pose3(cal.T_ds(theta) @ T_sI).inverse())
    values.insert(C, T_Wd)
    f = gimbal_camera_pose_factor(X, TH, C, cache, T_sI, 1e-3, 1e-3)
    assert f.error(values) < 1e-18
    # away from zero error (the Log derivative matters there)
    values.update(C, T_Wd.retract(np.array([0.05, -0.03, 0.02, 0.1, 0.05, -0.2])))
    _check_factor_pose_retract(f, values)


def _check_factor_pose_retract(factor: gtsam.NonlinearFactor, values: gtsam.Values) -> None:
    A, _ = factor.linearize(values).jacobian()
    col = 0
    for key in factor.keys():
        sym = chr(gtsam.Symbol(key).chr())

        def fun(v: gtsam.Values) -> np.ndarray:
            return factor.whitenedError(v)

        if sym == "c":
            dim = 6
            cols = []
            for d in range(dim):
                e = np.zeros(dim)
                e[d] = 1e-6
                vp, vm = gtsam.Values(values), gtsam.Values(values)
                vp.update(key, values.atPose3(key).retract(e))
                vm.update(key, values.atPose3(key).retract(-e))
                cols.append((fun(vp) - fun(vm)) / 2e-6)
            J_num = np.stack(cols, axis=-1)
        else:
            J_num = _numeric(fun, values, key)
            dim = J_num.shape[1]
        rel = _rel(A[:, col : col + dim], J_num)
        assert rel < 1e-6, f"key {gtsam.Symbol(key).string()}: relative error {rel:.2e}"
        col += dim


def test_projection_factory_matches_static_factor() -> None:
    values, z, _, T_sI, _ = _scene(5, 3, static=True)
    make = ProjectionFactory(2e-3, T_sI, huber_k=2.0)
    for i in range(3):
        a = make(z[i], X, _lm(i))
        b = static_projection_factor(z[i], 2e-3, X, _lm(i), T_sI, huber_k=2.0)
        assert a.error(values) == pytest.approx(b.error(values), rel=1e-12)


def test_gimbal_camera_pose_factor_with_a_known_exposure_motion() -> None:
    """The tie of an image exposed at a known time from its keyframe (constant body motion M and joint
    shift): Jacobians against central differences, zero at T_Wd = T_WI M T_Id(theta + shift)."""
    values, _, theta, T_sI, cal = _scene(5, 1)
    rng = np.random.default_rng(5)
    M = gtsam.Pose3.Expmap(rng.normal(size=6) * 0.02).matrix()
    shift = rng.normal(size=2) * 0.01
    C = gtsam.symbol("c", 0)
    T_Wd = values.atPose3(X).matrix() @ M @ np.linalg.inv(cal.T_ds(theta + shift) @ T_sI)
    values.insert(C, gtsam.Pose3(T_Wd))
    cache = ChainCache(cal.kin, 2)
    f = gimbal_camera_pose_factor(X, TH, C, cache, T_sI, 1e-3, 1e-3, body_motion=M, theta_shift=shift)
    assert np.abs(f.unwhitenedError(values)).max() < 1e-10
    values.update(C, gtsam.Pose3(T_Wd).retract(rng.normal(size=6) * 0.01))
    _check_factor(f, values)
