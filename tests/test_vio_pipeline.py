"""Images to trajectory: rendered flights through ``dcc-fg vio`` (front end + smoother), dcc vs scc.

Two 20 s flights of the same body trajectory, IMU noise and textures (seed 0), written as ROS2
bags: one with the gimbal moving freely (sinusoids and +-30 deg slews at up to 60 deg/s) for
``dcc``, one with the gimbal locked at its mid position for ``scc``. The acceptance levels are the
issue's (normalized translation RMSE <= 1 % and <= 1.25x scc; joint RMSE <= 1e-2 rad; back under
1e-2 rad within 1 s of every slew); the noise of the rendered images (2 grey levels, KLT) and of
the ADIS16448 IMU puts the expected errors an order of magnitude below them.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from rosbags.rosbag2 import Reader, Writer
from rosbags.typesys import Stores, get_typestore

from dcc_fg.cli import main
from dcc_fg.sim.flight_bag import FlightBag, load_flight_calibration, write_flight
from dcc_fg.sim.trajectory import FlightConfig, locked_gimbal
from dcc_fg.studies.vio_study import slew_recovery_errors
from dcc_fg.vio.backend import VioOptions
from dcc_fg.vio.evaluate import evaluate_output, evaluate_trajectory, joint_rmse, load_ground_truth
from dcc_fg.vio.pipeline import FrameEvent, PipelineOptions, run_vio_bag

pytestmark = pytest.mark.slow  # renders two 20 s flights and runs the whole VIO on them (~2-3 min)

DURATION = 20.0


@pytest.fixture(scope="module")
def flights(tmp_path_factory: pytest.TempPathFactory) -> dict[str, FlightBag]:
    root = tmp_path_factory.mktemp("flights")
    cfg = FlightConfig.short(DURATION)
    return {
        "moving": write_flight(root / "moving", "ros2", cfg, seed=0),
        "locked": write_flight(root / "locked", "ros2", cfg, seed=0, joints=locked_gimbal()),
    }


@pytest.fixture(scope="module")
def dcc(flights: dict[str, FlightBag]) -> dict[str, Any]:
    """dcc through the Python API with no joint-angle guess at all (found from the first frame)."""
    fb = flights["moving"]
    cal, imu = load_flight_calibration(fb.calibration)
    focal = float(cal.static_camera.intrinsics[0])  # type: ignore[union-attr]
    events: list[FrameEvent] = []
    opts = VioOptions(mode="dcc", sigma=1.0 / focal, keyframe_every=3)
    progress: list[tuple[int, int, float, float]] = []
    res, run = run_vio_bag(fb.bag, cal, imu, opts, observer=events.append, progress=lambda *a: progress.append(a))
    gt = load_ground_truth(fb.bag)
    ev = evaluate_trajectory(res.timestamps_ns, res.T_WI, gt, "se3")
    ev["joint_rmse_rad"] = joint_rmse(res.timestamps_ns, res.theta, gt)
    # slew_recovery_errors works on simulation times: undo the bag's time offset
    t0 = int(gt.t_ns[0]) - int(fb.truth.t_ns[0])
    res.timestamps_ns = res.timestamps_ns - t0
    return {**ev, "result": res, "truth": fb.truth, "run": run, "events": events, "progress": progress}


@pytest.fixture(scope="module")
def scc(flights: dict[str, FlightBag], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """scc through the command line, the locked angles read from the flight's calibration.yaml."""
    fb = flights["locked"]
    locked = yaml.safe_load(fb.calibration.read_text())["flight"]["joints_locked"]
    out = tmp_path_factory.mktemp("scc")
    fixed = ",".join(repr(x) for x in locked)
    argv = ["vio", str(fb.bag), "--calibration", str(fb.calibration), "--mode", "scc", "--fixed-joints", fixed]
    assert main([*argv, "--out", str(out), "--quiet"]) == 0
    return {"out": out, **evaluate_output(out, fb.bag)}


def test_dcc_within_one_percent_and_scc(dcc: dict[str, Any], scc: dict[str, Any]) -> None:
    assert dcc["result"].stats["failed_updates"] == 0
    assert dcc["distance_m"] > 40.0
    print(
        f"\nrendered {DURATION:.0f} s flight, {dcc['distance_m']:.1f} m: normalized translation RMSE dcc "
        f"{dcc['normalized_translation_rmse_percent']:.4f} %, scc {scc['normalized_translation_rmse_percent']:.4f} %; "
        f"APE dcc {dcc['ape_rmse_m']:.4f} m, scc {scc['ape_rmse_m']:.4f} m; real-time factor dcc "
        f"{dcc['result'].stats['real_time_factor']:.2f}"
    )
    assert dcc["normalized_translation_rmse_percent"] <= 1.0
    assert dcc["normalized_translation_rmse_percent"] <= 1.25 * scc["normalized_translation_rmse_percent"]


