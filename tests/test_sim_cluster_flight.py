"""N-camera VIO flights (issue 16 item 3, simulator side): the flight cluster presets, synthetic
tracks of every camera (``TrackFrame.extra``) and ``simulate flight --cluster`` bags.

Frames: ``s`` = cam0, ``T_cs`` maps points of s into camera c, ``I`` body, ``W`` world; ns, m, rad, px.
"""

from __future__ import annotations

from dataclasses import replace
from itertools import islice
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from scipy.stats import chi2

from dcc_fg.cli import main
from dcc_fg.data.cameras import run_cameras
from dcc_fg.data.vio import ImuConfig, TrackFrame, load_imu_config
from dcc_fg.io.bags import BagTopicImages, open_bag, scan_imu_and_image_stamps
from dcc_fg.io.outputs import read_joint_angles_csv
from dcc_fg.model import GimbalCalibration, load_calibration
from dcc_fg.sim.cluster_flight import (
    FLIGHT_PRESETS,
    THERMAL,
    check_flight_cluster,
    flight_cluster,
    further_chain_motions,
)
from dcc_fg.sim.cluster_scene import preset_cluster
from dcc_fg.sim.flight_bag import (
    FRAMES_NAME,
    START_NS,
    camera_frames,
    load_flight_calibration,
    read_frames_csv,
    render_frames,
    scaled_flight_calibration,
    write_flight,
)
from dcc_fg.sim.flight_render import WorldRenderer, planes_from_world
from dcc_fg.sim.timing import CameraTiming
from dcc_fg.sim.trajectory import (
    FlightConfig,
    FlightTruth,
    JointMotion,
    World,
    chain_motion_variant,
    chain_theta_at,
    default_static_mount,
    flight_calibration,
    locked_gimbal,
    simulate_camera_tracks,
    simulate_flight,
    simulate_tracks,
)
from factors import chain

DEG = np.pi / 180.0
DURATION = 4.5  # the shortest flight FlightConfig allows is > 4 s
SIGMA = 0.5  # pixel noise of the synthetic tracks, px
NUDGE = np.eye(4)
NUDGE[:3, :3] = chain.rot_y(0.3 * DEG)


# ------------------------------------------------------------------ presets


def _centre_s(T_cs: np.ndarray) -> np.ndarray:
    """Optical centre of camera c in s (m)."""
    return -T_cs[:3, :3].T @ T_cs[:3, 3]


def _angle(R: np.ndarray) -> float:
    """Rotation angle of R (rad)."""
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def _every_chain(cal: GimbalCalibration, theta: np.ndarray) -> dict[str, np.ndarray]:
    """The same joint angles ``theta`` (rad) on every chain of ``cal``."""
    return {name: theta for name in cal.cluster().chain_names}


def test_presets_keep_the_flight_gimbal_and_place_the_extra_camera() -> None:
    base = flight_calibration()
    thetas = [np.array([90.0, 0.0]) * DEG, np.array([115.0, -20.0]) * DEG, np.array([63.0, 11.0]) * DEG]
    for preset in FLIGHT_PRESETS:
        cal = flight_cluster(preset)
        cluster = cal.cluster()
        chains = ["gimbal", "gimbal2"] if preset == "two-gimbals" else ["gimbal"]
        assert cluster.camera_names == ["cam0", "cam1", "cam2"] and cluster.chain_names == chains
        # the primary chain and gimbal camera are the two-camera flight's, to the bit
        assert np.array_equal(cal.kin, base.kin) and cal.n_joints == 2
        assert cal.static_camera == base.static_camera and cal.dynamic_camera == base.dynamic_camera
        for th in thetas:
            assert np.array_equal(cal.T_ds(th), base.T_ds(th))
        # the layout survives calibration.yaml's cameras:/chains: form
        back = GimbalCalibration.from_dict(yaml.safe_load(yaml.safe_dump(cal.to_dict())))
        for name in cluster.camera_names:
            for th in thetas:
                both = _every_chain(cal, th)
                assert np.allclose(back.T_cs(name, both), cal.T_cs(name, both), atol=1e-12)
            assert back.cluster().camera(name).camera == cluster.camera(name).camera
    stereo = flight_cluster("stereo+gimbal")
    s = stereo.cluster()
    assert s.primary_gimbal_camera == "cam2" and s.camera("cam1").is_static
    T1 = s.T_cs("cam1")
    assert np.allclose(_centre_s(T1), [0.11, 0.0, 0.0], atol=1e-12)
    assert 0.5 * DEG < _angle(T1[:3, :3]) < 5.0 * DEG
    assert s.camera("cam1").camera == s.camera("cam0").camera  # same intrinsics as cam0
    pair = flight_cluster("gimbal-pair")
    p = pair.cluster()
    assert p.primary_gimbal_camera == "cam1" and p.camera("cam2").chain == "gimbal"
    thermal = p.camera("cam2").camera
    assert thermal is not None and thermal.resolution == (640, 480)
    assert thermal.intrinsics[0] < 0.9 * base.dynamic_camera.intrinsics[0]  # type: ignore[union-attr]
    for th in thetas:  # rigid on the chain end: 4 cm beside cam1, a few degrees rotated, at every angle
        T1, T2 = p.T_cs("cam1", th), p.T_cs("cam2", th)
        T21 = T2 @ chain.inv_se3(T1)
        assert np.isclose(np.linalg.norm(_centre_s(T2) - _centre_s(T1)), 0.04, atol=1e-12)
        assert np.allclose(-T21[:3, :3].T @ T21[:3, 3], [0.04, 0.0, 0.0], atol=1e-12)  # along cam1's x axis
        assert 1.0 * DEG < _angle(T21[:3, :3]) < 5.0 * DEG
    # scale: every camera model scaled, the geometry unchanged
    half = flight_cluster("gimbal-pair", 0.5).cluster()
    assert half.camera("cam2").camera.resolution == (320, 240)  # type: ignore[union-attr]
    assert half.camera("cam0").camera == scaled_flight_calibration(0.5).static_camera
    assert np.array_equal(half.T_cs("cam2", thetas[1]), p.T_cs("cam2", thetas[1]))
    with pytest.raises(ValueError, match="presets: stereo\\+gimbal, gimbal-pair, two-gimbals"):
        flight_cluster("three-gimbals")


