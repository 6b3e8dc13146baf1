"""Flight simulator ground truth: analytic derivatives, exact IMU, joint motion limits, tracks."""

from __future__ import annotations

import gtsam
import numpy as np

from dcc_fg.sim.trajectory import (
    DEG,
    BodyTrajectory,
    FlightConfig,
    JointMotion,
    World,
    default_static_mount,
    flight_calibration,
    simulate_flight,
    simulate_tracks,
)


def test_derivatives_match_finite_differences() -> None:
    traj = BodyTrajectory(FlightConfig())
    t = np.array([0.5, 1.7, 3.2, 10.0, 33.3, 61.0, 89.0])
    h = 1e-5
    s0, sp, sm = traj.evaluate(t), traj.evaluate(t + h), traj.evaluate(t - h)
    np.testing.assert_allclose((sp.p_W - sm.p_W) / (2 * h), s0.v_W, atol=1e-7)
    np.testing.assert_allclose((sp.v_W - sm.v_W) / (2 * h), s0.a_W, atol=1e-6)
    for k in range(t.size):
        dR = sm.R_WI[k].T @ sp.R_WI[k]
        w = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) / 2 / (2 * h)
        np.testing.assert_allclose(w, s0.omega_I[k], atol=1e-7)


def test_pattern_length_and_standstill() -> None:
    full = BodyTrajectory(FlightConfig())
    assert 170.0 < full.length() < 190.0  # the paper's ~180 m
    st = full.evaluate(np.array([0.0, 0.5]))
    np.testing.assert_allclose(st.v_W, 0.0, atol=1e-12)
    np.testing.assert_allclose(st.p_W[0], [0.0, 0.0, FlightConfig().altitude], atol=1e-12)


def test_noise_free_imu_preintegrates_to_truth() -> None:
    truth = simulate_flight(FlightConfig.short(20.0), noise=False)
    params = gtsam.PreintegrationParams.MakeSharedU(9.81)
    params.setAccelerometerCovariance(np.eye(3) * 1e-8)
    params.setGyroscopeCovariance(np.eye(3) * 1e-8)
    params.setIntegrationCovariance(np.eye(3) * 1e-8)
    bias = gtsam.imuBias.ConstantBias(truth.acc_bias[0], truth.gyro_bias[0])
    i0, i1 = 1000, 1200  # 1 s in the middle of the flight
    pim = gtsam.PreintegratedImuMeasurements(params, bias)
    for i in range(i0, i1):
        # midpoint measurement: the sample-and-hold integrator is then second-order accurate
        acc = 0.5 * (truth.imu.acc[i] + truth.imu.acc[i + 1])
        gyro = 0.5 * (truth.imu.gyro[i] + truth.imu.gyro[i + 1])
        pim.integrateMeasurement(acc, gyro, 0.005)
    state = gtsam.NavState(gtsam.Pose3(truth.T_WI[i0]), truth.v_W[i0])
    pred = pim.predict(state, bias)
    assert np.linalg.norm(pred.pose().translation() - truth.T_WI[i1][:3, 3]) < 2e-3
    assert np.linalg.norm(pred.velocity() - truth.v_W[i1]) < 5e-3
    dR = pred.pose().rotation().matrix().T @ truth.T_WI[i1][:3, :3]
    assert np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(dR))) < 1e-4


def test_imu_noise_statistics() -> None:
    truth_clean = simulate_flight(FlightConfig.short(20.0), noise=False)
    truth = simulate_flight(FlightConfig.short(20.0), seed=3)
    n_a = truth.imu.acc - truth_clean.imu.acc - (truth.acc_bias - truth_clean.acc_bias)
    expected = 2.0e-3 / np.sqrt(0.005)
    assert abs(n_a.std() / expected - 1.0) < 0.05


def test_joint_motion_rate_and_amplitude() -> None:
    jm = JointMotion()
    t = np.arange(0.0, 60.0, 0.001)
    th, thd = jm.evaluate(t, 60.0)
    assert np.abs(thd).max() <= 60.0 * DEG + 1e-9
    assert np.abs(thd).max() > 50.0 * DEG  # slews reach close to the limit
    assert np.ptp(th[:, 1]) > 60.0 * DEG  # +-30 deg slews
    np.testing.assert_allclose(np.gradient(th[:, 0], t)[1:-1], thd[1:-1, 0], atol=1e-3)
    assert len(jm.slew_windows(60.0)) >= 10


def test_tracks_share_ids_and_project_truth() -> None:
    truth = simulate_flight(FlightConfig.short(6.0), seed=1)
    world = World.around(truth.config)
    pts = world.sample_points(0.6, np.random.default_rng(0))
    cal = flight_calibration()
    T_sI = default_static_mount()
    frames = simulate_tracks(truth, pts, cal, T_sI, pixel_sigma=0.0)
    assert len(frames) == truth.frame_t_ns.size
    assert np.mean([np.intersect1d(f.static_ids, f.dynamic_ids).size for f in frames]) > 20
    # noise-free observations are exact projections of some landmark
    f = frames[40]
    i = truth.index_of(f.timestamp_ns)[0]
    T_sW = T_sI @ np.linalg.inv(truth.T_WI[i])
    p_s = pts @ T_sW[:3, :3].T + T_sW[:3, 3]
    xy_all = p_s[:, :2] / p_s[:, 2:3]
    for xy in f.static_xy[:10]:
        assert np.min(np.linalg.norm(xy_all - xy, axis=1)) < 1e-12
    # every surface faces the inside of the room (u x v is the visible side's normal)
    centre = np.array([np.mean(world.x_range), np.mean(world.y_range), 1.0])
    for _, o, u, v, _, _ in world.planes():
        assert np.dot(np.cross(u, v), centre - o) > 0.0
