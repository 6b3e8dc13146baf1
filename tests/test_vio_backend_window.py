"""Fixed-lag window pieces: anchor priors, the restart after a failed update, zero-velocity factors,
and the camera rig's poses and factors."""

from __future__ import annotations

import gtsam
import numpy as np

from dcc_fg.sim.trajectory import default_static_mount, flight_calibration
from dcc_fg.vio.backend.cameras import GIMBAL, STATIC, CameraRig
from dcc_fg.vio.backend.keys import bias_key, camera_key, landmark_key, pose_key, theta_key, velocity_key
from dcc_fg.vio.backend.options import NS, VioOptions
from dcc_fg.vio.backend.window import AnchorSigmas, FixedLagWindow, anchor_factors, key_timestamps, window_start_ns
from dcc_fg.vio.backend.zupt import static_tracks_at_rest, zero_velocity_factors
from factors.chain import inv_se3

POSE = gtsam.Pose3(gtsam.Rot3.Rz(0.4), np.array([1.0, -2.0, 0.5]))
VEL = np.array([0.5, 0.0, -0.1])
BIAS = gtsam.imuBias.ConstantBias(np.array([0.01, 0.0, 0.0]), np.array([0.0, 1e-3, 0.0]))


def test_window_start_and_key_times() -> None:
    assert window_start_ns(10 * NS, None, 1.5) == 10 * NS - 1_500_000_000
    assert window_start_ns(10 * NS, 9_900_000_000, 1.5) == 10 * NS - 1_500_000_000 + 100_000_000
    ts = key_timestamps({pose_key(0): 2 * NS})
    assert dict(ts.items()) == {pose_key(0): 2.0}


def test_anchor_factors() -> None:
    o = VioOptions()
    graph, values, stamps = anchor_factors(3, 7, POSE, VEL, BIAS, np.array([0.1, 0.2]), AnchorSigmas.first_keyframe(o))
    assert graph.size() == 4 and values.size() == 4 and set(stamps.values()) == {7}
    assert list(stamps) == [pose_key(3), velocity_key(3), bias_key(3), theta_key(3)]
    assert graph.error(values) == 0.0
    graph, values, stamps = anchor_factors(3, 7, POSE, VEL, BIAS, None, AnchorSigmas.recovery(o))
    assert graph.size() == 3 and not values.exists(theta_key(3))
    assert AnchorSigmas.recovery(o).velocity == 10 * o.prior_velocity_sigma


def test_failed_update_then_restart_keeps_the_last_state() -> None:
    o = VioOptions(mode="mono")
    window = FixedLagWindow(o)
    graph, values, stamps = anchor_factors(0, 0, POSE, VEL, BIAS, None, AnchorSigmas.first_keyframe(o))
    assert window.update(graph, values, stamps) is None
    # two landmarks tied only to each other: the linear system is indeterminant
    bad_graph = gtsam.NonlinearFactorGraph()
    noise = gtsam.noiseModel.Isotropic.Sigma(3, 1.0)
    bad_graph.add(gtsam.BetweenFactorPoint3(landmark_key(0), landmark_key(1), np.ones(3), noise))
    bad_values = gtsam.Values()
    bad_values.insert(landmark_key(0), np.ones(3))
    bad_values.insert(landmark_key(1), np.ones(3) * 2)
    error = window.update(bad_graph, bad_values, {landmark_key(0): NS // 10, landmark_key(1): NS // 10})
    assert error is not None and "\n" not in error
    last = gtsam.Pose3(gtsam.Rot3.Rz(0.5), np.array([2.0, -2.0, 0.5]))
    graph, values, stamps = anchor_factors(5, NS, last, VEL, BIAS, None, AnchorSigmas.recovery(o))
    window.restart(graph, values, stamps)
    est = window.estimate()
    assert est.atPose3(pose_key(5)).equals(last, 1e-9)
    np.testing.assert_allclose(est.atVector(velocity_key(5)), VEL, atol=1e-9)
    assert not est.exists(pose_key(0)) and not est.exists(landmark_key(0))


def test_zero_velocity() -> None:
    o = VioOptions()
    prev = {i: np.array([0.01 * i, 0.0]) for i in range(10)}
    still = {i: xy + 1e-4 for i, xy in prev.items()}
    moved = {i: xy + 1e-2 for i, xy in prev.items()}
    assert static_tracks_at_rest(prev, still, o)
    assert not static_tracks_at_rest(prev, moved, o)
    assert not static_tracks_at_rest(dict(list(prev.items())[:5]), still, o)  # too few common tracks
    v, between = zero_velocity_factors(2, 3, o)
    assert v.keys() == [velocity_key(3)] and between.keys() == [pose_key(2), pose_key(3)]


def test_camera_rig() -> None:
    cal, T_sI = flight_calibration(), default_static_mount()
    theta = np.array([0.2, -0.1])
    T_WI = POSE.matrix()
    for mode, gimbal_factor in (("dcc", "camera_pose"), ("dcc", "eq14"), ("scc", "camera_pose")):
        o = VioOptions(mode=mode, gimbal_factor=gimbal_factor, theta_fixed=tuple(theta) if mode == "scc" else None)
        rig = CameraRig(cal, T_sI, o)
        np.testing.assert_allclose(rig.T_Wc(T_WI, STATIC), T_WI @ inv_se3(T_sI))
        T_Wd = rig.T_Wc(T_WI, GIMBAL, theta)
        np.testing.assert_allclose(T_Wd, T_WI @ inv_se3(cal.T_ds(theta) @ T_sI))
        values = gtsam.Values()
        values.insert(pose_key(1), POSE)
        values.insert(theta_key(1), theta)
        graph = gtsam.NonlinearFactorGraph()
        stamps: dict[int, int] = {}
        if mode == "dcc":  # (the smoother adds the gimbal-camera pose in dcc only)
            rig.add_gimbal_camera_pose(1, 9, POSE, theta, graph, values, stamps)
        assert (stamps == {camera_key(1): 9}) == (mode == "dcc" and gimbal_factor == "camera_pose")
        for cam, T_Wc in ((STATIC, rig.T_Wc(T_WI, STATIC)), (GIMBAL, T_Wd)):
            p_c = np.array([0.5, 0.2, 6.0])  # a landmark in front of the camera
            values.insert(landmark_key(cam), T_Wc[:3, :3] @ p_c + T_Wc[:3, 3])
            graph.add(rig.observation_factor(1, cam, cam, p_c[:2] / p_c[2]))
        assert graph.error(values) < 1e-12  # exact observations at the true state