def test_two_gimbals_preset_mounts_a_second_gimbal_beside_the_first() -> None:
    """cam1 on the flight's gimbal (the primary chain), cam2 the thermal-like camera on gimbal2: the
    same 2-joint mechanism with its base 20 cm to the left; at equal angles cam2 sits 20 cm left of
    cam1 (along -x of s), a few degrees rotated; at the mid angles it looks ahead like cam0."""
    base = flight_calibration()
    cal = flight_cluster("two-gimbals")
    c = cal.cluster()
    assert c.primary_gimbal_camera == "cam1" and c.camera("cam1").chain == "gimbal"
    assert c.camera("cam2").chain == "gimbal2" and c.chain("gimbal2").n_joints == 2
    assert np.array_equal(c.chain("gimbal2").dh, base.dh)
    assert c.camera("cam2").camera == THERMAL
    extra = run_cameras(cal, "dcc")
    assert [(x.name, x.chain, x.slot) for x in extra] == [("cam2", "gimbal2", 1)]
    assert check_flight_cluster(cal)[0].name == "cam2"
    for th in ([90.0, 0.0], [115.0, -20.0], [63.0, 11.0]):
        both = _every_chain(cal, np.array(th) * DEG)
        T1, T2 = c.T_cs("cam1", both), c.T_cs("cam2", both)
        assert np.allclose(_centre_s(T2) - _centre_s(T1), [-0.20, 0.0, 0.0], atol=1e-12)
        assert 1.0 * DEG < _angle(T2[:3, :3] @ T1[:3, :3].T) < 5.0 * DEG
        assert np.allclose(T2, extra[0].T_cs_at(both["gimbal2"]), atol=1e-12)
    mid = c.T_cs("cam2", _every_chain(cal, np.array([90.0, 0.0]) * DEG))
    assert _angle(mid[:3, :3]) < 8.0 * DEG  # optical axis near cam0's: overlapping views


# ------------------------------------------------------------------ synthetic tracks


@pytest.fixture(scope="module")
def flight() -> tuple[FlightTruth, np.ndarray, np.ndarray]:
    cfg = FlightConfig.short(8.0)
    T_sI = default_static_mount()
    motions = further_chain_motions(flight_cluster("two-gimbals"), JointMotion())
    truth = simulate_flight(cfg, ImuConfig(T_sI=T_sI), seed=3, extra_joints=motions)
    landmarks = World.around(cfg).sample_points(0.5, np.random.default_rng(5))
    return truth, landmarks, T_sI