def test_dcc_joint_angles_and_slews(dcc: dict[str, Any]) -> None:
    truth = dcc["truth"]
    assert np.ptp(truth.theta, axis=0).min() > np.deg2rad(50.0)  # the gimbal really moved
    rmse = dcc["joint_rmse_rad"]
    init = dcc["run"]["initial_joint_angles"]
    after = slew_recovery_errors(dcc, settle=1.0)
    print(f"\njoint RMSE {np.round(rmse, 5)} rad; initial fit {init}; max error 1 s after slews {np.round(after, 5)}")
    assert len(rmse) == 2 and max(rmse) <= 1e-2
    # the first frame's static/gimbal matches put the start within 1e-2 rad without any guess
    assert np.max(np.abs(np.asarray(init["theta_rad"]) - truth.theta[0])) < 1e-2
    assert len(after) >= 3 and max(after) < 1e-2


def test_observer_sees_every_frame(dcc: dict[str, Any]) -> None:
    """``run_vio_bag(observer=...)``: one event per processed frame in order; the keyframe events are the
    result's keyframes, with a pose, joint angles and the window's landmarks; stage-two rejections are
    gimbal tracks of that frame."""
    events: list[FrameEvent] = dcc["events"]
    res = dcc["result"]
    assert len(events) == res.stats["frames"] > 0
    assert len(dcc["progress"]) == res.stats["frames"]  # one progress call per frame
    assert [e.index for e in events] == sorted(e.index for e in events)
    kf = [e for e in events if e.keyframe]
    assert len(kf) == res.timestamps_ns.size
    assert all(e.T_WI is not None and e.theta is not None and e.landmarks is not None for e in kf)
    assert np.median([len(e.landmarks) for e in kf]) > 20  # type: ignore[arg-type]
    rejected = [e for e in events if e.rejected_ids.size]
    assert all(np.isin(e.rejected_ids, e.frame.dynamic_ids).all() for e in rejected)


def test_front_end_process_runs_are_identical(flights: dict[str, FlightBag]) -> None:
    """Two dcc runs of the same bag with the front end in its own process give the same keyframes and the
    same trajectory and joint angles (the child applies the smoother's drops and joint angles at a fixed
    frame, :mod:`dcc_fg.vio.worker`), whatever the load on the machine. Before that rule the first joint's
    RMSE of a 60 s flight varied by 18 % between two runs. Not to the last bit: with the default on this
    synchronized flight (no persistent landmark, 2.5 s) two runs in one process, inline or with the worker,
    and pinned to one core, differ by 1e-11 to 8e-9 (m, and in the rotation entries); with every landmark
    persistent and 1.5 s they are bit-identical (ad-hoc runs on this test's flight). The
    order of some floating-point sums depends on where things sit in memory (not identified whether in the
    smoother's marginalization or the linear algebra), so 1e-6 is asserted: far below what a
    scheduling-dependent message would change (millimetres)."""
    fb = flights["moving"]
    cal, imu = load_flight_calibration(fb.calibration)
    opts = VioOptions(mode="dcc", sigma=1.0 / float(cal.static_camera.intrinsics[0]), keyframe_every=3)  # type: ignore[union-attr]
    both = [run_vio_bag(fb.bag, cal, imu, opts, pipeline=PipelineOptions(worker="process")) for _ in range(2)]
    assert [run["frontend_worker"] for _, run in both] == ["process", "process"]
    runs = [res for res, _ in both]
    assert runs[0].timestamps_ns.size > 50
    np.testing.assert_array_equal(runs[0].timestamps_ns, runs[1].timestamps_ns)
    np.testing.assert_allclose(runs[0].T_WI, runs[1].T_WI, rtol=0, atol=1e-6)
    np.testing.assert_allclose(runs[0].theta, runs[1].theta, rtol=0, atol=1e-6)


