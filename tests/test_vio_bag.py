"""VIO bags: the streaming writer, the time-sorted reader and its handling of bad input, and
``dcc-fg simulate flight``."""

from __future__ import annotations

import logging
import subprocess
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import dcc_fg.sources.vio_bag as vio_bag_module
import dcc_fg.vio.pipeline as pipeline_module
import dcc_fg.vio.worker as worker_module
from dcc_fg.cli import main
from dcc_fg.data.cameras import RunCamera
from dcc_fg.data.vio import ImuConfig, ImuSamples, load_imu_config
from dcc_fg.io.bag_writer import BagWriter
from dcc_fg.io.bags import bag_messages, open_bag
from dcc_fg.model import load_calibration
from dcc_fg.sim.trajectory import flight_calibration
from dcc_fg.sources.vio_bag import VioBag, VioFrame
from dcc_fg.vio.backend import VioOptions
from dcc_fg.vio.pipeline import (
    BagTopics,
    PipelineOptions,
    bag_synchronized,
    check_time_offsets,
    run_vio_bag,
    warn_persistence_on_unsynchronized,
)

T0 = 1_600_000_000_000_000_000
MS = 1_000_000


def _write(
    path: Path,
    ros: int = 2,
    imu_t: np.ndarray | None = None,
    acc: np.ndarray | None = None,
    frame_t: np.ndarray | None = None,
    imu_topic: str = "/imu0",
    dynamic: bool = True,
    dynamic_t: np.ndarray | None = None,
) -> Path:
    """A small bag: 200 Hz IMU over 1 s and 20 Hz 32x24 image pairs (unless overridden); ``dynamic_t``
    gives the gimbal camera its own stamps (an unsynchronized stream, recorded at its stamps)."""
    imu_t = T0 + np.arange(201) * 5 * MS if imu_t is None else imu_t
    acc = np.tile([0.1, 0.2, 9.81], (imu_t.size, 1)) if acc is None else acc
    frame_t = T0 + np.arange(21) * 50 * MS if frame_t is None else frame_t
    rng = np.random.default_rng(0)
    # IMU messages are recorded in their given order, at a record time that keeps increasing even
    # where the header stamps do not (as a bag recorder does)
    record = np.maximum.accumulate(imu_t)
    # images are recorded in their given order too (stamps out of order are recorded at increasing times)
    frame_record = np.sort(frame_t)
    events = [(int(t), 0, i) for i, t in enumerate(record)] + [(int(t), 1, i) for i, t in enumerate(frame_record)]
    if dynamic_t is not None:
        events += [(int(t), 2, i) for i, t in enumerate(dynamic_t)]
    events.sort(key=lambda e: (e[0], e[1], e[2]))
    with BagWriter(path, ros) as bag:  # type: ignore[arg-type]
        for t, kind, i in events:
            if kind == 0:
                bag.imu(imu_topic, int(imu_t[i]), acc[i], np.array([0.01, -0.02, 0.03]), record_ns=t)
            elif kind == 2:
                bag.image("/cam1/image_raw", t, rng.integers(0, 255, (24, 32), dtype=np.uint8), "cam1")
            else:
                img = rng.integers(0, 255, (24, 32), dtype=np.uint8)
                bag.image("/cam0/image_raw", int(frame_t[i]), img, "cam0", record_ns=t)
                if dynamic and dynamic_t is None:
                    bag.image("/cam1/image_raw", t, img[:, ::-1].copy(), "cam1")
    return path


