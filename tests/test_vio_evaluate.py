"""VIO evaluation (TUM and bag ground truth), output files, CLI, and bad input to the smoother."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import Writer as Rosbag2Writer
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from dcc_fg.cli import main
from dcc_fg.commands.evaluate import evaluation
from dcc_fg.data.vio import ImuConfig, ImuSamples, TrackFrame
from dcc_fg.io.tum import read_tum, write_tum
from dcc_fg.sim.trajectory import FlightConfig, default_static_mount, flight_calibration, simulate_flight
from dcc_fg.vio.backend import VioOptions, VioResult, run_vio, validate_imu, write_vio_outputs
from dcc_fg.vio.evaluate import (
    GroundTruth,
    evaluate_output,
    evaluate_trajectory,
    format_evaluation,
    joint_rmse,
    load_ground_truth,
)


@pytest.fixture(scope="module")
def truth():
    return simulate_flight(FlightConfig.short(12.0), seed=5)


def _perturbed(truth, sigma: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    idx = np.arange(0, truth.t_ns.size, 20)
    T = truth.T_WI[idx].copy()
    T[:, :3, 3] += rng.normal(size=(idx.size, 3)) * sigma
    return truth.t_ns[idx], T


def test_tum_round_trip(tmp_path: Path, truth) -> None:
    t, T = _perturbed(truth, 0.0)
    write_tum(tmp_path / "a.tum", t, T)
    t2, T2 = read_tum(tmp_path / "a.tum")
    np.testing.assert_array_equal(t, t2)
    np.testing.assert_allclose(T, T2, atol=1e-8)
    (tmp_path / "bad.tum").write_text("0.0 1 2 3\n")
    with pytest.raises(ValueError, match="bad.tum:1"):
        read_tum(tmp_path / "bad.tum")


def test_metrics_follow_the_noise(truth) -> None:
    gt = GroundTruth(truth.t_ns, truth.T_WI)
    t, T = _perturbed(truth, 0.02)
    # a rigid offset of the whole estimate is removed by the SE(3) alignment
    offset = np.eye(4)
    offset[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    offset[:3, 3] = [5.0, -2.0, 1.0]
    ev = evaluate_trajectory(t, offset @ T, gt, "se3")
    # 3D RMSE of N(0, 0.02^2 I) noise is 0.02 sqrt(3)
    assert abs(ev["ape_rmse_m"] / (0.02 * np.sqrt(3)) - 1.0) < 0.15
    assert ev["normalized_translation_rmse_percent"] == pytest.approx(100 * ev["ape_rmse_m"] / ev["distance_m"])
    assert ev["rotation_rmse_rad"] < 5e-3  # only the alignment error from the noisy positions
    # Sim(3) recovers a scale error of a monocular run
    T_scaled = T.copy()
    T_scaled[:, :3, 3] *= 0.5
    ev3 = evaluate_trajectory(t, T_scaled, gt, "sim3")
    assert abs(ev3["scale"] - 2.0) < 0.02
    with pytest.raises(ValueError, match="overlap"):
        evaluate_trajectory(t + 10**12, T, gt, "se3")


def test_joint_rmse_interpolates(truth) -> None:
    gt = GroundTruth(truth.t_ns, truth.T_WI, truth.t_ns[::7], truth.theta[::7])
    est_t = truth.t_ns[5::40]
    est = truth.theta[5::40] + np.array([0.01, -0.02])
    np.testing.assert_allclose(joint_rmse(est_t, est, gt), [0.01, 0.02], atol=2e-4)


def _write_gt_bag(path: Path, truth) -> None:
    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    with Rosbag2Writer(path, version=Rosbag2Writer.VERSION_LATEST) as w:
        cp = w.add_connection("/ground_truth/pose", "geometry_msgs/msg/PoseStamped", typestore=ts)
        cj = w.add_connection("/ground_truth/joints", "sensor_msgs/msg/JointState", typestore=ts)
        for i in range(0, truth.t_ns.size, 10):
            stamp = int(truth.t_ns[i]) + 1_000_000_000
            hdr = T["std_msgs/msg/Header"](
                stamp=T["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id="world"
            )
            q = Rotation.from_matrix(truth.T_WI[i, :3, :3]).as_quat()
            p = truth.T_WI[i, :3, 3]
            pose = T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
                orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
            )
            msg = T["geometry_msgs/msg/PoseStamped"](header=hdr, pose=pose)
            w.write(cp, stamp, ts.serialize_cdr(msg, "geometry_msgs/msg/PoseStamped"))
            js = T["sensor_msgs/msg/JointState"](
                header=hdr,
                name=["joint_1", "joint_2"],
                position=truth.theta[i].astype(np.float64),
                velocity=np.zeros(0),
                effort=np.zeros(0),
            )
            w.write(cj, stamp, ts.serialize_cdr(js, "sensor_msgs/msg/JointState"))


def test_bag_ground_truth_and_cli(tmp_path: Path, truth, capsys) -> None:
    bag = tmp_path / "gt_bag"
    _write_gt_bag(bag, truth)
    gt = load_ground_truth(bag)
    assert gt.joints is not None and gt.joints.shape[1] == 2
    np.testing.assert_allclose(gt.T_WI[3], truth.T_WI[30], atol=1e-9)
    # a fake run: the truth shifted by 1 s (the bag's stamps) with known joint errors
    idx = np.arange(0, truth.t_ns.size, 20)
    res = VioResult(
        truth.t_ns[idx] + 1_000_000_000,
        truth.T_WI[idx],
        truth.v_W[idx],
        truth.acc_bias[idx],
        truth.gyro_bias[idx],
        truth.theta[idx] + np.array([0.005, 0.0]),
        "dcc",
        {"real_time_factor": 0.5},
    )
    out = tmp_path / "out"
    write_vio_outputs(out, res)
    assert main(["evaluate", str(out), "--ground-truth", str(bag)]) == 0
    text = capsys.readouterr().out
    assert "normalized translation RMSE" in text and "joint 2 angle RMSE" in text
    ev = evaluate_output(out, bag)
    assert ev["ape_rmse_m"] < 1e-6
    assert ev["joint_rmse_rad"][0] == pytest.approx(0.005, abs=2e-4)
    assert main(["evaluate", str(tmp_path / "missing"), "--ground-truth", str(bag)]) == 2


def test_bad_imu_and_options_raise(truth) -> None:
    imu = truth.imu
    back = imu.t_ns.copy()
    back[50] = back[48]
    with pytest.raises(ValueError, match="not strictly increasing at sample"):
        validate_imu(ImuSamples(back, imu.acc, imu.gyro))
    acc = imu.acc.copy()
    acc[77, 1] = np.nan
    with pytest.raises(ValueError, match="acc is not finite at sample 77"):
        validate_imu(ImuSamples(imu.t_ns, acc, imu.gyro))
    with pytest.raises(ValueError, match="mode"):
        VioOptions(mode="stereo")
    cfg = ImuConfig(T_sI=default_static_mount())
    frames = [TrackFrame(int(t), np.zeros(0, np.int64), np.zeros((0, 2))) for t in truth.frame_t_ns[:5]]
    with pytest.raises(ValueError, match="theta_fixed"):
        run_vio(frames, imu, cfg, flight_calibration(), VioOptions(mode="scc"))
    with pytest.raises(ValueError, match="needs the gimbal calibration"):
        run_vio(frames, imu, cfg, None, VioOptions(mode="dcc"))
    with pytest.raises(ValueError, match="theta_initial"):
        run_vio(frames, imu, cfg, flight_calibration(), VioOptions(mode="dcc"))
    res = run_vio(frames, imu, cfg, flight_calibration(), VioOptions(mode="dcc", theta_initial=(1.5, 0.0)))
    np.testing.assert_allclose(res.theta[0], [1.5, 0.0], atol=1e-6)  # no gimbal tracks: the prior holds
    with pytest.raises(ValueError, match="not after"):
        run_vio(frames[::-1], imu, cfg, None, VioOptions(mode="mono"))


def test_standstill_initialization_and_image_gap(truth, caplog) -> None:
    """Mono run from standstill (the flight hovers 1 s) over IMU-only frames with a 3 s gap in the
    images: the gap is logged and bridged by the IMU (a failed update is a logged restart), every
    frame still gets a pose and the pose after the gap follows the truth."""
    cfg = ImuConfig(T_sI=default_static_mount())
    times = np.r_[truth.frame_t_ns[:10], truth.frame_t_ns[70:80]]
    frames = [TrackFrame(int(t), np.zeros(0, np.int64), np.zeros((0, 2))) for t in times]
    with caplog.at_level("WARNING"):
        res = run_vio(frames, truth.imu, cfg, None, VioOptions(mode="mono", keyframe_every=1))
    assert any("gap of 3.05 s" in r.getMessage() for r in caplog.records)
    if res.stats["failed_updates"]:
        assert any("restarting the window" in r.getMessage() for r in caplog.records)
    assert res.timestamps_ns.size == times.size and np.all(np.isfinite(res.T_WI))
    idx = truth.index_of(res.timestamps_ns)
    # standstill init puts the body at the origin with yaw 0 (the truth's start heading): compare displacements
    disp_est = res.T_WI[:, :3, 3] - res.T_WI[0, :3, 3]
    disp_true = truth.T_WI[idx, :3, 3] - truth.T_WI[idx[0], :3, 3]
    err = np.linalg.norm(disp_est - disp_true, axis=1)
    assert err[-1] < 0.5, err
    # gravity alignment: roll and pitch of the first keyframe match the truth's
    z_est = res.T_WI[0][:3, :3].T @ np.array([0.0, 0.0, 1.0])
    z_true = truth.T_WI[0][:3, :3].T @ np.array([0.0, 0.0, 1.0])
    # (up to the tilt the accelerometer bias of 0.11 m/s^2 causes: 0.65 deg)
    assert np.degrees(np.arccos(np.clip(z_est @ z_true, -1, 1))) < 1.0


def test_segments_after_a_restart_are_evaluated_each_on_its_own(tmp_path: Path, truth) -> None:
    """A run whose second segment lives in another world frame (the smoother restarted): one alignment
    of the whole file shows the frame jump, each segment aligned on its own shows the noise (1 cm)."""
    t, T = _perturbed(truth, 0.01)
    half = len(t) // 2
    jump = np.eye(4)
    jump[:3, :3] = Rotation.from_euler("z", 0.3).as_matrix()
    jump[:3, 3] = [2.0, -1.0, 0.5]
    T_run = T.copy()
    T_run[half:] = jump @ T[half:]
    out = tmp_path / "run"
    out.mkdir()
    write_tum(out / "trajectory.tum", t, T_run)
    write_tum(out / "trajectory_segment_1.tum", t[:half], T_run[:half])
    write_tum(out / "trajectory_segment_2.tum", t[half:], T_run[half:])
    gt_path = tmp_path / "gt.tum"
    write_tum(gt_path, truth.t_ns, truth.T_WI)
    result = evaluation(out, gt_path)
    assert [s["file"] for s in result["segments"]] == ["trajectory_segment_1.tum", "trajectory_segment_2.tum"]
    assert result["ape_rmse_m"] > 0.3
    for seg in result["segments"]:
        assert seg["ape_rmse_m"] < 3 * 0.01 * np.sqrt(3)
    assert "segment trajectory_segment_2.tum: APE RMSE" in format_evaluation(result)