def test_scc_outputs(scc: dict[str, Any]) -> None:
    out = scc["out"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["mode"] == "scc" and summary["failed_updates"] == 0
    assert summary["run"]["topics"]["dynamic"] == "/cam1/image_raw"
    assert summary["real_time_factor"] > 0 and summary["frames"] == 401
    theta = np.loadtxt(out / "joint_angles.csv", delimiter=",", skiprows=1)[:, 1:]
    assert np.allclose(theta, [np.pi / 2, 0.0])
    assert scc["normalized_translation_rmse_percent"] <= 1.0


def test_bad_input_leaves_no_output(flights: dict[str, FlightBag], tmp_path: Path, capsys) -> None:  # noqa: ANN001
    fb = flights["moving"]
    out = tmp_path / "out"
    base = ["vio", str(fb.bag), "--calibration", str(fb.calibration), "--out", str(out), "--quiet"]
    assert main([*base, "--imu-topic", "/imu_missing"]) == 2
    assert "topic /imu_missing not found" in capsys.readouterr().err
    assert main([*base, "--mode", "scc"]) == 2
    assert "--fixed-joints" in capsys.readouterr().err
    assert main([*base, "--initial-joints", "1.5"]) == 2
    assert "expected 2" in capsys.readouterr().err
    no_imu = tmp_path / "no_imu.yaml"
    d = yaml.safe_load(fb.calibration.read_text())
    del d["imu"]
    no_imu.write_text(yaml.safe_dump(d))
    assert main(["vio", str(fb.bag), "--calibration", str(no_imu), "--out", str(out), "--quiet"]) == 2
    assert "no 'imu:' section" in capsys.readouterr().err
    assert not out.exists()


def _copy_without_images(src: Path, dst: Path, t0_ns: int, t1_ns: int) -> None:
    """Copy a ROS2 bag, leaving out the image messages stamped within [t0, t1] (a camera dropout)."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    with Reader(src) as reader, Writer(dst, version=Writer.VERSION_LATEST) as writer:
        conns = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=store) for c in reader.connections}
        for conn, t, raw in reader.messages():
            if conn.msgtype == "sensor_msgs/msg/Image" and t0_ns <= t <= t1_ns:
                continue
            writer.write(conns[conn.id], t, raw)


def test_image_gap_is_logged_and_bridged(
    flights: dict[str, FlightBag], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Two seconds without images mid-flight (during a gimbal slew): the reader logs the gap, the
    front end restarts its tracks, the smoother bridges it on the IMU and re-acquires the joint
    angles; the trajectory stays within the accuracy target instead of silently going wrong."""
    fb = flights["moving"]
    start = int(load_ground_truth(fb.bag).t_ns[0])
    gapped = tmp_path / "gapped"
    _copy_without_images(fb.bag, gapped, start + 9 * 10**9, start + 11 * 10**9)
    cal, imu = load_flight_calibration(fb.calibration)
    with caplog.at_level("WARNING"):
        res, run = run_vio_bag(gapped, cal, imu, VioOptions(mode="dcc", sigma=1.0 / 460.0, keyframe_every=3))
    assert "image gap of 2.100 s" in caplog.text and "IMU-only propagation" in caplog.text
    assert run["image_gaps"] == 1 and run["frontend_resets"] == 1 and res.stats["failed_updates"] == 0
    gt = load_ground_truth(fb.bag)
    ev = evaluate_trajectory(res.timestamps_ns, res.T_WI, gt, "se3")
    rmse = joint_rmse(res.timestamps_ns, res.theta, gt)
    late = res.timestamps_ns > start + 13 * 10**9  # 2 s after the images come back
    idx = np.searchsorted(gt.joint_t_ns, res.timestamps_ns[late])
    late_err = np.abs(res.theta[late] - gt.joints[idx]).max()
    print(
        f"\n2 s image gap: normalized translation RMSE {ev['normalized_translation_rmse_percent']:.4f} %, joint RMSE "
        f"{np.round(rmse, 5)} rad, max joint error from 2 s after the gap {late_err:.2e} rad"
    )
    assert ev["normalized_translation_rmse_percent"] <= 1.0
    assert late_err < 1e-2


def test_unsynchronized_flight_through_the_command_line(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    """``dcc-fg simulate flight --rates 20,30 --time-offsets 0.005,0.015`` then ``dcc-fg vio``: every static
    frame is paired with its nearest gimbal image, the offsets come out within 1 ms of the truth (start
    0), summary.json reports them with their 1-sigma, and a start value beyond a frame period is refused."""
    fl = tmp_path / "fl"
    sim = ["simulate", "flight", "--out", str(fl), "--duration", "14", "--rates", "20,30"]
    assert main([*sim, "--time-offsets", "0.005,0.015", "--quiet"]) == 0
    out = tmp_path / "run"
    base = ["vio", str(fl / "flight"), "--calibration", str(fl / "calibration.yaml"), "--quiet"]
    assert main([*base, "--time-offsets", "0,0.05", "--out", str(out)]) == 2
    assert "more than one frame period (33.3 ms)" in capsys.readouterr().err and not out.exists()
    assert main([*base, "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    to = s["time_offsets"]
    assert abs(to["static_s"] - 0.005) <= 1e-3 and abs(to["dynamic_s"] - 0.015) <= 1e-3, to
    assert 0 < to["static_sigma_s"] < 1e-3 and 0 < to["dynamic_sigma_s"] < 1e-3
    assert s["run"]["pairing"]["pairs"] >= 0.95 * s["run"]["frames_in_bag"]  # nearly every static frame paired
    assert s["run"]["pairing"]["gap_max_ms"] <= 25.0 and s["health"]["healthy"]
    ev = evaluate_output(out, fl / "flight")
    assert ev["normalized_translation_rmse_percent"] < 1.0 and max(ev["joint_rmse_rad"]) < 1e-2
