"""Unsynchronized camera streams of the simulators (issue 15, part 1): rates, phase, time offsets,
stamp jitter, and the continuous-motion calibration recording.

Convention under test (dcc_fg.sim.timing): t_imu = t_cam_stamp + t_offset, i.e. an image exposed at
true time t is stamped t - t_offset.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import yaml

from dcc_fg.cli import main
from dcc_fg.io.bags import BagTopicImages, scan_imu_and_image_stamps
from dcc_fg.io.outputs import read_joint_angles_csv
from dcc_fg.sim.calibration_motion import ContinuousMotion
from dcc_fg.sim.flight_bag import (
    FRAMES_NAME,
    START_NS,
    CameraFrame,
    load_flight_calibration,
    load_flight_timing,
    read_frames_csv,
    render_frames,
    scaled_flight_calibration,
    write_flight,
)
from dcc_fg.sim.flight_render import WorldRenderer, planes_from_world, render_flight
from dcc_fg.sim.timing import CameraTiming
from dcc_fg.sim.trajectory import FlightConfig, World, default_static_mount, simulate_flight, truth_at
from dcc_fg.sim.write_dataset import (
    CONTINUOUS_T0_NS,
    CalibrationSimSpec,
    RenderedCalibration,
    load_ground_truth,
    write_calibration_dataset,
)

NS = 1_000_000_000
DURATION = 4.5  # the shortest flight FlightConfig allows is > 4 s
SCALE = 0.1  # 64 x 48 images
RATES, PHASE, OFFSETS = (20.0, 30.0), 0.004, (0.005, 0.015)
TOPICS = ("/cam0/image_raw", "/cam1/image_raw")


# ------------------------------------------------------------------ CameraTiming (pure)


def test_streams_follow_rates_phase_and_offsets() -> None:
    timing = CameraTiming(RATES, PHASE, OFFSETS)
    t_end = int(DURATION * NS)
    streams = timing.streams(t_end)
    for c, s in enumerate(streams):
        period = NS / RATES[c]
        phase = 0.0 if c == 0 else PHASE
        k = (s.exposure_ns - phase * NS) / period
        assert np.allclose(k, np.round(k), atol=1e-6)  # on the camera's own grid
        assert np.all(np.diff(np.round(k)) == 1)  # no frame skipped
        assert np.all(s.exposure_ns - s.stamp_ns == round(OFFSETS[c] * NS))  # t_exposure = stamp + offset
        inside = (s.exposure_ns >= 0) & (s.exposure_ns <= t_end) & (s.stamp_ns >= 0) & (s.stamp_ns <= t_end)
        assert inside.all()
        # all grid frames inside the window are kept: count = window length * rate (+-1)
        assert abs(len(s) - (DURATION - OFFSETS[c]) * RATES[c]) <= 1.0 + 1e-9
    # the positive offsets drop the frame exposed at 0 (its stamp would precede the recording)
    assert streams[0].exposure_ns[0] == 50_000_000


def test_default_timing_is_the_synchronized_20_hz_grid_of_the_flight() -> None:
    truth = simulate_flight(FlightConfig.short(DURATION), noise=False)
    s, d = CameraTiming().streams(int(truth.t_ns[-1]))
    for stream in (s, d):
        assert np.array_equal(stream.exposure_ns, truth.frame_t_ns)
        assert np.array_equal(stream.stamp_ns, truth.frame_t_ns)


def test_jitter_statistics_and_non_monotonic_warning(caplog: pytest.LogCaptureFixture) -> None:
    jitter = 0.002
    s, d = CameraTiming((200.0, 200.0), 0.0, (0.0, 0.0), jitter).streams(10 * NS, np.random.default_rng(1))
    noise = np.concatenate([s.stamp_ns - s.exposure_ns, d.stamp_ns - d.exposure_ns]) / NS
    n = noise.size  # ~4000 draws: std estimate within ~5 % (3 sigma of sqrt(1/(2n)))
    assert abs(noise.mean()) < 3 * jitter / np.sqrt(n) + 1e-6
    assert abs(noise.std() / jitter - 1.0) < 3.0 / np.sqrt(2 * n)
    # 2 ms jitter at a 5 ms period: stamps go backwards somewhere -> one warning per camera
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="dcc_fg.sim.timing"):
        CameraTiming((200.0, 200.0), 0.0, (0.0, 0.0), jitter).streams(10 * NS, np.random.default_rng(1))
    assert sum("--stamp-jitter" in r.getMessage() for r in caplog.records) == 2
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="dcc_fg.sim.timing"):
        CameraTiming((20.0, 20.0), 0.0, (0.0, 0.0), 1e-4).streams(10 * NS, np.random.default_rng(1))
    assert not caplog.records  # 0.1 ms jitter at 50 ms: monotonic, silent


@pytest.mark.parametrize(
    "kwargs, flag",
    [
        ({"rates": (20.0, 0.0)}, "--rates"),
        ({"rates": (float("inf"), 20.0)}, "--rates"),
        ({"phase": float("nan")}, "--phase"),
        ({"time_offsets": (0.0, 0.5)}, "--time-offsets"),
        ({"time_offsets": (float("nan"), 0.0)}, "--time-offsets"),
        ({"stamp_jitter": -1e-3}, "--stamp-jitter"),
    ],
)
def test_camera_timing_validation(kwargs: dict[str, object], flag: str) -> None:
    with pytest.raises(ValueError, match=flag):
        CameraTiming(**kwargs)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "argv, flag",
    [
        (["flight", "--rates", "20,-30"], "--rates"),
        (["flight", "--rates", "20"], "--rates"),
        (["flight", "--rates", "nan,20"], "--rates"),
        (["flight", "--phase", "inf"], "--phase"),
        (["flight", "--time-offsets", "0.6,0"], "--time-offsets"),
        (["flight", "--time-offsets", "0,x"], "--time-offsets"),
        (["flight", "--stamp-jitter", "-0.001"], "--stamp-jitter"),
        (["calibration", "--rates", "0,20"], "--rates"),
    ],
)
def test_cli_refuses_bad_timing_flags(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list, flag: str
) -> None:  # type: ignore[type-arg]
    out = tmp_path / "sim"
    with pytest.raises(SystemExit) as exc:
        main(["simulate", argv[0], "--out", str(out), *argv[1:]])
    assert exc.value.code == 2
    assert flag in capsys.readouterr().err
    assert not out.exists()


def test_held_calibration_refuses_timing_flags(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "sim"
    assert main(["simulate", "calibration", "--out", str(out), "--snapshots", "2", "--rates", "20,30"]) == 2
    assert "--motion continuous" in capsys.readouterr().err and not out.exists()
    with pytest.raises(ValueError, match="--snapshots must be >= 2"):
        write_calibration_dataset(tmp_path / "c", CalibrationSimSpec(n_snapshots=1, motion="continuous"))


def test_truth_at_is_the_stored_truth_on_samples_and_continuous_between() -> None:
    truth = simulate_flight(FlightConfig.short(DURATION), noise=False)
    idx = np.arange(0, truth.t_ns.size, 7)
    T, th = truth_at(truth, truth.t_ns[idx])
    assert np.array_equal(T, truth.T_WI[idx]) and np.array_equal(th, truth.theta[idx])
    # 1 ns after a sample: the analytic trajectory, within 1 ns of motion of the sample (<< 1e-6)
    T1, th1 = truth_at(truth, truth.t_ns[idx[:-1]] + 1)
    assert np.abs(T1 - truth.T_WI[idx[:-1]]).max() < 1e-6 and np.abs(th1 - truth.theta[idx[:-1]]).max() < 1e-6
    with pytest.raises(ValueError, match="outside"):
        truth_at(truth, np.array([truth.t_ns[-1] + 1]))


# ------------------------------------------------------------------ flights written to bags


@pytest.fixture(scope="module")
def unsync_flight(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object]:
    out = tmp_path_factory.mktemp("unsync") / "fl"
    res = write_flight(
        out, "ros1", FlightConfig.short(DURATION), seed=2, scale=SCALE, noise_sigma=0.0,
        timing=CameraTiming(RATES, PHASE, OFFSETS),
    )  # fmt: skip
    return out, res


def test_unsynchronized_flight_stamps_and_truth(unsync_flight: tuple[Path, object]) -> None:
    out, res = unsync_flight
    scan = scan_imu_and_image_stamps(out / "flight.bag", "/imu0", TOPICS)
    # IMU unchanged: one message per truth sample at the sample times
    assert np.array_equal(scan.imu_t_ns, res.truth.t_ns + START_NS)  # type: ignore[attr-defined]
    frames = read_frames_csv(out / FRAMES_NAME)
    for c, topic in enumerate(TOPICS):
        stamps = np.array(scan.image_stamps[topic], dtype=np.int64) - START_NS
        period = NS / RATES[c]
        exposure = stamps + round(OFFSETS[c] * NS)  # the convention: t_true = stamp + offset
        k = (exposure - (0.0 if c == 0 else PHASE) * NS) / period
        assert np.allclose(k, np.round(k), atol=1e-6) and np.all(np.diff(np.round(k)) == 1)
        sel = frames["camera"] == c
        assert np.array_equal(frames["stamp_ns"][sel] - START_NS, stamps)
        assert np.array_equal(frames["exposure_ns"][sel] - START_NS, exposure)
        assert res.images[c] == stamps.size  # type: ignore[attr-defined]
    cal = yaml.safe_load((out / "calibration.yaml").read_text())
    tm = cal["flight"]["timing"]
    assert tm["time_offsets_s"] == {"static": OFFSETS[0], "dynamic": OFFSETS[1]}
    assert tm["rates_hz"] == {"static": RATES[0], "dynamic": RATES[1]} and tm["phase_s"] == PHASE
    assert tm["stamp_jitter_s"] == 0.0 and "t_imu = t_cam_stamp + t_offset" in tm["convention"]
    assert load_flight_timing(out / "calibration.yaml") == CameraTiming(RATES, PHASE, OFFSETS)
    load_flight_calibration(out / "calibration.yaml")  # the extra record does not disturb the readers
    # ground_truth_joints.csv: keyed by the gimbal header stamps, angles at the true exposure time
    t_j, th_j = read_joint_angles_csv(out / "ground_truth_joints.csv")
    gimbal = frames["camera"] == 1
    assert np.array_equal(t_j, frames["stamp_ns"][gimbal])
    truth = res.truth  # type: ignore[attr-defined]
    _, th_true = truth_at(truth, t_j - START_NS + round(OFFSETS[1] * NS))
    assert np.allclose(th_j, th_true, atol=1e-10)
    _, th_at_stamp = truth_at(truth, t_j - START_NS)
    assert np.abs(th_at_stamp - th_true).max() > 1e-3  # the gimbal moves: 15 ms matters


def test_unsynchronized_flight_renders_at_the_true_exposure(unsync_flight: tuple[Path, object]) -> None:
    """Each gimbal image of the bag is exactly the noise-free rendering of the pose at stamp + t_d,
    and differs from the rendering at the stamp itself."""
    out, res = unsync_flight
    truth = res.truth  # type: ignore[attr-defined]
    config = FlightConfig.short(DURATION)
    renderer = WorldRenderer(planes_from_world(World.around(config)), seed=2)
    cal = scaled_flight_calibration(SCALE)
    T_sI = default_static_mount()
    images = list(BagTopicImages(out / "flight.bag", TOPICS[1]))
    picks = [len(images) // 3, 2 * len(images) // 3]  # during the gimbal's first slew (t > 4 s is after it)
    n_differ = 0
    for i in picks:
        stamp, img, _ = images[i]
        t_true = stamp - START_NS + round(OFFSETS[1] * NS)
        for t, expect_equal in ((t_true, True), (stamp - START_NS, False)):
            T, th = truth_at(truth, np.array([t]))
            ref = next(render_frames(renderer, [CameraFrame(1, t, t, T[0], th[0])], cal, T_sI, noise_sigma=0.0))
            if expect_equal:
                assert np.array_equal(img, ref)
            else:
                n_differ += int(not np.array_equal(img, ref))
    assert n_differ == len(picks)


def test_default_flight_is_unchanged(tmp_path: Path) -> None:
    """Default flags: both cameras stamped identically on the 20 Hz IMU grid, no timing record,
    the images exactly those of the synchronized renderer (render_flight)."""
    out = tmp_path / "fl"
    argv = ["simulate", "flight", "--out", str(out), "--duration", str(DURATION), "--scale", str(SCALE)]
    assert main([*argv, "--format", "ros1", "--seed", "4", "-q"]) == 0
    truth = simulate_flight(FlightConfig.short(DURATION), seed=4)
    bag = out / "flight.bag"
    scan = scan_imu_and_image_stamps(bag, "/imu0", TOPICS)
    expected = list(truth.frame_t_ns + START_NS)
    assert scan.image_stamps[TOPICS[0]] == expected and scan.image_stamps[TOPICS[1]] == expected
    assert len(scan.imu_t_ns) == truth.t_ns.size
    assert not (out / FRAMES_NAME).exists()
    assert "timing" not in yaml.safe_load((out / "calibration.yaml").read_text())["flight"]
    assert load_flight_timing(out / "calibration.yaml").is_default
    t_j, th_j = read_joint_angles_csv(out / "ground_truth_joints.csv")
    assert list(t_j) == expected
    renderer = WorldRenderer(planes_from_world(World.around(truth.config)), seed=4)
    legacy = render_flight(renderer, truth, scaled_flight_calibration(SCALE), default_static_mount(), 2.0, seed=5)
    got = zip(BagTopicImages(bag, TOPICS[0]), BagTopicImages(bag, TOPICS[1]), strict=True)
    for (t, img_s, img_d), ((ts, a, _), (td, b, _)) in zip(legacy, got, strict=True):
        assert ts == td == t + START_NS
        assert np.array_equal(a, img_s) and np.array_equal(b, img_d)


def test_jittered_flight_keeps_exposure_order(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Jitter comparable to the frame period: a warning, the stamps written as drawn (some go
    backwards) while the bag order follows the true exposure times."""
    out = tmp_path / "fl"
    timing = CameraTiming((20.0, 20.0), 0.0, (0.0, 0.0), 0.03)
    with caplog.at_level(logging.WARNING, logger="dcc_fg.sim.timing"):
        write_flight(out, "ros2", FlightConfig.short(DURATION), seed=1, scale=SCALE, timing=timing)
    assert any("--stamp-jitter" in r.getMessage() for r in caplog.records)
    frames = read_frames_csv(out / FRAMES_NAME)
    for c, topic in enumerate(TOPICS):
        stamps = [s for s, _, _ in BagTopicImages(out / "flight", topic)]
        sel = frames["camera"] == c
        assert stamps == list(frames["stamp_ns"][sel])  # bag order = exposure order (frames are sorted so)
        assert np.all(np.diff(frames["exposure_ns"][sel]) > 0) and np.any(np.diff(stamps) <= 0)
        jitter = (frames["stamp_ns"][sel] - frames["exposure_ns"][sel]) / NS
        # ~90 draws of N(0, 30 ms): the sample std within 35 % (> 3 sigma of sqrt(1/(2n)))
        assert abs(jitter.std() / 0.03 - 1.0) < 0.35
    assert load_flight_timing(out / "calibration.yaml").stamp_jitter == 0.03


