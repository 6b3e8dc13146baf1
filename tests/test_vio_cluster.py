"""N-camera VIO: which cameras a run uses, their factors' frames, stereo landmarks, and the accuracy of the
whole cluster against the two-camera run of the same flight (tracks level; rendered bags in
tests/test_bench_vio_cluster.py, real EuRoC stereo in tests/test_vio_euroc.py).

The comparisons run the same simulated flight twice: every camera of the cluster, and cam0 + the gimbal
camera only. The simulator gives cam0 and the gimbal camera the same noisy coordinates in both runs
(the further cameras draw from their own generator), so the difference is the further camera's data.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import gtsam
import numpy as np
import pytest
import yaml

from dcc_fg.cli import main
from dcc_fg.data.cameras import run_cameras, run_chains
from dcc_fg.data.vio import CameraTracks, ImuConfig, TrackFrame
from dcc_fg.io.bag_writer import BagWriter
from dcc_fg.model import GimbalCalibration
from dcc_fg.sim.cluster_flight import flight_cluster
from dcc_fg.sim.cluster_scene import preset_cluster
from dcc_fg.sim.trajectory import default_static_mount, simulate_camera_tracks
from dcc_fg.sources.vio_bag import VioBag
from dcc_fg.studies.vio_study import StudyConfig, _study_inputs, run_mode
from dcc_fg.vio.backend import InitialState, VioOptions, run_vio
from dcc_fg.vio.backend.cameras import CameraRig
from dcc_fg.vio.backend.keys import (
    chain_theta_key,
    extra_camera_key,
    landmark_key,
    pose_key,
    static_camera_key,
    theta_key,
)
from dcc_fg.vio.backend.landmarks import LandmarkMap, validate_frames
from dcc_fg.vio.health import vio_health
from dcc_fg.vio.pipeline import PipelineOptions, check_further_sync
from factors import chain


# ----------------------------------------------------------------------------- which cameras
@pytest.mark.parametrize(
    ("preset", "mode", "expected"),
    [
        ("stereo+gimbal", "mono", {"cam1": False}),
        ("stereo+gimbal", "scc", {"cam1": False}),
        ("stereo+gimbal", "dcc", {"cam1": False}),
        ("gimbal-pair", "mono", {}),
        ("gimbal-pair", "scc", {"cam2": False}),  # locked: rigid at the locked angles
        ("gimbal-pair", "dcc", {"cam2": True}),
        ("two-gimbals", "scc", {}),  # cam2 is on a second chain, which scc does not lock: left out
        ("two-gimbals", "dcc", {"cam2": True}),  # its own joint-angle state (slot 1)
    ],
)
def test_run_cameras_roles(preset: str, mode: str, expected: dict[str, bool]) -> None:
    cal = GimbalCalibration.from_cluster(preset_cluster(preset)[0])
    theta = np.array([1.4, 0.2])
    cams = run_cameras(cal, mode, theta if mode == "scc" else None)
    assert {c.name: c.on_gimbal for c in cams} == expected
    assert [c.index for c in cams] == list(range(2, 2 + len(cams)))
    for c in cams:  # every camera's pose relative to cam0 is the cluster's at its chain's angles
        chain_theta = {ch: theta for ch in cal.cluster().chain_names}
        assert np.allclose(c.T_cs_at(theta), cal.T_cs(c.name, chain_theta), atol=1e-12)


def test_run_cameras_refuses_by_name() -> None:
    cal = GimbalCalibration.from_cluster(preset_cluster("two-gimbals")[0])
    with pytest.raises(ValueError, match="cam2 cannot be used in scc mode: it is on chain 'gimbal2'"):
        run_cameras(cal, "scc", np.zeros(2), use=["cam2"])
    (cam2,) = run_cameras(cal, "dcc")
    assert cam2.chain == "gimbal2" and cam2.slot == 1 and run_chains(cal, "dcc") == ("gimbal", "gimbal2")
    assert run_chains(cal, "dcc", use=[]) == ("gimbal",) and run_chains(cal, "mono") == ()
    with pytest.raises(ValueError, match="no camera cam7"):
        run_cameras(cal, "dcc", use=["cam7"])
    pair = GimbalCalibration.from_cluster(preset_cluster("gimbal-pair")[0])
    with pytest.raises(ValueError, match="cam2 cannot be used in mono mode"):
        run_cameras(pair, "mono", use=["cam2"])
    assert run_cameras(pair, "dcc", use=[]) == ()


# ----------------------------------------------------------------------------- factors at the truth
def _rig_and_truth(mode_timing: str) -> tuple[CameraRig, gtsam.Values, Any, dict[str, Any]]:
    cal = flight_cluster("gimbal-pair")
    stereo = flight_cluster("stereo+gimbal")
    (second,) = run_cameras(flight_cluster("two-gimbals"), "dcc")  # cam2 on chain gimbal2, slot 1
    T_sI = default_static_mount()
    cams = (
        run_cameras(cal, "dcc")
        + tuple(dataclasses.replace(c, index=3) for c in run_cameras(stereo, "dcc"))
        + (dataclasses.replace(second, index=4),)
    )
    rig = CameraRig(cal, T_sI, VioOptions(mode="dcc", sigma=1e-3), cams)
    rng = np.random.default_rng(4)
    T_WI = chain.se3_from_tau(np.r_[rng.uniform(-0.3, 0.3, 3), rng.uniform(-2, 2, 3)])
    theta = np.array([1.5, 0.1])
    theta2 = np.array([1.7, -0.15])  # the second chain's angles
    shift = gtsam.Pose3(chain.se3_from_tau(np.r_[0.01, -0.02, 0.015, 0.003, 0.001, -0.002]))
    T_Is = chain.inv_se3(T_sI)
    T_Ws = T_WI @ (shift.matrix() if mode_timing == "shifted" else T_Is)
    if mode_timing == "timed":  # the static image's own exposure-time pose
        T_Ws = T_WI @ T_Is @ chain.se3_from_tau(np.r_[0.02, 0.0, -0.01, 0.01, 0.0, 0.02])
    values = gtsam.Values()
    values.insert(pose_key(0), gtsam.Pose3(T_WI))
    values.insert(static_camera_key(0), gtsam.Pose3(T_Ws))
    values.insert(theta_key(0), theta)
    values.insert(chain_theta_key(0, 1), theta2)
    graph = gtsam.NonlinearFactorGraph()
    stamps: dict[int, int] = {}
    static = (mode_timing == "timed", shift if mode_timing == "shifted" else None)
    rig.add_extra_camera_poses(0, 0, T_Ws, lambda slot: theta2 if slot else theta, *static, graph, values, stamps)
    truth = {"T_Ws": T_Ws, "theta": {0: theta, 1: theta2}, "static": static, "cams": cams}
    return rig, values, graph, truth


@pytest.mark.parametrize("timing", ["keyframe", "shifted", "timed"])
@pytest.mark.parametrize("gimbal_factor", ["camera_pose", "eq14"])
def test_extra_camera_factors_vanish_at_the_truth(timing: str, gimbal_factor: str) -> None:
    """A landmark seen by a rigid further camera, a camera on the primary gimbal and one on a second gimbal
    (its own angles), the static image at the keyframe time, shifted by a known offset, or with its own
    exposure pose: every factor (and the ties of the auxiliary poses e(k)) is zero at the true values, and
    each auxiliary pose starts at the camera's true pose T_Ws T_sc(theta of its chain). A wrong frame or
    chain anywhere (T_cs vs T_sc, T_sI vs the shift, t(k) vs u(k)) breaks this."""
    rig, values, ties, truth = _rig_and_truth(timing)
    rig.opt = VioOptions(mode="dcc", sigma=1e-3, gimbal_factor=gimbal_factor)
    for cam in truth["cams"]:
        T_Wc = truth["T_Ws"] @ chain.inv_se3(cam.T_cs_at(truth["theta"][cam.slot]))
        if cam.on_gimbal:
            assert np.allclose(values.atPose3(extra_camera_key(0, cam.index)).matrix(), T_Wc, atol=1e-12)
        for j, p_c in enumerate(([0.3, -0.2, 4.0], [-1.0, 0.5, 9.0])):
            lm = 10 * cam.index + j
            values.insert(landmark_key(lm), T_Wc[:3, :3] @ np.array(p_c) + T_Wc[:3, 3])
            z = np.array(p_c[:2]) / p_c[2]
            f = rig.extra_factor(0, cam.index, lm, z, *truth["static"])
            assert f.error(values) < 1e-18, (cam.name, timing, f.error(values))
            f_off = rig.extra_factor(0, cam.index, lm, z + 1e-3, *truth["static"])
            assert f_off.error(values) > 1e-2  # one sigma away: the factor sees it
    assert ties.size() == 2 and ties.error(values) < 1e-16


def test_stereo_track_is_ready_in_its_first_keyframe() -> None:
    """Two rigid cameras seeing a track in one keyframe make it a landmark at once (metric from the
    baseline); cam0 + the gimbal camera (run index 1) wait for min_track_keyframes as before."""
    opts = VioOptions(min_track_keyframes=3, min_parallax_deg=0.5)
    lms = LandmarkMap(frozenset({0, 2}))
    T_W0 = np.eye(4)
    T_W2 = np.eye(4)
    T_W2[0, 3] = 0.2  # 20 cm to the right
    p = np.array([0.4, -0.3, 6.0])
    for cam, T in ((0, T_W0), (2, T_W2), (1, T_W2)):
        q = p - T[:3, 3]
        lms.buffer({0: 7, 2: 7, 1: 8}[cam], 0, cam, q[:2] / q[2])
    q = p - T_W0[:3, 3]
    lms.buffer(8, 0, 0, q[:2] / q[2])
    poses = {0: T_W0, 2: T_W2, 1: T_W2}
    made = lms.triangulate_ready(0, 0, {0: 0}, 0, lambda k, cam: poses[cam], opts)
    assert [m.index for m in made] == [0] and lms.active == {7: 0}
    assert np.allclose(made[0].p_W, p, atol=1e-9)


def test_frames_with_extra_tracks_are_validated() -> None:
    bad = TrackFrame(
        0, np.zeros(0, np.int64), np.zeros((0, 2)), extra=(CameraTracks(2, np.arange(3), np.zeros((2, 2))),)
    )
    with pytest.raises(ValueError, match="camera 2: 3 ids but xy has shape"):
        validate_frames([bad])


# ----------------------------------------------------------------------------- accuracy, tracks level
SEEDS = (0, 1, 2)


# Both runs at the settings the cluster's default resolves to (further cameras: every landmark
# persistent, 1.5 s). Left to the default, the two-camera run (synchronized) resolves to no persistent
# landmark and 2.5 s, and the comparison would mix two changes: the CI run that did so measured
# stereo+gimbal translation ratios up to 1.26 (mean 0.89).
EQUAL_SETTINGS: dict[str, Any] = {"persistent_landmarks": "all", "lag": 1.5}


def _pair_runs(preset: str, seed: int, duration: float = 15.0) -> tuple[dict[str, Any], dict[str, Any]]:
    cfg = StudyConfig(duration=duration, density=0.5, pixel_sigma=0.5, seed=seed)
    return (
        run_mode("dcc", cfg, EQUAL_SETTINGS, preset=preset),
        run_mode("dcc", cfg, EQUAL_SETTINGS, preset=preset, cameras=()),
    )


def test_short_stereo_gimbal_run_uses_every_camera() -> None:
    every, two = _pair_runs("stereo+gimbal", 5, duration=10.0)
    r = every["result"]
    assert r.stats["failed_updates"] == 0 and r.stats["extra_obs"]["cam1"] > 1000
    assert two["result"].stats["extra_obs"] == {}
    assert max(every["joint_rmse_rad"]) <= 1e-2


@pytest.mark.slow
@pytest.mark.parametrize("preset", ["stereo+gimbal", "gimbal-pair"])
def test_cluster_no_worse_than_two_cameras(preset: str) -> None:
    """Over seeds (landmarks, IMU and pixel noise): the whole cluster's normalized translation RMSE is at
    most the two-camera run's on average and in every run within 10 %; joint RMSE <= 1e-2 rad, and with a
    second camera on the gimbal no worse than with one. Measured (15 s flights, seeds 0-2): stereo+gimbal
    translation ratios 0.73-0.96, joint ratios 0.06-0.07 (the stereo pair's metric landmarks remove the
    depth error that dominates the joint error); gimbal-pair translation 0.66-0.96, joint 0.997-1.023 (the
    second camera, 4 cm from the first, adds little on the joints: the ratio scatters around 1 by ~2 %
    from seed to seed, hence the 5 % allowance on its mean)."""
    t_ratio, j_ratio = [], []
    for seed in SEEDS:
        every, two = _pair_runs(preset, seed)
        assert every["failed_updates"] == 0 and two["failed_updates"] == 0
        assert max(every["joint_rmse_rad"]) <= 1e-2
        t_ratio.append(every["normalized_translation_rmse_percent"] / two["normalized_translation_rmse_percent"])
        j_ratio.append(np.mean(np.array(every["joint_rmse_rad"]) / np.array(two["joint_rmse_rad"])))
    print(f"\n{preset}: translation RMSE ratios {np.round(t_ratio, 3)}, joint RMSE ratios {np.round(j_ratio, 3)}")
    assert np.mean(t_ratio) <= 1.0 and max(t_ratio) <= 1.1
    assert np.mean(j_ratio) <= (0.5 if preset == "stereo+gimbal" else 1.05)


def test_vio_cli_refuses_unknown_camera(tmp_path: Any, capsys: pytest.CaptureFixture[str]) -> None:
    cal = tmp_path / "calibration.yaml"
    d = {**flight_cluster("stereo+gimbal").to_dict(), "imu": ImuConfig(T_sI=default_static_mount()).to_dict()}
    cal.write_text(yaml.safe_dump(d))
    bag = tmp_path / "bag"
    bag.mkdir()
    rc = main(["vio", str(bag), "--calibration", str(cal), "--cameras", "cam5", "--out", str(tmp_path / "o")])
    assert rc == 2
    assert "no camera cam5" in capsys.readouterr().err


@pytest.mark.slow
def test_two_gimbals_each_chain_followed() -> None:
    """Two gimbals moving on their own (cam1 on the primary chain, cam2 on gimbal2 with its own joint-angle
    state): the second chain's joint RMSE <= 1e-2 rad on every seed, the primary chain's no worse than
    without the second gimbal camera (mean ratio <= 1.05, as for the gimbal pair), and the trajectory
    within 25 % of the two-camera run's (the second gimbal adds landmarks, but its camera's joint angles are
    estimated along with them). Measured (15 s, seeds 0-2): gimbal2 1.4-1.5e-3 / 5.3-5.5e-4 rad, translation
    ratios 1.13, 0.96, 0.67, primary joint ratios 1.00."""
    t_ratio, j_ratio = [], []
    for seed in SEEDS:
        every, two = _pair_runs("two-gimbals", seed)
        assert every["failed_updates"] == 0
        assert max(every["chain_joint_rmse_rad"]["gimbal2"]) <= 1e-2
        t_ratio.append(every["normalized_translation_rmse_percent"] / two["normalized_translation_rmse_percent"])
        j_ratio.append(np.mean(np.array(every["joint_rmse_rad"]) / np.array(two["joint_rmse_rad"])))
        print(f"\nseed {seed}: gimbal2 joint RMSE {np.round(every['chain_joint_rmse_rad']['gimbal2'], 5)} rad")
    print(
        f"two-gimbals: translation RMSE ratios {np.round(t_ratio, 3)}, primary joint RMSE ratios {np.round(j_ratio, 3)}"
    )
    assert np.mean(j_ratio) <= 1.05 and np.mean(t_ratio) <= 1.25


def _bag_with_late_camera(path: Path, late_ms: float, n: int = 12) -> Path:
    """A ROS2 bag: 200 Hz IMU, cam0 and the gimbal camera cam2 at 20 Hz with equal stamps, the stereo
    partner cam1 stamped ``late_ms`` after them (a camera on its own clock)."""
    rng = np.random.default_rng(0)
    t0 = 1_000_000_000_000
    with BagWriter(path, 2) as bag:
        for k in range(10 * n + 1):
            t = t0 + k * 5_000_000
            bag.imu("/imu0", t, np.array([0.0, 0.0, 9.81]), np.zeros(3))
            if k % 10 == 0 and k // 10 < n:
                img = rng.integers(0, 255, (48, 64), dtype=np.uint8)
                bag.image("/cam0/image_raw", t, img, "cam0")
                bag.image("/cam2/image_raw", t, img, "cam2")
                bag.image("/cam1/image_raw", t + int(late_ms * 1e6), img, "cam1")
    return path


def test_a_further_camera_on_its_own_clock_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Further cameras are used as exposed at cam0's stamp: a stereo partner 10 ms late (free-running) is
    refused before any work, naming the topic and the gap; 1 ms (a triggered camera's driver) passes the
    check; --max-further-gap accepts a larger gap knowingly."""
    cal = tmp_path / "calibration.yaml"
    d = {**flight_cluster("stereo+gimbal").to_dict(), "imu": ImuConfig(T_sI=default_static_mount()).to_dict()}
    cal.write_text(yaml.safe_dump(d))
    late = _bag_with_late_camera(tmp_path / "late", 10.0)
    args = ["vio", str(late), "--calibration", str(cal), "--out", str(tmp_path / "o"), "-q"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "topic /cam1/image_raw (cam1): its images are 10.00 ms (median) from cam0's" in err, err
    assert not (tmp_path / "o").exists()
    cameras = run_cameras(flight_cluster("stereo+gimbal"), "dcc")
    vb = VioBag(late, "/imu0", "/cam0/image_raw", "/cam2/image_raw", extra_topics=["/cam1/image_raw"])
    check_further_sync(vb, cameras, 12.0)  # accepted when allowed
    ok = _bag_with_late_camera(tmp_path / "ok", 1.0)
    vb = VioBag(ok, "/imu0", "/cam0/image_raw", "/cam2/image_raw", extra_topics=["/cam1/image_raw"])
    check_further_sync(vb, cameras, PipelineOptions().max_further_gap_ms)


def test_health_flags_a_further_camera_that_contributed_nothing() -> None:
    """A further camera none of whose tracks became an observation (wrong topic or extrinsics) is a
    warning naming it; NaN joint angles of a further chain fail ``finite``."""
    every, _ = _pair_runs("stereo+gimbal", 5, duration=10.0)
    r = every["result"]
    report = vio_health(r, ImuConfig(T_sI=default_static_mount()), VioOptions(mode="dcc"))
    check = {c.name: c for c in report.checks}["cameras.cam1"]
    assert check.passed and check.value > 1000
    r.stats["extra_obs"] = {"cam1": 0}
    check = {c.name: c for c in vio_health(r, ImuConfig(), VioOptions(mode="dcc")).checks}["cameras.cam1"]
    assert not check.passed and check.severity == "warning" and "cam1" in check.hint
    r.chain_theta = {"gimbal2": np.full((len(r.timestamps_ns), 2), np.nan)}
    assert not {c.name: c for c in vio_health(r, ImuConfig(), VioOptions(mode="dcc")).checks}["finite"].passed


def test_a_further_camera_with_a_wrong_extrinsic_fails_the_run() -> None:
    """The stereo partner's T_cs off by 1 deg (the tracks simulated with the true one) wrecks the run (its
    stereo tracks fail triangulation, its observations are gated, the landmarks go wrong): the cameras no
    longer fit each other and a ``residuals.*`` / ``observations.*`` check fails (an error: the trajectory
    is refused). With the true T_cs the run is healthy, every camera's residual is within 20 % of cam0's and
    every camera uses its tracks about as often as cam0."""
    cfg = StudyConfig(duration=10.0, density=0.5, pixel_sigma=0.5, seed=2)
    cal = flight_cluster("stereo+gimbal")
    truth, pts, imu = _study_inputs(cfg, cal)
    cams = run_cameras(cal, "dcc")
    frames = simulate_camera_tracks(truth, pts, cal, imu.T_sI, cams, 0.5, seed=3)
    init = InitialState(int(truth.t_ns[0]), truth.T_WI[0], truth.v_W[0], truth.acc_bias[0], truth.gyro_bias[0],
                        truth.theta[0])  # fmt: skip
    opts = VioOptions(mode="dcc", sigma=0.5 / float(cal.static_camera.intrinsics[0]))  # type: ignore[union-attr]
    wrong = dataclasses.replace(cams[0], T_cs=chain.se3_from_tau(np.r_[np.deg2rad(1.0), 0, 0, 0, 0, 0]) @ cams[0].T_cs)
    checks, used = {}, {}
    for name, run_cams in (("true", cams), ("wrong", (wrong,))):
        res = run_vio(frames, truth.imu, imu, cal, opts, init, cameras=run_cams)
        med, used[name] = res.stats["residual_median_px"], res.stats["observations_used_fraction"]
        checks[name] = {c.name: c for c in vio_health(res, imu, opts).checks}
        print(f"\n{name} T_cs: median residuals {med}, used fractions {used[name]}")
        if name == "true":
            assert all(abs(m / med["cam0"] - 1.0) < 0.2 for m in med.values())
    for check in ("residuals.cam1", "residuals.cam2", "observations.cam1", "observations.cam2"):
        assert checks["true"][check].passed, checks["true"][check].message
    assert all(c.passed for c in checks["true"].values() if c.severity == "error")
    fit = [c for n, c in checks["wrong"].items() if n.startswith(("residuals.", "observations."))]
    failed = [c for c in fit if not c.passed]
    assert failed and all(c.severity == "error" and "extrinsics" in c.hint for c in failed), [c.message for c in fit]