def _normalized(cal: GimbalCalibration, name: str, theta: Any, T_sW: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Undistorted normalized coordinates (N, 2) of the world points P in camera ``name`` (NaN behind);
    ``theta``: joint angles (rad) as :meth:`GimbalCalibration.T_cs` takes them."""
    p = P @ (cal.T_cs(name, theta) @ T_sW)[:3, :3].T + (cal.T_cs(name, theta) @ T_sW)[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(p[:, 2:3] > 0, p[:, :2] / p[:, 2:3], np.nan)


def _observations(frame: TrackFrame, names: dict[int, str]) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(camera name, ids, xy) of every camera of a frame; ``names``: run index -> cluster name."""
    out = [(names[0], frame.static_ids, frame.static_xy), (names[1], frame.dynamic_ids, frame.dynamic_xy)]
    return out + [(names[t.camera], t.ids, t.xy) for t in frame.extra]


@pytest.mark.parametrize("preset", FLIGHT_PRESETS)
def test_cluster_tracks_reproject_with_the_true_geometry(
    preset: str, flight: tuple[FlightTruth, np.ndarray, np.ndarray]
) -> None:
    """Noise-free tracks are the exact projections of one landmark per id (the same landmark in every
    camera and frame: one id space); noisy tracks deviate from them like N(0, SIGMA) pixel noise."""
    truth, P, T_sI = flight
    cal = flight_cluster(preset)
    extra = run_cameras(cal, "dcc")
    assert [c.index for c in extra] == [2]
    names = {0: "cam0", 1: cal.cluster().primary_gimbal_camera, 2: extra[0].name}
    exact = simulate_camera_tracks(truth, P, cal, T_sI, extra, pixel_sigma=0.0)
    noisy = simulate_camera_tracks(truth, P, cal, T_sI, extra, pixel_sigma=SIGMA, seed=7)
    idx = truth.index_of(truth.frame_t_ns)
    landmark_of: dict[int, int] = {}
    seen_in: dict[int, set[int]] = {}  # landmark -> frames in which some camera saw it
    ids_of: dict[tuple[int, int], int] = {}  # (landmark, frame) -> id
    z2: list[float] = []
    n_extra = 0
    for f, (fe, fn) in enumerate(zip(exact, noisy, strict=True)):
        T_sW = T_sI @ chain.inv_se3(truth.T_WI[idx[f]])
        theta = {"gimbal": truth.theta[idx[f]], **{c: th[idx[f]] for c, th in truth.extra_theta.items()}}
        for (name, ids, xy), (_, ids_n, xy_n) in zip(_observations(fe, names), _observations(fn, names), strict=True):
            assert np.array_equal(ids, ids_n)  # visibility and ids do not depend on the noise
            if ids.size == 0:
                continue
            ref = _normalized(cal, name, theta, T_sW, P)
            d = np.linalg.norm(np.nan_to_num(ref, nan=1e9)[None, :, :] - xy[:, None, :], axis=2)
            lm = d.argmin(axis=1)
            assert d[np.arange(lm.size), lm].max() < 1e-12  # an exact projection of a true landmark
            for i, k in zip(ids.tolist(), lm.tolist(), strict=True):
                assert landmark_of.setdefault(i, k) == k  # one landmark per id, in every camera
                assert ids_of.setdefault((k, f), i) == i
                seen_in.setdefault(k, set()).add(f)
            model = cal.cluster().camera(name).camera
            assert model is not None
            r_px = (xy_n - ref[lm]) * np.array(model.intrinsics[:2])
            z2 += list((r_px**2).sum(axis=1) / SIGMA**2)
            n_extra += ids.size if name == names[2] else 0
    assert n_extra > 50 * len(exact)
    # ids are kept while a landmark stays in view of some camera and renewed after a gap
    for k, frames in seen_in.items():
        for f in frames:
            if f + 1 in frames:
                assert ids_of[(k, f)] == ids_of[(k, f + 1)]
            elif f + 2 in frames:
                assert ids_of[(k, f)] != ids_of[(k, f + 2)]
    # pixel residuals: chi-square with 2 degrees of freedom per observation
    z = np.array(z2)
    n = z.size
    assert abs(z.sum() - 2 * n) < 5.0 * np.sqrt(4 * n), (z.sum() / n, n)
    assert z.max() < chi2.isf(1e-6 / n, 2)


def test_cluster_tracks_share_ids_and_keep_the_two_camera_tracks(
    flight: tuple[FlightTruth, np.ndarray, np.ndarray],
) -> None:
    truth, P, T_sI = flight
    cal = flight_cluster("stereo+gimbal")
    extra = run_cameras(cal, "dcc")
    two = simulate_tracks(truth, P, cal, T_sI, seed=4)
    none = simulate_camera_tracks(truth, P, cal, T_sI, (), seed=4)
    many = simulate_camera_tracks(truth, P, cal, T_sI, extra, seed=4)
    shared, seen = 0, 0
    for a, b, c in zip(two, none, many, strict=True):
        # no further camera: simulate_tracks bit for bit
        for field in ("static_ids", "static_xy", "dynamic_ids", "dynamic_xy"):
            assert np.array_equal(getattr(a, field), getattr(b, field))
        assert a.timestamp_ns == b.timestamp_ns and b.extra == ()
        # with the stereo partner: cam0's and the gimbal camera's coordinates are unchanged
        assert np.array_equal(a.static_xy, c.static_xy) and np.array_equal(a.dynamic_xy, c.dynamic_xy)
        (t,) = c.extra
        assert t.camera == 2 and t.xy.shape == (t.ids.size, 2)
        shared += np.intersect1d(c.static_ids, t.ids).size
        seen += t.ids.size
    assert seen > 0 and shared > 0.8 * seen  # a stereo pair 11 cm apart sees mostly the same landmarks
    # the locked-gimbal and mono variants pass through as well
    theta = np.tile(truth.theta[0], (len(truth.frame_t_ns), 1))
    a = simulate_tracks(truth, P, cal, T_sI, seed=2, dynamic=False, theta=theta)
    b = simulate_camera_tracks(truth, P, cal, T_sI, (), seed=2, dynamic=False, theta=theta)
    assert all(np.array_equal(x.static_xy, y.static_xy) and np.array_equal(x.static_ids, y.static_ids)
               for x, y in zip(a, b, strict=True))  # fmt: skip
    with pytest.raises(ValueError, match="distinct"):
        simulate_camera_tracks(truth, P, cal, T_sI, (extra[0], extra[0]))


# ------------------------------------------------------------------ rendered bags


SCALE = 0.5
SEED = 6


@pytest.fixture(scope="module")
def stereo_flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("cluster") / "fl"
    argv = ["simulate", "flight", "--out", str(out), "--duration", str(DURATION), "--scale", str(SCALE)]
    assert main([*argv, "--format", "ros1", "--seed", str(SEED), "--cluster", "stereo+gimbal", "-q"]) == 0
    return out


def _topics(bag: Path) -> set[str]:
    with open_bag(bag) as reader:
        return {c.topic for c in reader.connections}


def test_stereo_gimbal_bag_topics_and_calibration(stereo_flight: Path) -> None:
    out = stereo_flight
    bag = out / "flight.bag"
    images = ["/cam0/image_raw", "/cam1/image_raw", "/cam2/image_raw"]
    assert _topics(bag) == {"/imu0", *images, "/ground_truth/pose", "/ground_truth/joints"}
    scan = scan_imu_and_image_stamps(bag, "/imu0", images)
    truth = simulate_flight(FlightConfig.short(DURATION), seed=SEED)
    expected = list(truth.frame_t_ns + START_NS)
    for topic in images:  # triggered together: the same stamps on every camera
        assert scan.image_stamps[topic] == expected
    assert len(scan.imu_t_ns) == truth.t_ns.size
    # calibration.yaml: the cluster with 3 cameras, T_cs and intrinsics of the preset, the imu: section
    preset = flight_cluster("stereo+gimbal", SCALE)
    cal = load_calibration(out / "calibration.yaml")
    assert cal.camera_names == ["cam0", "cam1", "cam2"] and cal.cluster().primary_gimbal_camera == "cam2"
    for name in cal.camera_names:
        assert cal.cluster().camera(name).camera == preset.cluster().camera(name).camera
        for th in truth.theta[:: len(truth.theta) // 4]:
            assert np.allclose(cal.T_cs(name, th), preset.T_cs(name, th), atol=1e-12)
    imu = load_imu_config(out / "calibration.yaml")
    assert imu is not None and np.allclose(imu.T_sI, default_static_mount(), atol=1e-15)
    cal_f, imu_f = load_flight_calibration(out / "calibration.yaml")  # cam1 is static: the whole cluster
    assert cal_f.camera_names == cal.camera_names and np.array_equal(imu_f.T_sI, imu.T_sI)
    flight_rec = yaml.safe_load((out / "calibration.yaml").read_text())["flight"]
    assert flight_rec["cluster"] == {
        "source": "stereo+gimbal",
        "primary": "cam2",
        "topics": {"cam0": images[0], "cam1": images[1], "cam2": images[2]},
    }
    assert flight_rec["topics"]["static"] == images[0] and flight_rec["topics"]["dynamic"] == images[2]
    # ground truth unchanged: joints of the primary chain at each gimbal image
    t_j, th_j = read_joint_angles_csv(out / "ground_truth_joints.csv")
    assert list(t_j) == expected and np.allclose(th_j, truth.theta[truth.index_of(truth.frame_t_ns)], atol=1e-9)


def _rms(a: Any, b: Any) -> float:
    return float(np.sqrt(np.mean((np.asarray(a, float) - np.asarray(b, float)) ** 2)))


def test_stereo_gimbal_images_show_the_true_poses(stereo_flight: Path) -> None:
    """cam1's images are the world seen from T_cs(cam1) T_sI inv(T_WI) (image noise only, sigma 2),
    clearly unlike cam0's view; cam0's and the gimbal camera's images are exactly those of the
    two-camera flight of the same seed."""
    bag = stereo_flight / "flight.bag"
    config = FlightConfig.short(DURATION)
    truth = simulate_flight(config, seed=SEED)
    renderer = WorldRenderer(planes_from_world(World.around(config)), seed=SEED)
    T_sI = default_static_mount()
    cal = flight_cluster("stereo+gimbal", SCALE)
    cam1 = cal.cluster().camera("cam1").camera
    assert cam1 is not None
    picks = [10, 45, 80]
    got = {t: img for t, img, _ in BagTopicImages(bag, "/cam1/image_raw")}
    for k in picks:
        t = int(truth.frame_t_ns[k])
        T_sW = T_sI @ chain.inv_se3(truth.T_WI[truth.index_of(t)[0]])
        img = got[t + START_NS]
        assert img.shape == (cam1.resolution[1], cam1.resolution[0])
        true_view = renderer.render(cam1, cal.T_cs("cam1") @ T_sW, 0.0)
        cam0_view = renderer.render(cam1, T_sW, 0.0)
        err, wrong = _rms(img, true_view), _rms(img, cam0_view)
        nudged = renderer.render(cam1, NUDGE @ cal.T_cs("cam1") @ T_sW, 0.0)  # a 0.3 deg error of T_cs
        assert err < 2.3 and wrong > 10.0 * err and _rms(img, nudged) > 5.0 * err, (k, err, wrong)
    # cam0 and the primary gimbal camera: the first images equal the two-camera flight's
    frames = camera_frames(truth, CameraTiming(), SEED)[:6]  # cam0, gimbal, cam0, gimbal, ...
    ref: dict[int, list[np.ndarray]] = {0: [], 1: []}
    for f, img in zip(frames, render_frames(renderer, frames, scaled_flight_calibration(SCALE), T_sI, 2.0,
                                            seed=SEED + 1), strict=True):  # fmt: skip
        ref[f.camera].append(img)
    for camera, topic in ((0, "/cam0/image_raw"), (1, "/cam2/image_raw")):
        got_first = [img for _, img, _ in islice(BagTopicImages(bag, topic), 3)]
        assert len(got_first) == len(ref[camera]) == 3
        assert all(np.array_equal(a, b) for a, b in zip(got_first, ref[camera], strict=True))


def _save(cal: GimbalCalibration, path: Path) -> Path:
    path.write_text(yaml.safe_dump(cal.to_dict(), sort_keys=False))
    return path


def test_gimbal_pair_file_with_unsynchronized_timing(tmp_path: Path) -> None:
    """A cluster file (here the gimbal-pair preset saved) with other rates for the gimbal camera: the
    second gimbal camera follows cam0's exposures and stamps, its image is the true view at the joint
    angles of cam0's exposure; ground_truth_frames.csv lists cam0 and the primary gimbal camera only."""
    cluster_file = _save(flight_cluster("gimbal-pair"), tmp_path / "pair.yaml")
    out = tmp_path / "fl"
    scale = 0.2
    timing = CameraTiming((20.0, 30.0), 0.0, (0.0, 0.01))
    res = write_flight(out, "ros2", FlightConfig.short(DURATION), seed=1, scale=scale, timing=timing,
                       cluster=cluster_file)  # fmt: skip
    topics = ["/cam0/image_raw", "/cam1/image_raw", "/cam2/image_raw"]
    assert res.topics == tuple(topics) and res.cluster is not None
    scan = scan_imu_and_image_stamps(out / "flight", "/imu0", topics)
    assert scan.image_stamps[topics[2]] == scan.image_stamps[topics[0]]
    assert len(scan.image_stamps[topics[1]]) == res.images[1] > 1.4 * res.images[0] == 1.4 * res.images[2]
    frames = read_frames_csv(out / FRAMES_NAME)
    assert set(frames["camera"].tolist()) == {0, 1}
    cal = load_calibration(out / "calibration.yaml")
    thermal = cal.cluster().camera("cam2").camera
    assert thermal is not None and thermal.resolution == (128, 96)
    renderer = WorldRenderer(planes_from_world(World.around(res.truth.config)), seed=1)
    T_sI = default_static_mount()
    static = frames["camera"] == 0
    imgs = list(BagTopicImages(out / "flight", topics[2]))
    for k in (20, 60):
        stamp, img, _ = imgs[k]
        assert stamp == frames["stamp_ns"][static][k]
        T_WI, theta = frames["T_WI"][static][k], frames["theta"][static][k]
        T_sW = T_sI @ chain.inv_se3(T_WI)
        err = _rms(img, renderer.render(thermal, cal.T_cs("cam2", theta) @ T_sW, 0.0))
        wrong = _rms(img, renderer.render(thermal, cal.T_cs("cam1", theta) @ T_sW, 0.0))
        assert err < 2.3 and wrong > 10.0 * err, (k, err, wrong)


def test_bad_cluster_arguments(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["simulate", "flight", "--out", str(tmp_path / "fl"), "--duration", str(DURATION), "--scale", "0.1", "-q"]
    assert main([*argv, "--cluster", "stereo"]) == 2
    err = capsys.readouterr().err
    assert "--cluster" in err and "stereo+gimbal" in err and "gimbal-pair" in err
    # a second chain with joints is flown now, if it has the flight gimbal's 2 joints
    two_gimbals, _ = preset_cluster("two-gimbals")
    cal2 = GimbalCalibration.from_cluster(two_gimbals)
    assert [c.name for c in check_flight_cluster(cal2)] == ["cam2"]
    one = two_gimbals.chain("gimbal2")
    short2 = type(two_gimbals)(two_gimbals.cameras, (two_gimbals.chains[0], type(one)(one.name, one.tau_s, one.dh[:1])))
    path = _save(GimbalCalibration.from_cluster(short2), tmp_path / "two.yaml")
    assert main([*argv, "--cluster", str(path)]) == 2
    err = capsys.readouterr().err
    assert "--cluster" in err and "cam2" in err and "second chain 'gimbal2'" in err and "1 joint(s)" in err
    # a camera may not take a further chain's truth topic
    tg = flight_cluster("two-gimbals").cluster()
    clash2 = type(tg)((*tg.cameras[:2], replace(tg.cameras[2], rostopic="/ground_truth/joints_gimbal2")), tg.chains)
    path = _save(GimbalCalibration.from_cluster(clash2), tmp_path / "clash2.yaml")
    assert main([*argv, "--cluster", str(path)]) == 2
    assert "image topic of its own" in capsys.readouterr().err
    one_joint = flight_cluster("gimbal-pair").cluster()
    ch = one_joint.chains[0]
    short = type(one_joint)(one_joint.cameras, (type(ch)(ch.name, ch.tau_s, ch.dh[:1]),))
    path = _save(GimbalCalibration.from_cluster(short), tmp_path / "one.yaml")
    assert main([*argv, "--cluster", str(path)]) == 2
    assert "has 1 joint(s)" in capsys.readouterr().err
    pair = flight_cluster("gimbal-pair").cluster()
    clash = type(pair)((*pair.cameras[:2], replace(pair.cameras[2], rostopic="/cam1/image_raw")), pair.chains)
    path = _save(GimbalCalibration.from_cluster(clash), tmp_path / "clash.yaml")
    assert main([*argv, "--cluster", str(path)]) == 2
    assert "image topic of its own" in capsys.readouterr().err
    assert not (tmp_path / "fl").exists()


# ------------------------------------------------------------------ two gimbals: a second chain on its own


def test_second_chain_moves_on_its_own(flight: tuple[FlightTruth, np.ndarray, np.ndarray]) -> None:
    """gimbal2's angles (FlightTruth.extra_theta) move, differ from the primary chain's, stay in the
    primary's range and rate limit; everything else of the flight is unchanged, bit for bit."""
    truth, _, _ = flight
    assert list(truth.extra_theta) == ["gimbal2"] and list(truth.extra_joints) == ["gimbal2"]
    th1, th2 = truth.theta, truth.chain_theta("gimbal2")
    assert th2.shape == th1.shape == (truth.t_ns.size, 2)
    assert np.all(np.ptp(th2, axis=0) > 5.0 * DEG)  # it moves (sinusoids here; it slews from 8 s on)
    assert np.abs(th2 - th1).max(axis=0).min() > 10.0 * DEG  # on its own
    assert np.corrcoef(th1[:, 0], th2[:, 0])[0, 1] < 0.9
    motion = JointMotion()
    assert truth.extra_joints["gimbal2"] == chain_motion_variant(motion, 1) != motion
    bound = motion.slew_amplitude + motion.sin_amplitude + 1e-9
    assert np.all(np.abs(th2 - np.array(motion.mid)) <= bound)
    rate = np.abs(np.diff(th2, axis=0)) / np.diff(truth.t_ns / 1e9)[:, None]
    assert rate.max() <= motion.max_rate * 1.001
    # the whole flight (more slews): chain 2 slews while chain 1 holds still
    long = simulate_flight(FlightConfig.short(30.0), seed=3, extra_joints={"gimbal2": chain_motion_variant(motion, 1)})
    windows1 = motion.slew_windows(30.0)
    windows2 = long.extra_joints["gimbal2"].slew_windows(30.0)
    assert len(windows2) >= 4
    assert all(b1 <= a2 or b2 <= a1 for _, a1, b1 in windows1 for _, a2, b2 in windows2)
    # no extra chain: the same flight, bit for bit
    plain = simulate_flight(truth.config, ImuConfig(T_sI=default_static_mount()), seed=3)
    assert plain.extra_theta == {} and plain.extra_joints == {}
    for name in ("t_ns", "T_WI", "v_W", "acc_bias", "gyro_bias", "theta", "frame_t_ns"):
        assert np.array_equal(getattr(plain, name), getattr(truth, name))
    assert np.array_equal(plain.imu.acc, truth.imu.acc) and np.array_equal(plain.imu.gyro, truth.imu.gyro)
    # chain_theta_at: the samples at IMU times, the analytic motion between them
    t = np.array([truth.t_ns[3], truth.t_ns[3] + 1_234_567, truth.t_ns[-1]])
    at = chain_theta_at(truth, t)
    assert np.array_equal(at["gimbal2"][[0, 2]], th2[[3, -1]])
    assert np.allclose(at["gimbal2"][1], truth.extra_joints["gimbal2"].evaluate(t[1] / 1e9)[0][0], atol=1e-15)
    assert chain_theta_at(plain, t) == {}
    # a locked gimbal's variant is locked as well
    locked = chain_motion_variant(locked_gimbal(), 1).evaluate(np.linspace(0.0, 30.0, 301), 30.0)[0]
    assert np.ptp(locked, axis=0).max() == 0.0
    with pytest.raises(ValueError, match="does not move chain 'gimbal3'"):
        truth.chain_theta("gimbal3")


def test_two_gimbals_tracks_follow_the_second_chain(flight: tuple[FlightTruth, np.ndarray, np.ndarray]) -> None:
    """cam2's noise-free tracks are projections at T_cs(cam2, gimbal2's true angles), not at the
    primary chain's angles (nor at an overriding primary ``theta``); a flight that does not move
    gimbal2 is refused."""
    truth, P, T_sI = flight
    cal = flight_cluster("two-gimbals")
    extra = run_cameras(cal, "dcc")
    idx = truth.index_of(truth.frame_t_ns)
    locked = np.tile(truth.theta[0], (idx.size, 1))  # overrides the primary chain only
    exact = simulate_camera_tracks(truth, P, cal, T_sI, extra, pixel_sigma=0.0, theta=locked)
    worst_true, worst_primary, n = 0.0, 0.0, 0
    for f, frame in enumerate(exact):
        (t2,) = frame.extra
        if t2.ids.size == 0:
            continue
        T_sW = T_sI @ chain.inv_se3(truth.T_WI[idx[f]])
        p = P @ T_sW[:3, :3].T + T_sW[:3, 3]
        for th, label in ((truth.extra_theta["gimbal2"][idx[f]], "true"), (truth.theta[idx[f]], "primary")):
            p_c = p @ extra[0].T_cs_at(th)[:3, :3].T + extra[0].T_cs_at(th)[:3, 3]
            with np.errstate(divide="ignore", invalid="ignore"):
                xy = np.where(p_c[:, 2:3] > 0, p_c[:, :2] / p_c[:, 2:3], np.nan)
            d = np.nan_to_num(np.linalg.norm(xy[None] - t2.xy[:, None], axis=2), nan=1e9).min(axis=1)
            px = float(d.max()) * THERMAL.intrinsics[0]
            if label == "true":
                worst_true = max(worst_true, px)
            else:
                worst_primary = max(worst_primary, px)
        n += t2.ids.size
    assert n > 50 * len(exact)
    assert worst_true < 1e-8 and worst_primary > 20.0, (worst_true, worst_primary)
    still = simulate_flight(truth.config, seed=3)
    with pytest.raises(ValueError, match="does not move chain 'gimbal2'"):
        simulate_camera_tracks(still, P, cal, T_sI, extra)


@pytest.fixture(scope="module")
def two_gimbals_flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("two") / "fl"
    argv = ["simulate", "flight", "--out", str(out), "--duration", str(DURATION), "--scale", "0.25"]
    assert main([*argv, "--format", "ros2", "--seed", str(SEED), "--cluster", "two-gimbals", "-q"]) == 0
    return out


def _joint_messages(bag: Path, topic: str) -> tuple[np.ndarray, np.ndarray]:
    """Header stamps (ns) and positions (N, L) of a JointState topic."""
    stamps, rows = [], []
    with open_bag(bag) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            stamps.append(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
            rows.append(list(msg.position))
    return np.array(stamps, dtype=np.int64), np.array(rows)


def test_two_gimbals_bag_truth_and_images(two_gimbals_flight: Path) -> None:
    """``simulate flight --cluster two-gimbals``: the images of three cameras, the primary truth as
    without the cluster, gimbal2's truth on /ground_truth/joints_gimbal2 (IMU rate) and in
    ground_truth_joints_gimbal2.csv (per cam2 image) consistent with each other and the simulation,
    cam2's images the true view at gimbal2's angles, cam0's and cam1's the two-camera flight's."""
    out = two_gimbals_flight
    bag = out / "flight"
    images = ["/cam0/image_raw", "/cam1/image_raw", "/cam2/image_raw"]
    joints2 = "/ground_truth/joints_gimbal2"
    assert _topics(bag) == {"/imu0", *images, "/ground_truth/pose", "/ground_truth/joints", joints2}
    config = FlightConfig.short(DURATION)
    cal = flight_cluster("two-gimbals", 0.25)
    truth = simulate_flight(config, seed=SEED, extra_joints=further_chain_motions(cal, JointMotion()))
    scan = scan_imu_and_image_stamps(bag, "/imu0", images)
    expected = list(truth.frame_t_ns + START_NS)
    assert all(scan.image_stamps[t] == expected for t in images)
    # the truth topic: gimbal2's angles at every IMU sample
    t_b, th_b = _joint_messages(bag, joints2)
    assert np.array_equal(t_b, truth.t_ns + START_NS)
    assert np.allclose(th_b, truth.extra_theta["gimbal2"], atol=1e-12)
    t_p, th_p = _joint_messages(bag, "/ground_truth/joints")
    assert np.array_equal(t_p, t_b) and np.allclose(th_p, truth.theta, atol=1e-12)
    # the CSV: one row per cam2 image (its header stamp), the angles the topic carries at that time
    t_c, th_c = read_joint_angles_csv(out / "ground_truth_joints_gimbal2.csv")
    assert list(t_c) == scan.image_stamps["/cam2/image_raw"]
    rows = np.searchsorted(t_b, t_c)
    assert np.array_equal(t_b[rows], t_c) and np.allclose(th_c, th_b[rows], atol=1e-9)
    t_j, th_j = read_joint_angles_csv(out / "ground_truth_joints.csv")  # the primary chain's, unchanged
    assert list(t_j) == expected and np.allclose(th_j, truth.theta[truth.index_of(truth.frame_t_ns)], atol=1e-9)
    assert (out / "ground_truth_joints.csv").read_text().splitlines()[0] == (
        (out / "ground_truth_joints_gimbal2.csv").read_text().splitlines()[0]
    )
    # calibration.yaml: both chains, and the further chain's truth listed in flight.cluster
    back = load_calibration(out / "calibration.yaml")
    assert back.cluster().chain_names == ["gimbal", "gimbal2"]
    th = {"gimbal": truth.theta[40], "gimbal2": truth.extra_theta["gimbal2"][40]}
    assert np.allclose(back.T_cs("cam2", th), cal.T_cs("cam2", th), atol=1e-12)
    rec = yaml.safe_load((out / "calibration.yaml").read_text())["flight"]
    assert rec["gimbal"] == "moving" and rec["cluster"]["primary"] == "cam1"
    assert rec["cluster"]["chains"] == {
        "gimbal2": {
            "camera": "cam2",
            "joints_topic": joints2,
            "joints_file": "ground_truth_joints_gimbal2.csv",
            "gimbal": "moving",
        }
    }
    # cam2's images: the world from T_cs(cam2, gimbal2's angles), not from the primary chain's angles
    renderer = WorldRenderer(planes_from_world(World.around(config)), seed=SEED)
    T_sI = default_static_mount()
    thermal = cal.cluster().camera("cam2").camera
    assert thermal is not None
    got = {t: img for t, img, _ in BagTopicImages(bag, "/cam2/image_raw")}
    run2 = run_cameras(cal, "dcc")[0]
    for k in (10, 45, 80):
        i = truth.index_of(truth.frame_t_ns[k])[0]
        T_sW = T_sI @ chain.inv_se3(truth.T_WI[i])
        img = got[int(truth.frame_t_ns[k]) + START_NS]
        T_true = run2.T_cs_at(th_c[k])
        err = _rms(img, renderer.render(thermal, T_true @ T_sW, 0.0))
        wrong = _rms(img, renderer.render(thermal, run2.T_cs_at(truth.theta[i]) @ T_sW, 0.0))
        nudged = _rms(img, renderer.render(thermal, NUDGE @ T_true @ T_sW, 0.0))
        assert err < 2.3 and wrong > 10.0 * err and nudged > 5.0 * err, (k, err, wrong, nudged)
    # cam0 and the primary gimbal camera: the first images equal the two-camera flight's
    frames = camera_frames(truth, CameraTiming(), SEED)[:6]
    ref: dict[int, list[np.ndarray]] = {0: [], 1: []}
    for f, img in zip(frames, render_frames(renderer, frames, scaled_flight_calibration(0.25), T_sI, 2.0,
                                            seed=SEED + 1), strict=True):  # fmt: skip
        ref[f.camera].append(img)
    for camera, topic in ((0, images[0]), (1, images[1])):
        got_first = [img for _, img, _ in islice(BagTopicImages(bag, topic), 3)]
        assert all(np.array_equal(a, b) for a, b in zip(got_first, ref[camera], strict=True))


def test_two_gimbals_cam2_sees_the_world_through_the_whole_flight() -> None:
    """Over the paper's 90 s flight (all slews of both chains) cam2 keeps seeing many landmarks, about
    as many as the primary gimbal camera, most of them also seen by cam0 (overlapping views)."""
    config = FlightConfig()
    cal = flight_cluster("two-gimbals")
    T_sI = default_static_mount()
    motions = further_chain_motions(cal, JointMotion())
    truth = simulate_flight(config, ImuConfig(T_sI=T_sI), seed=2, extra_joints=motions)
    P = World.around(config).sample_points(0.3, np.random.default_rng(2))
    frames = simulate_camera_tracks(truth, P, cal, T_sI, run_cameras(cal, "dcc"), seed=2)
    seen = np.array([f.extra[0].ids.size for f in frames])
    primary = np.array([f.dynamic_ids.size for f in frames])
    shared = np.array([np.intersect1d(f.extra[0].ids, f.static_ids).size for f in frames])
    assert seen.min() >= 8 and np.median(seen) > 0.5 * np.median(primary), (seen.min(), np.median(primary))
    assert shared.sum() > 0.6 * seen.sum()


def test_two_gimbals_unsynchronized_and_locked(tmp_path: Path) -> None:
    """Unsynchronized timing: cam2 follows cam0's exposures and stamps, and gimbal2's CSV holds its
    angles at cam0's true exposure times (between IMU samples: the analytic motion), keyed by cam0's
    stamps. A locked flight locks every chain (flight.cluster.chains.gimbal2.gimbal: locked)."""
    timing = CameraTiming((23.0, 30.0), 0.0, (0.004, 0.01), 0.0005)
    res = write_flight(tmp_path / "fl", "ros1", FlightConfig.short(DURATION), seed=2, scale=0.1, timing=timing,
                       cluster="two-gimbals")  # fmt: skip
    assert list(res.chain_joints) == ["gimbal2"]
    frames = read_frames_csv(tmp_path / "fl" / FRAMES_NAME)
    static = frames["camera"] == 0
    t_c, th_c = read_joint_angles_csv(res.chain_joints["gimbal2"])
    assert np.array_equal(t_c, frames["stamp_ns"][static])
    exposure = frames["exposure_ns"][static] - START_NS
    assert np.any(~np.isin(exposure, res.truth.t_ns))  # exposures between IMU samples
    assert np.allclose(th_c, chain_theta_at(res.truth, exposure)["gimbal2"], atol=1e-9)
    res_l = write_flight(tmp_path / "locked", "ros2", FlightConfig.short(DURATION), seed=2, scale=0.1,
                         joints=locked_gimbal(), cluster="two-gimbals")  # fmt: skip
    th_l = res_l.truth.extra_theta["gimbal2"]
    assert np.ptp(th_l, axis=0).max() == 0.0 and np.array_equal(th_l[0], locked_gimbal().mid)
    rec = yaml.safe_load(res_l.calibration.read_text())["flight"]
    assert rec["gimbal"] == "locked" and rec["cluster"]["chains"]["gimbal2"]["gimbal"] == "locked"
    with pytest.raises(ValueError, match="not a further chain"):
        write_flight(tmp_path / "bad", cluster="two-gimbals", extra_joints={"gimbal": JointMotion()})
    with pytest.raises(ValueError, match="need a cluster"):
        write_flight(tmp_path / "bad", extra_joints={"gimbal2": JointMotion()})