# ------------------------------------------------------------------ continuous calibration recordings


CAL_OFFSETS = (0.005, 0.015)
CAL_RATES = (4.0, 6.0)


@pytest.fixture(scope="module")
def continuous_ros1(tmp_path_factory: pytest.TempPathFactory) -> RenderedCalibration:
    spec = CalibrationSimSpec(
        fmt="ros1", seed=3, n_snapshots=3, motion="continuous", timing=CameraTiming(CAL_RATES, 0.01, CAL_OFFSETS)
    )
    return write_calibration_dataset(tmp_path_factory.mktemp("cont") / "set", spec)


def test_continuous_calibration_stamps_and_truth(continuous_ros1: RenderedCalibration) -> None:
    res = continuous_ros1
    gt = yaml.safe_load(res.ground_truth.read_text())
    tm = gt["motion"]["timing"]
    assert gt["motion"]["mode"] == "continuous"
    assert tm["time_offsets_s"] == {"static": CAL_OFFSETS[0], "dynamic": CAL_OFFSETS[1]}
    scan = {topic: [s for s, _, _ in BagTopicImages(res.data, topic)] for topic in TOPICS}
    for c, (name, topic) in enumerate(zip(("static", "dynamic"), TOPICS, strict=True)):
        ims = gt["images"][name]
        stamps = np.array([im["stamp_ns"] for im in ims], dtype=np.int64)
        exposure = np.array([im["exposure_ns"] for im in ims], dtype=np.int64)
        assert list(stamps) == scan[topic] and res.images is not None and res.images[c] == len(ims)
        assert np.all(exposure - stamps == round(CAL_OFFSETS[c] * NS))  # t_true = stamp + offset
        period = NS / CAL_RATES[c]
        k = (exposure - CONTINUOUS_T0_NS - (0.0 if c == 0 else 0.01) * NS) / period
        assert np.allclose(k, np.round(k), atol=1e-6) and np.all(np.diff(np.round(k)) == 1)
        # moving: joint angles and board pose change between consecutive images, within the rate limits
        theta = np.array([im["theta"] for im in ims])
        T_st = np.array([im["T_st"] for im in ims])
        dt = np.diff(exposure) / NS
        joint_rate = np.abs(np.diff(theta, axis=0)) / dt[:, None]
        assert joint_rate.max() > np.deg2rad(5.0) and joint_rate.max() <= np.deg2rad(20.0) * (1 + 1e-6)
        R_rel = np.einsum("kji,kjl->kil", T_st[:-1, :3, :3], T_st[1:, :3, :3])
        angle = np.arccos(np.clip((np.trace(R_rel, axis1=1, axis2=2) - 1) / 2, -1, 1))
        assert angle.max() > 0 and (angle / dt).max() <= np.deg2rad(30.0) * (1 + 1e-6)
        # T_ds is the true chain at the recorded angles; every corner in view at these slow rates
        for im in ims[:: max(1, len(ims) // 5)]:
            assert np.allclose(im["T_ds"], res.sim.truth.T_ds(np.array(im["theta"])), atol=1e-12)
        assert all(im["visible"] for im in ims)
    # loader-compatible snapshots: one per static image, truth at its true exposure time
    loaded = load_ground_truth(res.ground_truth)
    assert list(loaded.timestamps_ns) == scan[TOPICS[0]]
    assert np.allclose(loaded.theta, [im["theta"] for im in gt["images"]["static"]])


def test_continuous_motion_makes_15_ms_matter(continuous_ros1: RenderedCalibration) -> None:
    """At the peak rates a 15 ms offset moves the gimbal camera's corners by more than 1.5 px
    (the truth's waypoints reproduce the recorded motion exactly)."""
    res = continuous_ros1
    gt = yaml.safe_load(res.ground_truth.read_text())
    wp = gt["motion"]["waypoints"]
    pts = res.sim.config.target.points
    motion = ContinuousMotion(np.array([w["T_st"] for w in wp]), np.array([w["theta"] for w in wp]), pts.mean(0))
    assert motion.duration == pytest.approx(gt["motion"]["duration_s"])
    dyn = gt["images"]["dynamic"]
    t = (np.array([im["exposure_ns"] for im in dyn]) - CONTINUOUS_T0_NS) / NS
    T, th = motion.evaluate(t)
    assert np.allclose(T, [im["T_st"] for im in dyn], atol=1e-9) and np.allclose(th, [im["theta"] for im in dyn])
    cam = res.sim.truth.dynamic_camera
    assert cam is not None
    worst = 0.0
    for tk in np.linspace(0.02, motion.duration, 150):
        (Ta, Tb), (qa, qb) = motion.evaluate(np.array([tk, tk - 0.015]))
        uv = [
            cam.project(pts @ M[:3, :3].T + M[:3, 3], jacobian=False)[0]
            for M in (res.sim.truth.T_ds(qa) @ Ta, res.sim.truth.T_ds(qb) @ Tb)
        ]
        worst = max(worst, float(np.linalg.norm(uv[0] - uv[1], axis=1).max()))
    assert worst > 1.5


@pytest.mark.parametrize("fmt", ["folder", "ros2"])
def test_continuous_calibration_cli_formats(tmp_path: Path, fmt: str) -> None:
    out = tmp_path / "set"
    argv = ["simulate", "calibration", "--out", str(out), "--snapshots", "2", "--motion", "continuous",
            "--rates", "3,5", "--time-offsets", "0,0.015", "--seed", "1", "--format", fmt]  # fmt: skip
    assert main(argv) == 0
    gt = yaml.safe_load((out / "ground_truth.yaml").read_text())
    for name, folder, topic in (("static", "cam0", TOPICS[0]), ("dynamic", "cam1", TOPICS[1])):
        if fmt == "folder":
            stamps = sorted(int(p.stem) for p in (out / "images" / folder).glob("*.png"))
        else:
            stamps = [s for s, _, _ in BagTopicImages(out / "images_bag", topic)]
        assert stamps == [im["stamp_ns"] for im in gt["images"][name]] and stamps
    assert gt["motion"]["timing"]["time_offsets_s"]["dynamic"] == 0.015


def test_held_calibration_has_no_motion_record(tmp_path: Path) -> None:
    res = write_calibration_dataset(tmp_path / "set", CalibrationSimSpec(fmt="ros1", n_snapshots=2))
    gt = yaml.safe_load(res.ground_truth.read_text())
    assert "motion" not in gt and "images" not in gt and len(gt["snapshots"]) == 2 and res.images is None
    for snap in gt["snapshots"]:
        assert snap["dynamic_timestamp_ns"] - snap["timestamp_ns"] == 500_000  # today's trigger skew
