"""VIO health: wrong inputs are caught before the run, the divergence detector and the result checks
flag what they should, and correct runs (simulated flights in dcc/scc/mono, EuRoC real data) stay
healthy (no false alarm)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import yaml
from rosbags.rosbag2 import Reader, Writer
from rosbags.typesys import Stores, get_typestore

from dcc_fg.data.vio import ImuConfig, TrackFrame, check_imu_against_frames, load_imu_config
from dcc_fg.io.bag_writer import BagWriter
from dcc_fg.io.euroc import pack_euroc_bag
from dcc_fg.io.tum import read_tum
from dcc_fg.model import load_calibration
from dcc_fg.sim.trajectory import (
    FlightConfig,
    World,
    default_static_mount,
    flight_calibration,
    simulate_flight,
    simulate_tracks,
)
from dcc_fg.sources.eqvio import load_eqvio_csv
from dcc_fg.sources.euroc import load_euroc, write_euroc_calibration
from dcc_fg.sources.vio_bag import VioBag, validate_imu
from dcc_fg.vio.backend import InitialState, KeyframeState, VioOptions, VioResult, run_vio, write_vio_outputs
from dcc_fg.vio.backend.divergence import DivergenceLimits, divergence
from dcc_fg.vio.health import vio_health
from dcc_fg.vio.pipeline import run_vio_bag
from tests.conftest import shared_data

T0 = 1_600_000_000_000_000_000
MS = 1_000_000
NS = 1_000_000_000


# --------------------------------------------------------------------------- divergence detector
def _state(t_s: float, p: list[float], v: list[float]) -> KeyframeState:
    T = np.eye(4)
    T[:3, 3] = p
    return KeyframeState(int(t_s * NS), T, np.asarray(v, float), np.zeros(3), np.zeros(3), np.zeros(0))


LIMITS = DivergenceLimits.from_options(VioOptions(), ImuConfig())


def test_divergence_detector_on_synthetic_states() -> None:
    # 3 m/s along x, keyframes every 0.1 s, accelerating at 2 m/s^2: healthy
    states = [_state(0.1 * i, [0.3 * i + 0.01 * i * i, 0, 0], [3.0 + 0.2 * i, 0, 0]) for i in range(20)]
    for a, b in zip(states[:-1], states[1:], strict=True):
        assert divergence(a, b, LIMITS, velocity_sigma=0.05) is None
    prev = states[-1]
    nan = _state(2.0, [np.nan, 0, 0], [3, 0, 0])
    assert "non-finite" in (divergence(prev, nan, LIMITS) or "")
    fast = _state(2.0, [6.5, 0, 0], [1e28, 0, 0])  # the 1e30 m/s^2 sample's velocity
    assert "speed" in (divergence(prev, fast, LIMITS) or "")
    # 5 m in 0.1 s at 6.8 m/s: beyond 0.68 m + a_max dt^2 / 2 = 0.68 + 0.9 m
    jump = _state(prev.t_ns / NS + 0.1, [prev.T_WI[0, 3] + 5.0, 0, 0], [6.8, 0, 0])
    assert "jumped" in (divergence(prev, jump, LIMITS) or "")
    # the same move but within the IMU's acceleration range passes
    ok = _state(prev.t_ns / NS + 0.1, [prev.T_WI[0, 3] + 1.0, 0, 0], [6.8, 0, 0])
    assert divergence(prev, ok, LIMITS) is None
    assert "covariance" in (divergence(prev, ok, LIMITS, velocity_sigma=5.0) or "")
    assert "covariance" in (divergence(prev, ok, LIMITS, velocity_sigma=float("nan")) or "")


def _result(t_s: np.ndarray, p: np.ndarray, v: np.ndarray, stats: dict) -> VioResult:
    n = t_s.size
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, 3] = p
    return VioResult(
        (t_s * NS).astype(np.int64), T, v, np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 0)), "mono", stats
    )


def test_vio_health_flags_implausible_results() -> None:
    t = np.arange(30) * 0.1
    p = np.c_[3 * t, 0 * t, 0 * t]
    v = np.tile([3.0, 0, 0], (30, 1))
    stats = {"segments": [{"start_ns": 0, "end_ns": int(t[-1] * NS), "keyframes": 30, "reason": "start"}]}
    opts, imu = VioOptions(), ImuConfig()
    good = vio_health(_result(t, p, v, {**stats, "longest_without_vision_s": 0.3}), imu, opts)
    assert good.healthy, good.failure_text()
    v_bad = v.copy()
    v_bad[20] = [1e28, 0, 0]
    p_bad = p.copy()
    p_bad[25:] += 100.0
    bad = vio_health(
        _result(
            t,
            p_bad,
            v_bad,
            {
                **stats,
                "longest_without_vision_s": 10.0,
                "final_velocity_sigma_mps": 50.0,
                "divergences": [{"t_ns": 2 * NS, "reason": "speed 1e28 m/s", "recovered": False}],
            },
        ),
        imu,
        opts,
    )
    failed = {c.name for c in bad.failures}
    assert failed == {"speed", "position_jumps", "vision", "velocity_covariance", "divergences"}
    text = bad.failure_text()
    assert "1e+28 m/s" in text and "max_speed 30" in text and "IMU clock offset" in text
    too_short = vio_health(_result(t[:2], p[:2], v[:2], stats), imu, opts)
    assert [c.name for c in too_short.failures] == ["keyframes"]
    # a jump across a segment boundary is not a jump
    seg2 = {"segments": [*stats["segments"], {"start_ns": int(2.5 * NS), "end_ns": 0, "keyframes": 5, "reason": "x"}]}
    assert vio_health(_result(t, p_bad, v, seg2), imu, opts).healthy


# --------------------------------------------------------------------------- input validation
def test_negative_noise_density_is_refused_naming_field_and_file(tmp_path: Path) -> None:
    path = tmp_path / "calibration.yaml"
    imu = ImuConfig().to_dict()
    imu["accelerometer_noise_density"] = -2e-3
    path.write_text(yaml.safe_dump({"imu": imu}))
    with pytest.raises(ValueError, match=r"calibration\.yaml: imu: 'accelerometer_noise_density' must be a positive"):
        load_imu_config(path)
    for field, value in [("gyroscope_random_walk", float("nan")), ("rate_hz", 0.0), ("acc_range", -1.0)]:
        with pytest.raises(ValueError, match=field):
            ImuConfig(**{field: value})


@pytest.mark.parametrize(
    ("T", "expected"),
    [
        (np.diag([2.0, 2.0, 2.0, 1.0]), "not a rotation"),
        (np.diag([1.0, 1.0, -1.0, 1.0]), r"det = -1"),
        (np.r_[np.eye(4)[:3], [[0.0, 0.0, 1.0, 1.0]]], "last row"),
        (np.eye(3), "4x4"),
    ],
)
def test_T_sI_that_is_not_a_rigid_transform_is_refused(tmp_path: Path, T: np.ndarray, expected: str) -> None:
    path = tmp_path / "calibration.yaml"
    imu = ImuConfig().to_dict()
    imu["T_sI"] = T.tolist()
    path.write_text(yaml.safe_dump({"imu": imu}))
    with pytest.raises(ValueError, match=rf"calibration\.yaml: imu: 'T_sI'.*{expected}"):
        load_imu_config(path)


def _bag(
    path: Path,
    imu_t: np.ndarray,
    frame_t: np.ndarray,
    acc: np.ndarray | None = None,
    duplicate: bool = False,
) -> Path:
    """A ROS2 bag: IMU at ``imu_t`` (gravity along z), 32x24 image pairs at ``frame_t`` (each
    message written twice with ``duplicate``)."""
    acc = np.tile([0.1, 0.2, 9.81], (imu_t.size, 1)) if acc is None else acc
    rng = np.random.default_rng(0)
    events = sorted([(int(t), 0, i) for i, t in enumerate(imu_t)] + [(int(t), 1, i) for i, t in enumerate(frame_t)])
    with BagWriter(path, 2) as bag:
        for t, kind, i in events:
            for _ in range(2 if duplicate else 1):
                if kind == 0:
                    bag.imu("/imu0", t, acc[i], np.array([0.01, -0.02, 0.03]))
                else:
                    img = rng.integers(0, 255, (24, 32), dtype=np.uint8)
                    bag.image("/cam0/image_raw", t, img, "cam0")
                    bag.image("/cam1/image_raw", t, img[:, ::-1].copy(), "cam1")
    return path


FRAMES = T0 + np.arange(41) * 50 * MS  # 20 Hz over 2 s


def test_imu_at_10_hz_is_refused_with_the_measured_rate(tmp_path: Path) -> None:
    imu_t = T0 + np.arange(21) * 100 * MS
    with pytest.raises(ValueError, match=r"topic /imu0: the IMU rate is 10\.0 Hz .* at least 50 Hz"):
        VioBag(_bag(tmp_path / "b", imu_t, FRAMES), "/imu0", "/cam0/image_raw", "/cam1/image_raw")
    # 200 Hz passes, 35 Hz IMU with a 20 Hz camera is refused (below 50 Hz)
    VioBag(_bag(tmp_path / "ok", T0 + np.arange(401) * 5 * MS, FRAMES), "/imu0", "/cam0/image_raw")
    with pytest.raises(ValueError, match=r"the IMU rate is 3[45]\.\d Hz"):
        check_imu_against_frames(T0 + np.arange(71) * 29 * MS, FRAMES, "imu")


def test_imu_clock_offset_of_3_s_is_refused_with_the_offset(tmp_path: Path) -> None:
    frames = T0 + np.arange(201) * 50 * MS  # 10 s of images
    imu_t = T0 + 3 * NS + np.arange(2001) * 5 * MS  # the IMU's clock 3 s ahead
    with pytest.raises(ValueError, match=r"start 3\.00 s before the first IMU sample and end -3\.00 s .* clock"):
        VioBag(_bag(tmp_path / "b", imu_t, frames), "/imu0", "/cam0/image_raw", "/cam1/image_raw")
    # 0.5 s (a recorder starting the IMU late) is accepted
    VioBag(_bag(tmp_path / "ok", imu_t - int(2.5 * NS), frames), "/imu0", "/cam0/image_raw")


def test_a_1e30_sample_is_dropped_with_a_log_line(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    imu_t = T0 + np.arange(401) * 5 * MS
    acc = np.tile([0.1, 0.2, 9.81], (imu_t.size, 1))
    acc[123, 0] = 1e30
    path = _bag(tmp_path / "b", imu_t, FRAMES, acc)
    cfg = ImuConfig()
    with caplog.at_level(logging.WARNING):
        vb = VioBag(path, "/imu0", "/cam0/image_raw", acc_range=cfg.acc_range, gyro_range=cfg.gyro_range)
    assert vb.imu_check.out_of_range == 1 and len(vb.imu) == 400 and np.abs(vb.imu.acc).max() < 10
    assert "dropped 1 IMU samples beyond the sensor's range" in caplog.text and "156.9 m/s^2" in caplog.text


def test_duplicate_messages_are_dropped(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    imu_t = T0 + np.arange(401) * 5 * MS
    with caplog.at_level(logging.WARNING):
        vb = VioBag(_bag(tmp_path / "b", imu_t, FRAMES, duplicate=True), "/imu0", "/cam0/image_raw", "/cam1/image_raw")
    # dropped while reading the bag (dcc_fg.io.bags) or, failing that, by VioBag itself
    assert len(vb) == 41 and len(vb.imu) == 401 and np.all(np.diff(vb.imu.t_ns) > 0)
    assert [f.timestamp_ns for f in vb.frames()] == FRAMES.tolist()
    assert "duplicate" in caplog.text
    # VioBag's own check on the samples
    t = np.repeat(imu_t, 2)
    acc = np.tile([0.1, 0.2, 9.81], (t.size, 1))
    imu, check = validate_imu(t, acc, np.zeros_like(acc), "bag: topic /imu0")
    assert check.duplicates == 401 and len(imu) == 401 and check.out_of_order == 0


def test_vision_contributing_nothing_is_flagged() -> None:
    """A flight whose camera sees nothing (no tracks: e.g. the IMU clock so far off that every
    landmark is gated): IMU dead reckoning, healthy numbers otherwise, but no visual factor for the
    whole run."""
    imu_cfg = ImuConfig(T_sI=default_static_mount())
    truth = simulate_flight(FlightConfig.short(8.0), imu_cfg, seed=0)
    empty = np.zeros(0, dtype=np.int64)
    frames = [TrackFrame(int(t), empty, np.zeros((0, 2))) for t in truth.frame_t_ns]
    tr = truth
    init = InitialState(int(tr.t_ns[0]), tr.T_WI[0], tr.v_W[0], tr.acc_bias[0], tr.gyro_bias[0])
    opts = VioOptions(mode="mono")
    res = run_vio(frames, tr.imu, imu_cfg, None, opts, init)
    report = vio_health(res, imu_cfg, opts)
    assert "vision" in [c.name for c in report.failures], report.failure_text()
    assert res.stats["longest_without_vision_s"] > 7.0


# --------------------------------------------------------------------------- no false alarms
@pytest.mark.slow  # three 10 s tracks-level runs (~10-20 s each)
@pytest.mark.parametrize("mode", ["dcc", "scc", "mono"])
def test_simulated_flights_are_healthy(mode: str) -> None:
    imu_cfg = ImuConfig(T_sI=default_static_mount())
    truth = simulate_flight(FlightConfig.short(10.0), imu_cfg, seed=3)
    pts = World.around(truth.config).sample_points(0.5, np.random.default_rng(103))
    cal = flight_calibration()
    mid = np.asarray(truth.joints.mid, float)
    theta = np.tile(mid, (truth.frame_t_ns.size, 1)) if mode == "scc" else None
    frames = simulate_tracks(truth, pts, cal, imu_cfg.T_sI, 0.5, seed=4, theta=theta, dynamic=mode != "mono")
    tr = truth
    theta0 = tr.theta[0] + 0.03 if mode == "dcc" else np.zeros(0)
    init = InitialState(int(tr.t_ns[0]), tr.T_WI[0], tr.v_W[0], tr.acc_bias[0], tr.gyro_bias[0], theta0)
    opts = VioOptions(mode=mode, sigma=0.5 / 460.0, theta_fixed=tuple(mid) if mode == "scc" else None)
    res = run_vio(frames, tr.imu, imu_cfg, cal, opts, init)
    report = vio_health(res, imu_cfg, opts)
    print(f"\n{mode}: " + "; ".join(c.message for c in report.checks))
    assert report.healthy, report.failure_text()
    assert res.stats["segment_count"] == 1 and res.stats["divergences"] == []


@pytest.mark.slow  # 30 s of real tracks through the smoother (~15-30 s)
def test_eqvio_euroc_tracks_are_healthy() -> None:
    d = load_eqvio_csv()
    opts = VioOptions(mode="mono", sigma=1.0 / d.focal_length)
    res = run_vio(d.frames, d.imu, d.imu_config, None, opts)
    report = vio_health(res, d.imu_config, opts)
    print("\neqvio mono: " + "; ".join(c.message for c in report.checks))
    assert report.healthy, report.failure_text()


def _duplicate_every_message(src: Path, dst: Path) -> None:
    """Copy a ROS2 bag writing every message twice (a recorder or merge fault)."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    with Reader(src) as reader, Writer(dst, version=Writer.VERSION_LATEST) as writer:
        conns = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=store) for c in reader.connections}
        for conn, t, raw in reader.messages():
            writer.write(conns[conn.id], t, raw)
            writer.write(conns[conn.id], t, raw)


