"""VIO reprojection factors (paper eq. 14-15): analytic Jacobians against central finite differences."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from dcc_fg.sim.trajectory import default_static_mount, flight_calibration
from factors.calibration import RobustLoss
from factors.vio import (
    gimbal_batch_factor,
    gimbal_reprojection_factor,
    static_batch_factor,
    static_projection_factor,
)

X, TH = gtsam.symbol("x", 0), gtsam.symbol("t", 0)


def _lm(i: int) -> int:
    return gtsam.symbol("l", i)


def _scene(seed: int, n: int) -> tuple[gtsam.Values, np.ndarray, np.ndarray, np.ndarray, object]:
    """Random body pose, joint angles and landmarks 3-15 m in front of the gimbal camera."""
    rng = np.random.default_rng(seed)
    cal = flight_calibration()
    T_sI = default_static_mount()
    theta = np.array([np.deg2rad(90.0), 0.0]) + rng.normal(size=2) * 0.3
    T_WI = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), rng.normal(size=3) * 5.0)
    T_dW = cal.T_ds(theta) @ T_sI @ T_WI.inverse().matrix()
    p_d = np.column_stack([rng.uniform(-0.5, 0.5, (n, 2)), np.ones(n)]) * rng.uniform(3.0, 15.0, (n, 1))
    T_Wd = np.linalg.inv(T_dW)
    p_W = p_d @ T_Wd[:3, :3].T + T_Wd[:3, 3]
    values = gtsam.Values()
    values.insert(X, T_WI)
    values.insert(TH, theta)
    for i in range(n):
        values.insert(_lm(i), p_W[i])
    z = p_d[:, :2] / p_d[:, 2:3] + rng.normal(size=(n, 2)) * 2e-3
    return values, z, theta, T_sI, cal


def _retract(values: gtsam.Values, key: int, delta: np.ndarray) -> gtsam.Values:
    out = gtsam.Values(values)
    sym = chr(gtsam.Symbol(key).chr())
    if sym == "x":
        out.update(key, values.atPose3(key).retract(delta))
    elif sym == "t":
        out.update(key, values.atVector(key) + delta)
    else:
        out.update(key, values.atPoint3(key) + delta)
    return out


def _check_jacobians(factor: gtsam.NonlinearFactor, values: gtsam.Values, h: float = 1e-6) -> None:
    A, _ = factor.linearize(values).jacobian()
    col = 0
    for key in factor.keys():
        dim = {"x": 6, "t": 2, "l": 3}[chr(gtsam.Symbol(key).chr())]
        J_num = np.zeros((A.shape[0], dim))
        for d in range(dim):
            e = np.zeros(dim)
            e[d] = h
            ep = factor.whitenedError(_retract(values, key, e))
            em = factor.whitenedError(_retract(values, key, -e))
            J_num[:, d] = (ep - em) / (2 * h)
        J = A[:, col : col + dim]
        rel = np.linalg.norm(J - J_num) / max(np.linalg.norm(J_num), 1e-12)
        assert rel < 1e-6, f"key {gtsam.Symbol(key).string()}: relative error {rel:.2e}"
        col += dim


@pytest.mark.parametrize("robust", [None, RobustLoss("huber", 1.5)])
def test_gimbal_factor_jacobians(robust: RobustLoss | None) -> None:
    values, z, _, T_sI, cal = _scene(0, 6)
    sigma = 1e-3
    f = gimbal_batch_factor(z, sigma, X, [_lm(i) for i in range(6)], TH, cal.kin, 2, T_sI, robust=robust)
    _check_jacobians(f, values)
    single = gimbal_reprojection_factor(z[2], sigma, X, _lm(2), TH, cal.kin, 2, T_sI)
    _check_jacobians(single, values)


def test_gimbal_factor_zero_at_truth_and_locked_mode() -> None:
    values, _, theta, T_sI, cal = _scene(1, 5)
    T_dW = cal.T_ds(theta) @ T_sI @ values.atPose3(X).inverse().matrix()
    p = np.array([values.atPoint3(_lm(i)) for i in range(5)]) @ T_dW[:3, :3].T + T_dW[:3, 3]
    z_exact = p[:, :2] / p[:, 2:3]
    keys = [_lm(i) for i in range(5)]
    f = gimbal_batch_factor(z_exact, 1e-3, X, keys, TH, cal.kin, 2, T_sI)
    assert f.error(values) < 1e-18
    locked = gimbal_batch_factor(z_exact, 1e-3, X, keys, None, cal.kin, 2, T_sI, theta_const=theta + 0.01)
    assert locked.error(values) > 1.0  # 0.01 rad off is many sigmas
    assert len(locked.keys()) == 6
    _check_jacobians(locked, values)


def test_static_factor_matches_gtsam_projection_factor() -> None:
    values, _, _, T_sI, _ = _scene(2, 4)
    T_sW = T_sI @ values.atPose3(X).inverse().matrix()
    values_front = gtsam.Values()
    values_front.insert(X, values.atPose3(X))
    # landmarks in front of the static camera
    T_Ws = np.linalg.inv(T_sW)
    q_s = np.column_stack([[0.1, -0.2, 0.3, 0.0], [0.2, 0.1, -0.1, 0.05], np.ones(4)]) * [[4.0], [6.0], [9.0], [12.0]]
    q_W = q_s @ T_Ws[:3, :3].T + T_Ws[:3, 3]
    for i in range(4):
        values_front.insert(_lm(i), q_W[i])
    z = q_s[:, :2] / q_s[:, 2:3] + 1e-3
    sigma = 2e-3
    batch = static_batch_factor(z, sigma, X, [_lm(i) for i in range(4)], T_sI)
    _check_jacobians(batch, values_front)
    A_b, b_b = batch.linearize(values_front).jacobian()
    for i in range(4):
        f = static_projection_factor(z[i], sigma, X, _lm(i), T_sI)
        A, b = f.linearize(values_front).jacobian()
        np.testing.assert_allclose(A[:, :6], A_b[2 * i : 2 * i + 2, :6], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(A[:, 6:], A_b[2 * i : 2 * i + 2, 6 + 3 * i : 9 + 3 * i], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(b, b_b[2 * i : 2 * i + 2], rtol=1e-9, atol=1e-12)