@pytest.mark.parametrize("ros", [1, 2])
def test_round_trip_is_time_sorted(tmp_path: Path, ros: int) -> None:
    path = _write(tmp_path / ("a.bag" if ros == 1 else "a"), ros)
    assert not (tmp_path / ".a.bag.partial").exists() and not (tmp_path / ".a.partial").exists()
    vb = VioBag(path, "/imu0", "/cam0/image_raw", "/cam1/image_raw")
    assert len(vb) == 21 and len(vb.imu) == 201 and vb.duration_s == pytest.approx(1.0)
    last, n_imu, n_frames = -1, 0, 0
    for item in vb:
        if isinstance(item, ImuSamples):
            assert item.t_ns[0] > last and np.all(np.diff(item.t_ns) > 0)
            assert np.allclose(item.acc, [0.1, 0.2, 9.81]) and np.allclose(item.gyro, [0.01, -0.02, 0.03])
            last = int(item.t_ns[-1])
            n_imu += len(item)
        else:
            assert isinstance(item, VioFrame)
            assert item.timestamp_ns >= last  # all IMU up to the frame came first
            assert item.dynamic is not None and np.array_equal(item.dynamic, item.static[:, ::-1])
            assert not item.after_gap
            last = item.timestamp_ns
            n_frames += 1
    assert (n_imu, n_frames) == (201, 21)
    mono = VioBag(path, "/imu0", "/cam0/image_raw")
    assert all(f.dynamic is None for f in mono.frames())


def test_unsynchronized_gimbal_stream_is_paired_by_exposure_time(tmp_path: Path, caplog) -> None:
    """A 20 Hz static and a 30 Hz gimbal camera on their own clocks: every static frame takes its nearest
    gimbal image (automatic tolerance: half the 50 ms period), in exposure time (stamp + offset), and
    keeps its own stamp; after the gimbal stream stops the static frames go on without it."""
    gimbal_t = T0 + 7 * MS + np.arange(20) * 33_333_333  # 30 Hz, stops after 0.64 s
    path = _write(tmp_path / "u", dynamic_t=gimbal_t)
    with caplog.at_level(logging.WARNING):
        vb = VioBag(path, "/imu0", "/cam0/image_raw", "/cam1/image_raw")
    frames = list(vb.frames())
    assert len(frames) == 21 and vb.tolerance_ns == 25 * MS
    with_gimbal = [f for f in frames if f.dynamic is not None]
    gaps = np.array([f.dynamic_timestamp_ns - f.timestamp_ns for f in with_gimbal])
    assert len(with_gimbal) == 14 and np.abs(gaps).max() <= 17 * MS  # the nearest 30 Hz image (to 0.65 s)
    assert all(f.dynamic is None for f in frames[14:])  # the stream stopped
    assert "static frames without a partner are used without the gimbal camera" in caplog.text
    # every gimbal image up to the last partner reaches the front end once, in stamp order: as a frame's
    # partner or as an image between two frames (tracked through)
    seen = [
        t for f in frames for t in (*f.dynamic_between_ns, *([f.dynamic_timestamp_ns] if f.dynamic is not None else []))
    ]
    assert seen == sorted(seen) and seen == [int(t) for t in gimbal_t if t <= with_gimbal[-1].dynamic_timestamp_ns]
    assert vb.gimbal_images_between == len(seen) - 14 > 0
    assert all(len(f.dynamic_between) == len(f.dynamic_between_ns) for f in frames)
    # pairing by exposure time: a 40 ms offset of the gimbal stamps (t_imu = stamp + 0.040) moves the partners
    shifted = VioBag(path, "/imu0", "/cam0/image_raw", "/cam1/image_raw", time_offsets_ns=(0, 40 * MS))
    pairs = [(f.timestamp_ns, f.dynamic_timestamp_ns) for f in shifted.frames() if f.dynamic is not None]
    exposure_gap = np.array([d + 40 * MS - s for s, d in pairs])
    assert len(pairs) >= 12 and np.abs(exposure_gap).max() <= 25 * MS and np.median(np.abs(exposure_gap)) <= 17 * MS


def test_start_offsets_beyond_half_or_one_frame_period(tmp_path: Path, caplog) -> None:
    """Start values of the time offsets: beyond half the 50 ms frame period a logged warning (images
    are paired by stamp + offset), beyond one period a refusal naming the topic, period and offset."""
    vb = VioBag(_write(tmp_path / "h"), "/imu0", "/cam0/image_raw", "/cam1/image_raw")
    check_time_offsets(vb, VioOptions(time_offsets=(0.01, -0.02)))  # within half a period: silent
    with caplog.at_level(logging.WARNING):
        check_time_offsets(vb, VioOptions(time_offsets=(0.03, 0.0)))
    assert "more than half a frame period (50.0 ms)" in caplog.text
    with pytest.raises(
        ValueError, match=r"topic /cam1/image_raw: .* gimbal camera's time offset is 80 ms, more than one"
    ):
        check_time_offsets(vb, VioOptions(time_offsets=(0.0, 0.08)))


