"""Exposure-time camera poses (factors/exposure.py): analytic Jacobians against central differences,
zero error at the true exposure pose, and the first-order motion model against exact kinematics."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from dcc_fg.sim.trajectory import default_static_mount, flight_calibration
from factors.chain import inv_se3
from factors.exposure import CameraMount, ExposureKeys, exposure_pose, exposure_pose_factor, exposure_rate
from factors.vio import ChainCache

X, V, C, O, TH = (gtsam.symbol(c, 0) for c in "xvcot")


def _retract(values: gtsam.Values, key: int, d: np.ndarray) -> gtsam.Values:
    out = gtsam.Values(values)
    if chr(gtsam.Symbol(key).chr()) in "xc":
        out.update(key, values.atPose3(key).retract(d))
    else:
        out.update(key, values.atVector(key) + d)
    return out


def _dim(values: gtsam.Values, key: int) -> int:
    return 6 if chr(gtsam.Symbol(key).chr()) in "xc" else values.atVector(key).shape[0]


def _check(factor: gtsam.NonlinearFactor, values: gtsam.Values, h: float = 1e-6) -> None:
    A, _ = factor.linearize(values).jacobian()
    col = 0
    for key in factor.keys():
        dim = _dim(values, key)
        cols = []
        for i in range(dim):
            e = np.zeros(dim)
            e[i] = h
            plus = factor.whitenedError(_retract(values, key, e))
            minus = factor.whitenedError(_retract(values, key, -e))
            cols.append((plus - minus) / (2 * h))
        J_num = np.stack(cols, axis=-1)
        J = A[:, col : col + dim]
        rel = np.linalg.norm(J - J_num) / max(np.linalg.norm(J_num), 1e-9)
        assert rel < 1e-5, f"key {gtsam.Symbol(key).string()}: relative error {rel:.2e}"
        col += dim


def _values(rng: np.random.Generator, L: int) -> gtsam.Values:
    """Random keyframe state (speeds to 10 m/s), offsets (+-30 ms), joints and a camera pose off the model."""
    values = gtsam.Values()
    values.insert(X, gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), rng.normal(size=3) * 5.0))
    values.insert(V, rng.normal(size=3) * 5.0)
    values.insert(C, gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), rng.normal(size=3) * 5.0))
    values.insert(O, rng.uniform(-0.03, 0.03, 2))
    values.insert(TH, rng.normal(size=L) * 0.5)
    return values


@pytest.mark.parametrize("seed", range(6))
def test_static_exposure_factor_jacobians(seed: int) -> None:
    rng = np.random.default_rng(seed)
    values = _values(rng, 2)
    mount = CameraMount(T_Ic=inv_se3(default_static_mount()))
    keys = ExposureKeys(X, V, C, O, offset_index=0)
    f = exposure_pose_factor(keys, mount, rng.uniform(-0.04, 0.04), rng.normal(size=3) * 2.0)
    _check(f, values)
    # fixed offset: no offset key
    f = exposure_pose_factor(ExposureKeys(X, V, C), mount, rng.uniform(-0.04, 0.04), rng.normal(size=3), 0.012)
    assert len(f.keys()) == 3
    _check(f, values)


@pytest.mark.parametrize("seed", range(6))
def test_gimbal_exposure_factor_jacobians(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    cal = flight_calibration()
    values = _values(rng, cal.n_joints)
    mount = CameraMount(cache=ChainCache(cal.kin, cal.n_joints), T_sI=default_static_mount())
    keys = ExposureKeys(X, V, C, O, offset_index=1, theta=TH)
    rate = rng.normal(size=cal.n_joints)  # rad/s
    _check(exposure_pose_factor(keys, mount, rng.uniform(-0.04, 0.04), rng.normal(size=3), 0.0, rate), values)
    _check(exposure_pose_factor(keys, mount, rng.uniform(-0.04, 0.04), rng.normal(size=3)), values)
    jitter = rng.normal(size=6) * 1e-3  # the camera's motion in one sigma of stamp jitter: a full covariance
    _check(exposure_pose_factor(keys, mount, 0.01, rng.normal(size=3), 0.0, rate, 1e-4, 1e-4, jitter), values)
    fixed = ExposureKeys(X, V, C, theta=TH)
    _check(exposure_pose_factor(fixed, mount, rng.uniform(-0.04, 0.04), rng.normal(size=3), 0.015, rate), values)


def test_zero_error_at_the_modelled_exposure_pose() -> None:
    rng = np.random.default_rng(7)
    cal = flight_calibration()
    T_sI = default_static_mount()
    values = _values(rng, cal.n_joints)
    gap, rate, omega = 0.021, rng.normal(size=cal.n_joints), rng.normal(size=3)
    delta = gap + values.atVector(O)[1]
    th_c = values.atVector(TH) + delta * rate
    T_Id = inv_se3(cal.T_ds(th_c) @ T_sI)
    T_Wd = exposure_pose(values.atPose3(X).matrix(), values.atVector(V), omega, delta, T_Id)
    values.update(C, gtsam.Pose3(T_Wd))
    mount = CameraMount(cache=ChainCache(cal.kin, cal.n_joints), T_sI=T_sI)
    f = exposure_pose_factor(ExposureKeys(X, V, C, O, 1, TH), mount, gap, omega, 0.0, rate)
    assert np.abs(f.unwhitenedError(values)).max() < 1e-12


def test_constant_twist_model_matches_exact_constant_twist_motion() -> None:
    """A body moving with constant body-frame twist is exactly T(t) = T0 Exp(t xi): the model is exact there."""
    rng = np.random.default_rng(3)
    T0 = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), rng.normal(size=3))
    omega, v_I = rng.normal(size=3), rng.normal(size=3)
    # the velocity in W of T(t) = T0 Exp(t xi) at t = 0 is R0 J v_I with J = I at t = 0
    v_W = T0.rotation().matrix() @ v_I
    for delta in (-0.04, 0.013, 0.05):
        exact = T0.compose(gtsam.Pose3.Expmap(delta * np.r_[omega, v_I])).matrix()
        model = exposure_pose(T0.matrix(), v_W, omega, delta, np.eye(4))
        np.testing.assert_allclose(model, exact, atol=1e-12)


def test_exposure_rate_is_the_derivative_of_the_exposure_pose() -> None:
    """``T_Wc(delta + dt) = T_Wc(delta) Exp(u dt)`` for the static camera (constant mount)."""
    rng = np.random.default_rng(11)
    T_WI = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), rng.normal(size=3)).matrix()
    v, omega, T_Ic = rng.normal(size=3), rng.normal(size=3), inv_se3(default_static_mount())
    u = exposure_rate(T_WI, v, omega, T_Ic, np.zeros((6, 0)), np.zeros(0))
    h = 1e-6
    a = gtsam.Pose3(exposure_pose(T_WI, v, omega, 0.01 - h, T_Ic))
    b = gtsam.Pose3(exposure_pose(T_WI, v, omega, 0.01 + h, T_Ic))
    np.testing.assert_allclose(gtsam.Pose3.Logmap(a.between(b)) / (2 * h), u, atol=1e-6)