@pytest.mark.slow  # packs the MicroEuroc bag and runs the whole VIO twice (~30-60 s)
@pytest.mark.parametrize("mode", ["mono", "dcc"])
def test_euroc_bag_with_duplicated_messages_is_healthy(tmp_path: Path, mode: str) -> None:
    """The real EuRoC images (MicroEuroc, 4.7 s) with every bag message written twice: the
    duplicates are dropped, the trajectory file's stamps increase strictly and the run is healthy."""
    root = shared_data("euroc_v1_01_micro/MicroEurocDataset")
    bag = pack_euroc_bag(root, tmp_path / "euroc", ros=2)
    cal_path = write_euroc_calibration(load_euroc(root), tmp_path / "calibration.yaml")
    doubled = tmp_path / "doubled"
    _duplicate_every_message(bag, doubled)
    cal = load_calibration(cal_path)
    imu = load_imu_config(cal_path)
    assert imu is not None and cal.static_camera is not None
    # the options of ``dcc-fg vio`` (keyframe every 3rd frame, 1 px feature noise)
    opts = VioOptions(mode=mode, keyframe_every=3, sigma=1.0 / float(np.mean(cal.static_camera.intrinsics[:2])))
    res, run = run_vio_bag(doubled, cal, imu, opts)
    out = tmp_path / "out"
    write_vio_outputs(out, res, {"run": run})
    t, T = read_tum(out / "trajectory.tum")
    assert np.all(np.diff(t) > 0) and np.all(np.isfinite(T)) and res.stats["frames"] == 95
    assert res.stats["segment_count"] == 1 and res.stats["failed_updates"] == 0
    report = vio_health(res, imu, opts)
    print(f"\nEuRoC MicroEuroc bag, {mode}: " + "; ".join(c.message for c in report.checks))
    assert report.healthy, report.failure_text()