def test_image_stamps_out_of_record_order_are_sorted(tmp_path: Path, caplog) -> None:
    t = T0 + np.arange(21) * 50 * MS
    t[[5, 6]] = t[[6, 5]]  # recorded in the wrong order
    with caplog.at_level(logging.WARNING):
        vb = VioBag(_write(tmp_path / "o", frame_t=t), "/imu0", "/cam0/image_raw")
    stamps = [f.timestamp_ns for f in vb.frames()]
    assert stamps == sorted(stamps) and len(stamps) == 21
    assert "the header stamp goes backwards 1 times in record order" in caplog.text


def test_missing_or_wrong_topics(tmp_path: Path) -> None:
    path = _write(tmp_path / "b", imu_topic="/imu/data")
    with pytest.raises(ValueError, match=r"topic /imu0 not found; the bag has: .*/imu/data \(sensor_msgs/msg/Imu\)"):
        VioBag(path, "/imu0", "/cam0/image_raw", "/cam1/image_raw")
    with pytest.raises(ValueError, match="topic /cam0/image_raw has type sensor_msgs/msg/Image, expected sensor_msgs"):
        VioBag(path, "/cam0/image_raw", "/cam0/image_raw")
    with pytest.raises(ValueError, match="topic /cam2/image_raw not found"):
        VioBag(path, "/imu/data", "/cam0/image_raw", "/cam2/image_raw")


