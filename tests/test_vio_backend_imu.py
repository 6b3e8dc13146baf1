"""IMU propagation pieces of the smoother: preintegration against the closed form, standstill start."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from dcc_fg.data.vio import ImuConfig, ImuSamples
from dcc_fg.vio.backend.imu import preintegrate, preintegration_params, standstill_state
from dcc_fg.vio.backend.options import NS

G = 9.81


def _constant_samples(acc_W: np.ndarray, R_WI: np.ndarray, t_end: float, rate: float = 200.0) -> ImuSamples:
    """Samples of a body with fixed attitude ``R_WI`` accelerating at ``acc_W`` (m/s^2) in W."""
    t = np.arange(0, int(t_end * rate) + 1) * int(NS / rate)
    f_I = R_WI.T @ (acc_W + np.array([0.0, 0.0, G]))  # specific force in I
    return ImuSamples(t.astype(np.int64), np.tile(f_I, (t.size, 1)), np.zeros((t.size, 3)))


def test_constant_acceleration_matches_the_closed_form() -> None:
    R_WI = gtsam.Rot3.RzRyRx(0.1, -0.2, 0.7).matrix()
    a = np.array([0.5, -1.0, 0.25])
    imu = _constant_samples(a, R_WI, 2.0)
    params = preintegration_params(ImuConfig(gravity=G))
    p0, v0 = np.array([1.0, 2.0, 3.0]), np.array([0.3, 0.0, -0.1])
    t0, t1 = 12_345_678, 1_700_000_000  # not on sample times: partial intervals at both ends
    pim = preintegrate(params, gtsam.imuBias.ConstantBias(), imu, t0, t1)
    dt = (t1 - t0) / NS
    assert pim.deltaTij() == pytest.approx(dt, abs=1e-12)
    pred = pim.predict(gtsam.NavState(gtsam.Pose3(gtsam.Rot3(R_WI), p0), v0), gtsam.imuBias.ConstantBias())
    np.testing.assert_allclose(pred.position(), p0 + v0 * dt + 0.5 * a * dt**2, atol=1e-9)
    np.testing.assert_allclose(pred.velocity(), v0 + a * dt, atol=1e-9)
    np.testing.assert_allclose(pred.attitude().matrix(), R_WI, atol=1e-12)


def test_integration_holds_the_last_sample_after_the_data() -> None:
    imu = _constant_samples(np.array([1.0, 0.0, 0.0]), np.eye(3), 1.0)
    params = preintegration_params(ImuConfig(gravity=G))
    pim = preintegrate(params, gtsam.imuBias.ConstantBias(), imu, int(0.5 * NS), int(1.5 * NS))
    assert pim.deltaTij() == pytest.approx(1.0)
    np.testing.assert_allclose(pim.deltaVij(), [1.0, 0.0, G], atol=1e-9)  # in I; gravity not yet removed


def test_standstill_state_aligns_gravity_and_takes_the_gyro_bias() -> None:
    R_WI = gtsam.Rot3.RzRyRx(0.05, -0.08, 0.0).matrix()
    imu = _constant_samples(np.zeros(3), R_WI, 1.0)
    gyro_bias = np.array([1e-3, -2e-3, 5e-4])
    imu = ImuSamples(imu.t_ns, imu.acc, imu.gyro + gyro_bias)
    s = standstill_state(imu, 0, 0.5, G, 2)
    R_est = s.T_WI[:3, :3]
    np.testing.assert_allclose(R_est.T @ [0, 0, 1], R_WI.T @ [0, 0, 1], atol=1e-12)  # same "up" in I
    np.testing.assert_allclose(s.gyro_bias, gyro_bias, atol=1e-15)
    assert s.theta.shape == (2,) and np.all(s.v_W == 0) and s.t_ns == 0
    moving = ImuSamples(imu.t_ns, imu.acc * 1.2, imu.gyro)
    with pytest.raises(ValueError, match="not at rest"):
        standstill_state(moving, 0, 0.5, G, 2)
    with pytest.raises(ValueError, match="needs IMU samples"):
        standstill_state(imu, 10 * NS, 0.5, G, 2)