def test_imu_going_backwards(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    t = T0 + np.arange(201) * 5 * MS
    t[100] = t[98]  # one stamp repeats an earlier one
    with caplog.at_level(logging.WARNING):
        vb = VioBag(_write(tmp_path / "c", imu_t=t), "/imu0", "/cam0/image_raw", "/cam1/image_raw")
    assert vb.imu_check.out_of_order == 1 and len(vb.imu) == 200 and np.all(np.diff(vb.imu.t_ns) > 0)
    assert "go backwards or repeat" in caplog.text
    t = T0 + np.arange(201) * 5 * MS
    t[50:150] = t[50:150][::-1]  # half the stream reversed: not recoverable
    with pytest.raises(ValueError, match=r"topic /imu0: \d+ of 201 IMU samples are unusable .* going backwards"):
        VioBag(_write(tmp_path / "d", imu_t=t), "/imu0", "/cam0/image_raw", "/cam1/image_raw")


def test_nan_imu_samples(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    acc = np.tile([0.1, 0.2, 9.81], (201, 1))
    acc[77, 1] = np.nan
    with caplog.at_level(logging.WARNING):
        vb = VioBag(_write(tmp_path / "e", acc=acc), "/imu0", "/cam0/image_raw", "/cam1/image_raw")
    assert vb.imu_check.non_finite == 1 and len(vb.imu) == 200 and np.all(np.isfinite(vb.imu.acc))
    assert "NaN/inf" in caplog.text
    acc[20:60] = np.nan
    with pytest.raises(ValueError, match=r"41 of 201 IMU samples are unusable \(41 NaN/inf"):
        VioBag(_write(tmp_path / "f", acc=acc), "/imu0", "/cam0/image_raw", "/cam1/image_raw")


def test_gaps_are_reported(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    frame_t = T0 + np.concatenate([np.arange(10) * 50, 3000 + np.arange(10) * 50]) * MS
    imu_t = T0 + np.concatenate([np.arange(100) * 5, 600 + np.arange(600) * 5]) * MS  # IMU gap 495..600 ms
    with caplog.at_level(logging.WARNING):
        vb = VioBag(_write(tmp_path / "g", imu_t=imu_t, frame_t=frame_t), "/imu0", "/cam0/image_raw")
    assert vb.image_gaps == [(int(frame_t[9]), int(frame_t[10]))]
    assert vb.imu_gaps == [(int(imu_t[99]), int(imu_t[100]))]
    assert "image gap of 2.550 s" in caplog.text and "IMU gap of 0.105 s" in caplog.text
    flagged = [f.timestamp_ns for f in vb.frames() if f.after_gap]
    assert flagged == [int(frame_t[10])]  # first frame after both gaps


def test_pose_messages_hold_the_rotation_with_w_nonnegative(tmp_path: Path) -> None:
    rotations = [Rotation.random(random_state=seed) for seed in range(20)]
    with BagWriter(tmp_path / "poses", 2) as bag:
        for k, R in enumerate(rotations):
            T = np.eye(4)
            T[:3, :3] = R.as_matrix()
            bag.pose("/pose", T0 + k * MS, T)
    with open_bag(tmp_path / "poses") as reader:
        msgs = [msg for _, _, msg in bag_messages(tmp_path / "poses", reader, list(reader.connections))]
    for R, msg in zip(rotations, msgs, strict=True):
        o = msg.pose.orientation
        q = np.array([o.x, o.y, o.z, o.w])
        ref = R.as_quat()
        assert q[3] >= 0 and np.allclose(q, ref if ref[3] >= 0 else -ref, atol=1e-12)


def test_simulate_flight_cli(tmp_path: Path) -> None:
    out = tmp_path / "fl"
    code = main(["simulate", "flight", "--out", str(out), "--duration", "5", "--scale", "0.25", "--quiet"])
    assert code == 0
    cal = load_calibration(out / "calibration.yaml")
    imu = load_imu_config(out / "calibration.yaml")
    assert cal.n_joints == 2 and imu is not None and cal.static_camera is not None
    assert cal.static_camera.resolution == (160, 120)
    vb = VioBag(out / "flight", "/imu0", "/cam0/image_raw", "/cam1/image_raw")
    assert len(vb) == 101 and len(vb.imu) == 1001 and not vb.image_gaps and not vb.imu_gaps
    tum = np.loadtxt(out / "ground_truth.tum")
    assert tum.shape == (1001, 8)
    with open_bag(out / "flight") as reader:
        conns = [c for c in reader.connections if c.topic == "/ground_truth/pose"]
        _, _, msg = next(bag_messages(out / "flight", reader, conns))
    p = msg.pose.position
    assert np.allclose([p.x, p.y, p.z], tum[0, 1:4]) and msg.header.stamp.sec == int(tum[0, 0])
    # the bag's gravity-dominated specific force: ~9.81 m/s^2 at standstill (first second hovers)
    assert np.linalg.norm(vb.imu.acc[:100].mean(axis=0)) == pytest.approx(imu.gravity, abs=0.2)
    frames = list(vb.frames())
    assert frames[0].static.shape == (120, 160) and frames[0].static.std() > 30  # textured, not blank
    joints = np.loadtxt(out / "ground_truth_joints.csv", delimiter=",", skiprows=1)
    assert joints.shape == (101, 3)
    with pytest.raises(SystemExit):
        main(["simulate", "flight", "--out", str(out), "--format", "ros3"])


def test_a_first_pass_given_is_not_read_again(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The front end's process gets the parent's first pass of the bag (IMU and image stamps) and builds
    the same frames from it without reading it again; a first pass of other topics is refused."""
    path = _write(tmp_path / "b")
    vb = VioBag(path, "/imu0", "/cam0/image_raw", "/cam1/image_raw")

    def read_again(*args: object) -> None:
        raise AssertionError("the first pass was read again")

    monkeypatch.setattr(vio_bag_module, "scan_imu_and_image_stamps", read_again)
    again = VioBag(path, "/imu0", "/cam0/image_raw", "/cam1/image_raw", scan=vb.scan)
    np.testing.assert_array_equal(again.imu.t_ns, vb.imu.t_ns)
    np.testing.assert_array_equal(again.imu.acc, vb.imu.acc)
    ours, theirs = list(vb.frames()), list(again.frames())
    assert len(ours) == len(theirs) == 21
    for a, b in zip(ours, theirs, strict=True):
        assert a.timestamp_ns == b.timestamp_ns and a.dynamic_timestamp_ns == b.dynamic_timestamp_ns
        assert np.array_equal(a.static, b.static) and np.array_equal(a.dynamic, b.dynamic)  # type: ignore[arg-type]
    with pytest.raises(
        ValueError, match=r"/b: the given first pass has image topics /cam0/image_raw, /cam1/image_raw, "
    ):
        VioBag(path, "/imu0", "/cam0/image_raw", scan=vb.scan)


def test_a_bag_refused_stops_the_front_end_process(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The front end's process starts before the bag is read (its imports overlap the first pass); when
    the bag is refused, the process is stopped, not left behind."""
    path = _write(tmp_path / "b")
    started: list[subprocess.Popen[bytes]] = []

    def spawn() -> subprocess.Popen[bytes]:
        started.append(worker_module.spawn_frontend_process())
        return started[-1]

    monkeypatch.setattr(pipeline_module, "spawn_frontend_process", spawn)
    cal = flight_calibration()
    topics = BagTopics(imu="/imu_missing")
    with pytest.raises(ValueError, match="topic /imu_missing not found"):
        run_vio_bag(path, cal, ImuConfig(), VioOptions(mode="dcc"), topics, PipelineOptions(worker="process"))
    assert len(started) == 1 and started[0].poll() is not None


def test_the_front_end_process_imports_the_parents_dcc_fg(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Started from a folder holding another ``dcc_fg`` (a checkout of another version), the front end's
    process still imports the parent's: ``python -m`` would put the working directory first, and a child
    of another version deadlocked with its parent (found running an old checkout's VIO from this one's
    folder). Here the folder's ``dcc_fg`` fails to import; the child reaches its spec (EOF: exit 0)."""
    fake = tmp_path / "dcc_fg"
    (fake / "vio").mkdir(parents=True)
    (fake / "__init__.py").write_text("raise ImportError('the working directory dcc_fg was imported')\n")
    (fake / "vio" / "__init__.py").write_text("")
    monkeypatch.chdir(tmp_path)
    proc = worker_module.spawn_frontend_process()
    _, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0


def test_non_persistent_landmarks_on_unsynchronized_cameras_warn(tmp_path: Path, caplog) -> None:  # noqa: ANN001
    """``persistent_landmarks`` given as ``none`` or ``gimbal`` with a gimbal camera on its own clock is warned
    about (``none`` measured 1.19x the translation RMSE of ``all`` there); synchronized pairs, ``all`` or
    ``auto`` are not, and ``auto`` resolves to ``none`` with 2.5 s on synchronized cameras, ``all`` with
    1.5 s on unsynchronized ones or with further cameras."""
    synced = VioBag(_write(tmp_path / "s"), "/imu0", "/cam0/image_raw", "/cam1/image_raw")
    gimbal_t = T0 + 7 * MS + np.arange(30) * 33_333_333  # 30 Hz on its own phase
    unsynced = VioBag(_write(tmp_path / "u", dynamic_t=gimbal_t), "/imu0", "/cam0/image_raw", "/cam1/image_raw")
    assert bag_synchronized(synced, "dcc", ()) and bag_synchronized(unsynced, "mono", ())
    assert not bag_synchronized(unsynced, "dcc", ()) and not bag_synchronized(unsynced, "scc", ())
    further = (RunCamera(2, "cam2", None, "/cam2/image_raw", np.eye(4)),)  # type: ignore[arg-type]
    assert not bag_synchronized(synced, "dcc", further)
    auto = VioOptions()
    assert (auto.resolved(True).persistent_landmarks, auto.resolved(True).lag) == ("none", 2.5)
    assert (auto.resolved(False).persistent_landmarks, auto.resolved(False).lag) == ("all", 1.5)
    assert VioOptions(lag=2.0).resolved(True).lag == 2.0  # a given window is kept
    assert VioOptions(landmarks="smart").resolved(True).persistent_landmarks == "all"
    none = VioOptions(persistent_landmarks="none", lag=2.5)
    caplog.clear()  # the bag's own pairing warning
    with caplog.at_level(logging.WARNING):
        assert not warn_persistence_on_unsynchronized(synced, none, True)
        assert not warn_persistence_on_unsynchronized(unsynced, auto, False)
        assert not warn_persistence_on_unsynchronized(unsynced, VioOptions(persistent_landmarks="all"), False)
        assert not caplog.records
        assert warn_persistence_on_unsynchronized(unsynced, none, False)
    assert "gimbal camera is not synchronized" in caplog.text and "--persistent-landmarks all" in caplog.text
    assert "/u" in caplog.text
