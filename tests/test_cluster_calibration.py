"""Calibration of a whole camera cluster in one graph (dcc_fg.cluster_calibration).

Claims and their tests:

* analytic Jacobians of every camera term (static camera with a Pose3 extrinsic, chain camera,
  target pose, joint angles) match central differences;
* the gauge: the information matrix of the *full* parameterization has exactly as many null
  directions as the gauge rules fix (6 per chain, however many cameras it carries), the held
  coordinates span that null space (fixing them removes it and nothing else), and the gauge-fixed
  information is full rank;
* calibration of the presets against the simulator's truth: errors within k sigma of the reported
  covariances, reprojection RMS at the noise level; the CRB ratio (fast: 2 seeds, slow: 20 seeds <= 1.2);
* snapshots holding a subset of the cameras (and unusable single-group snapshots skipped);
* a two-camera cluster reproduces :func:`dcc_fg.calibrate.calibrate` (simulation, and EuRoC cam_april
  with cam0 + cam1 as a static stereo pair: ``--joints 0``);
* the automatic initialization on random geometries (fast: 1 geometry; slow: >= 9 of 10 per preset);
* bad input is refused with a message naming the problem.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import gtsam
import numpy as np
import pytest
import yaml
from conftest import load_benchmark
from conftest import shared_data as real
from test_real_stereo import euroc_sensor

from dcc_fg.calibrate import CalibrationOptions, calibrate
from dcc_fg.cli import main
from dcc_fg.cluster import CameraCluster, CameraMount, ChainSpec
from dcc_fg.cluster_calibration import (
    ClusterKinematics,
    ClusterOptions,
    ClusterState,
    Columns,
    calibrate_cluster,
    information,
    problem_at,
    snapshot_jacobians,
    term_residual,
    terms_of,
)
from dcc_fg.cluster_data import ClusterDataset, ClusterSnapshot, read_cluster_detections
from dcc_fg.cluster_init import auto_initialize_cluster
from dcc_fg.data import Observation
from dcc_fg.io.camchain import CamchainEntry
from dcc_fg.io.detections import write_detection_table
from dcc_fg.model import GimbalCalibration
from dcc_fg.sim.calibration_scene import SceneConfig, simulate_calibration
from dcc_fg.sim.cluster_scene import ClusterSceneConfig, SimulatedCluster, simulate_cluster
from dcc_fg.sources.dataset import load_dataset
from dcc_fg.studies.cluster_accuracy import CameraAccuracy, cluster_accuracy
from dcc_fg.targets import TargetGeometry, load_target

bench = load_benchmark("bench_cluster_calibration")
SIGMA = 0.4


def small(preset: str, seed: int = 0, n: int = 30) -> SimulatedCluster:
    return simulate_cluster(preset, seed, ClusterSceneConfig(n_snapshots=n))


def truth_state(sim: SimulatedCluster):  # type: ignore[no-untyped-def]
    return problem_at(sim.data, ClusterKinematics.from_cluster(sim.truth), sim.joints, sim.T_st, SIGMA)


# ------------------------------------------------------------------ Jacobians


def perturbed(state: ClusterState, cols: Columns, delta: np.ndarray) -> ClusterState:
    """``state`` moved by ``delta`` over the full columns (vectors added, poses T Exp(xi))."""
    m = state.model.copy()
    th = {k: v.copy() for k, v in state.thetas.items()}
    T_st = state.T_st.copy()
    for (kind, name), idx in cols.block.items():
        d = delta[idx]
        if kind == "C":
            L = m.n_joints(name)
            vec = np.concatenate([m.tau_s[name], m.dh[name].ravel()]) + d
            m.tau_s[name], m.dh[name] = vec[:6], vec[6:].reshape(L, 3)
        elif kind == "D":
            m.tau_d[name] = m.tau_d[name] + d
        elif kind == "E":
            m.T_cs[name] = gtsam.Pose3(m.T_cs[name]).retract(d).matrix()
        elif kind == "J":
            i, ch = name.split(":")
            th[ch][int(i)] = th[ch][int(i)] + d
        else:
            T_st[int(name)] = gtsam.Pose3(T_st[int(name)]).retract(d).matrix()
    return ClusterState(m, th, T_st)


@pytest.mark.parametrize("preset", ["stereo+gimbal", "gimbal-pair"])
def test_jacobians_match_central_differences(preset: str) -> None:
    sim = small(preset, n=3)
    problem, state = truth_state(sim)
    cols = Columns(problem, full=True)
    blocks = []
    for idx, Jc in snapshot_jacobians(problem, cols, state):
        Jd = np.zeros((Jc.shape[0], cols.n))
        Jd[:, idx] = Jc
        blocks.append(Jd)
    J = np.vstack(blocks)

    def residuals(st: ClusterState) -> np.ndarray:
        out = []
        for term in terms_of(problem.data):
            ch = st.model.mounts[term.camera]
            th = st.thetas[ch][term.snapshot] if ch is not None else None
            r, _ = term_residual(st.model, problem.data.cameras[term.camera], term, th, st.T_st[term.snapshot], False)
            out.append(r.ravel())
        return np.concatenate(out) / SIGMA

    h = 1e-6
    J_num = np.zeros_like(J)
    for k in range(cols.n):
        e = np.zeros(cols.n)
        e[k] = h
        J_num[:, k] = (residuals(perturbed(state, cols, e)) - residuals(perturbed(state, cols, -e))) / (2 * h)
    scale = np.abs(J_num).max()
    assert np.abs(J - J_num).max() < 1e-5 * scale


# ------------------------------------------------------------------ gauge


@pytest.mark.parametrize(("preset", "n_gauge"), [("stereo+gimbal", 6), ("gimbal-pair", 6), ("two-gimbals", 12)])
def test_gauge_removes_exactly_the_null_space(preset: str, n_gauge: int) -> None:
    """Nullity of the full information = the directions the gauge rules fix; the held coordinates
    (chain entries held, mean of theta_L over the reference snapshots) are independent on the null
    space, so holding them removes all of it; the gauge-fixed information is full rank."""
    sim = small(preset, n=20)
    problem, state = truth_state(sim)
    assert problem.n_gauge == n_gauge
    H, cols = information(problem, state, full=True)
    d = np.sqrt(np.diag(H))
    w, V = np.linalg.eigh(H / np.outer(d, d))
    null = w < 1e-10 * w.max()
    assert int(null.sum()) == n_gauge
    assert w[~null].min() > 1e-7 * w.max()  # a clear gap: the rest is well determined
    N = V[:, null] / d[:, None]  # null directions in parameter units
    rows = []
    for ch in problem.chains:
        names = [n for n in cols.names if n.startswith(f"{ch}.")]
        held = [n for n, f in zip(names, problem.chain_free[ch], strict=True) if not f]
        rows += [N[cols.names.index(n)] for n in held]
        for j in problem.offsets[ch]:
            idx = [cols.block[("J", f"{i}:{ch}")][j] for i in np.flatnonzero(problem.has_theta[ch])]
            rows.append(N[idx].mean(axis=0))
    M = np.array(rows)
    assert M.shape == (n_gauge, n_gauge)
    sv = np.linalg.svd(M / np.abs(M).max(), compute_uv=False)
    assert sv.min() > 1e-3  # the held coordinates move along every null direction independently
    H_fixed, _ = information(problem, state, full=False)
    d = np.sqrt(np.diag(H_fixed))
    w_fixed = np.linalg.eigvalsh(H_fixed / np.outer(d, d))
    assert w_fixed.min() > 1e-8 * w_fixed.max()


def test_two_cameras_on_one_end_share_the_end_frame_gauge() -> None:
    """With two cameras on one chain end the end-frame gauge is absorbed once: with the chain's held
    entries held, both cameras' tau_d are determined (finite 1-sigma); like every tau_d they move with
    the end-frame gauge in the full parameterization (reported not observable, as in the two-camera
    report), while the cameras' relative pose, which no gauge moves, matches the truth."""
    sim = small("gimbal-pair", n=20)
    res = calibrate_cluster(sim.data, sim.initial, ClusterOptions(pixel_sigma=SIGMA))
    taus = [f"{c}.tau_d.{t}" for c in ("cam1", "cam2") for t in ("rx", "ry", "rz", "tx", "ty", "tz")]
    assert all(np.isfinite(res.parameter_std[n]) and res.parameter_std[n] > 0 for n in taus)
    assert not res.observable["gimbal.dh2.d"] and not res.observable["gimbal.tau_s.rz"]
    assert res.observable["gimbal.dh1.alpha"]
    assert res.null_space_dim == res.n_gauge == 6
    m, t = res.model, ClusterKinematics.from_cluster(sim.truth)
    rel = gtsam.Pose3(t.T_cs_of("cam2", np.zeros(2)) @ np.linalg.inv(t.T_cs_of("cam1", np.zeros(2))))
    est = gtsam.Pose3(m.T_cs_of("cam2", np.zeros(2)) @ np.linalg.inv(m.T_cs_of("cam1", np.zeros(2))))
    err = rel.localCoordinates(est)
    assert np.linalg.norm(err[:3]) < 1e-3 and np.linalg.norm(err[3:]) < 1e-3  # ~1e-4 expected (0.4 px, 20 views)


# ------------------------------------------------------------------ against the truth


def check_against_truth(sim: SimulatedCluster, res, k_sigma: float = 5.0) -> None:  # type: ignore[no-untyped-def]
    """Every camera's T_cs(theta_i) error within k sigma of the reported covariance (per component;
    ~200 correlated components per camera, so 5 sigma: p ~ 6e-7 each), and the mean NEES over the
    snapshots below chi2_6(0.999) = 22.5 (the snapshots share the kinematic error: the mean is
    distributed like one chi2_6 draw, not a mean of independent ones)."""
    acc = cluster_accuracy(sim, res)
    assert res.T_cs_covariances is not None
    for c, a in acc.items():
        covs = res.T_cs_covariances[c]
        covs = covs[np.isfinite(covs[:, 0, 0])]
        assert covs.shape[0] == a.errors.shape[0]
        z = a.errors / np.sqrt(np.einsum("kii->ki", covs))
        assert np.max(np.abs(z)) < k_sigma, c
        nees = [e @ np.linalg.solve(P, e) for e, P in zip(a.errors, covs, strict=True)]
        assert np.mean(nees) < 22.5, c
        # the reported covariance is the bound at the solution: close to the CRB at the truth
        rr, rt = CameraAccuracy.bound_rms(covs)
        br, bt = CameraAccuracy.bound_rms(a.bound)
        assert 0.8 < rr / br < 1.25 and 0.8 < rt / bt < 1.25


@pytest.mark.parametrize("preset", ["stereo+gimbal", "gimbal-pair"])
def test_preset_calibration_matches_truth(preset: str) -> None:
    sim = small(preset, seed=5, n=30)
    res = calibrate_cluster(sim.data, sim.initial, ClusterOptions(pixel_sigma=SIGMA))
    assert abs(res.reprojection_rms()["all"] / SIGMA - 1.0) < 0.05
    assert res.null_space_dim == res.n_gauge
    check_against_truth(sim, res)


def test_crb_ratio_two_seeds() -> None:
    """Two seeds per preset of the benchmark's CRB study (sampling spread is wide at 2 seeds: <= 1.5)."""
    for preset in ("stereo+gimbal", "gimbal-pair"):
        s = bench.crb_study(preset, [0, 1], n_snapshots=40, verbose=False)
        for c, (rr, rt) in s.ratios.items():
            assert rr < 1.5 and rt < 1.5, (preset, c, rr, rt)


@pytest.mark.slow
@pytest.mark.parametrize("preset", ["stereo+gimbal", "gimbal-pair"])
def test_crb_ratio_twenty_seeds(preset: str) -> None:
    s = bench.crb_study(preset, list(range(20)), verbose=False)
    for c, (rr, rt) in s.ratios.items():
        assert rr <= 1.2 and rt <= 1.2, (preset, c, rr, rt)


def test_subset_snapshots() -> None:
    """Snapshots with only some cameras: cam0 + cam2, cam1 + cam2 (no reference camera), cam0 + cam1
    (no gimbal camera: no joint angles), and a single camera (skipped)."""
    sim = small("stereo+gimbal", seed=3, n=36)
    snaps = []
    for i, s in enumerate(sim.data.snapshots):
        keep = s.cameras
        if len(keep) == 3:
            keep = [["cam0", "cam2"], ["cam1", "cam2"], ["cam0", "cam1"], keep][i % 4]
        snaps.append(ClusterSnapshot(s.timestamp_ns, {c: s.observations[c] for c in keep}, s.joints))
    lone = next(i for i, s in enumerate(sim.data.snapshots) if "cam2" in s.observations and i % 4 == 3)
    snaps[lone] = ClusterSnapshot(snaps[lone].timestamp_ns, {"cam2": snaps[lone].observations["cam2"]}, None)
    kinds = {tuple(s.cameras) for s in snaps}
    assert {("cam0", "cam2"), ("cam1", "cam2"), ("cam0", "cam1"), ("cam2",)} <= kinds
    data = ClusterDataset(sim.data.cameras, sim.data.target_points, snaps, "subset")
    res = calibrate_cluster(data, sim.initial, ClusterOptions(pixel_sigma=SIGMA))
    assert res.skipped_snapshots == [lone]
    pos = {int(i): k for k, i in enumerate(res.snapshot_index)}
    no_gimbal = [pos[i] for i, s in enumerate(snaps) if i != lone and "cam2" not in s.observations]
    assert no_gimbal and np.all(np.isnan(res.joint_angles["gimbal"][no_gimbal]))
    kept = [s for i, s in enumerate(snaps) if i != lone]
    sub = SimulatedCluster(
        ClusterDataset(data.cameras, data.target_points, kept, "subset"), sim.truth, sim.initial,
        {k: np.delete(v, lone, axis=0) for k, v in sim.joints.items()}, np.delete(sim.T_st, lone, axis=0),
        sim.ranges, sim.preset, sim.seed, sim.config,
    )  # fmt: skip
    res2 = calibrate_cluster(sub.data, sim.initial, ClusterOptions(pixel_sigma=SIGMA))
    check_against_truth(sub, res2)
    assert np.abs(res2.T_cs("cam2", 0) - res.T_cs("cam2", 0)).max() < 1e-6  # the skipped view changed nothing


# ------------------------------------------------------------------ two cameras: today's result


def test_two_camera_cluster_reproduces_calibrate() -> None:
    """cam0 + cam1 on a 2-DOF chain: the same problem, start and solve as the two-camera calibrate()."""
    sim = simulate_calibration(0, SceneConfig(n_calibration=25, n_validation=1))
    ref = calibrate(sim.calibration_set, sim.initial, CalibrationOptions(pixel_sigma=SIGMA))
    cl = sim.initial.cluster()
    res = calibrate_cluster(ClusterDataset.from_pair(sim.calibration_set, chain="gimbal"), cl,
                            ClusterOptions(pixel_sigma=SIGMA))  # fmt: skip
    for i in range(len(sim.calibration_set.snapshots)):
        assert np.abs(res.T_cs("cam1", i) - ref.T_ds(i)).max() < 1e-7
    assert res.T_cs_covariances is not None and ref.T_ds_covariances is not None
    np.testing.assert_allclose(res.T_cs_covariances["cam1"], ref.T_ds_covariances, rtol=1e-3, atol=1e-14)
    assert abs(res.final_error - ref.final_error) < 1e-6 * ref.final_error


def euroc_pair(recording: str, tmp_path: Path) -> ClusterDataset:
    """EuRoC ``cam_april`` (30 frames) or ``imu_april`` (100 frames spread over its 72 s, as in
    tests/test_real_stereo.py) yac detections with EuRoC's intrinsics, as a cluster data set."""
    mav0 = real("euroc_v1_01_micro") / "MicroEurocDataset" / "mav0"
    _, cam0 = euroc_sensor(mav0 / "cam0" / "sensor.yaml")
    _, cam1 = euroc_sensor(mav0 / "cam1" / "sensor.yaml")
    chain = {"cam0": CamchainEntry(cam0), "cam1": CamchainEntry(cam1)}
    src = real("euroc_aprilgrid") / "calib" / recording
    if recording == "imu_april":
        names = sorted(p.name for p in (src / "cam0").glob("*.csv"))
        for cam in ("cam0", "cam1"):
            (tmp_path / cam).mkdir()
            for k in np.linspace(0, len(names) - 1, 100).round().astype(int):
                (tmp_path / cam / names[k]).symlink_to(src / cam / names[k])
        src = tmp_path
    return ClusterDataset.from_pair(load_dataset(src, chain, progress=False))


@pytest.mark.parametrize("recording", ["cam_april", pytest.param("imu_april", marks=pytest.mark.slow)])
def test_euroc_static_stereo_reproduces_two_camera_result(recording: str, tmp_path: Path) -> None:
    """EuRoC, cam0 + cam1 a static stereo pair: today's ``calibrate --joints 0`` result.

    cam1 on an L = 0 chain is the two-camera parameterization itself (tau_s held, tau_d free): equal to
    round-off. cam1 static with a Pose3 T_cs is another parameterization of the same cost: equal to the
    solver's tolerance (~1e-11). The cluster calibration whitens every image with one sigma, so the
    reference does too (``corner_noise="shared"``; by default ``calibrate`` weights each image by its
    own noise floor)."""
    data = euroc_pair(recording, tmp_path)
    pair, _ = data.pair("cam0", "cam1")
    ref = calibrate(pair, GimbalCalibration(np.zeros(12), 0), CalibrationOptions(corner_noise="shared"))
    l0 = CameraCluster((CameraMount("cam0"), CameraMount("cam1", "rig", tau_d=np.zeros(6))),
                       (ChainSpec("rig", np.zeros(6), np.zeros((0, 3))),))  # fmt: skip
    res_l0 = calibrate_cluster(data, l0)
    assert np.abs(res_l0.T_cs("cam1", 0) - ref.T_ds(0)).max() < 1e-12
    res_static = calibrate_cluster(data, ClusterKinematics.static_pair())
    assert np.abs(res_static.T_cs("cam1", 0) - ref.T_ds(0)).max() < 1e-9
    assert ref.T_ds_covariances is not None
    for res in (res_l0, res_static):
        assert res.T_cs_covariances is not None
        np.testing.assert_allclose(res.T_cs_covariances["cam1"][0], ref.T_ds_covariances[0], rtol=1e-6, atol=1e-16)
        assert abs(res.variance_factor - ref.variance_factor) < 1e-9
    assert res_static.observable["cam1.T_cs.wx"] and res_static.null_space_dim == 0
    assert res_l0.null_space_dim == res_l0.n_gauge == 6


# ------------------------------------------------------------------ automatic initialization


def test_auto_init_random_geometry() -> None:
    r = bench.auto_run("stereo+gimbal", 0)
    assert r["ok"], r


@pytest.mark.slow
@pytest.mark.parametrize("preset", ["stereo+gimbal", "gimbal-pair"])
def test_auto_init_ten_random_geometries(preset: str) -> None:
    runs = [bench.auto_run(preset, g) for g in range(10)]
    assert sum(bool(r["ok"]) for r in runs) >= 9, runs


# ------------------------------------------------------------------ bad input


def test_bad_input_is_refused() -> None:
    sim = small("stereo+gimbal", n=8)
    d = sim.data
    bad = replace(d, snapshots=[ClusterSnapshot(1, {"cam0": d.snapshots[0].observations["cam0"],
                                                    "cam7": d.snapshots[0].observations["cam1"]})])  # fmt: skip
    with pytest.raises(ValueError, match="camera cam7 is not in the cluster"):
        calibrate_cluster(bad, sim.initial)
    few = Observation([0, 1, 2], np.zeros((3, 2)))
    bad = replace(d, snapshots=[ClusterSnapshot(1, {"cam0": few, "cam1": d.snapshots[0].observations["cam1"]})])
    with pytest.raises(ValueError, match="only 3 corners in camera cam0"):
        calibrate_cluster(bad, sim.initial)
    only_one = replace(d, snapshots=[ClusterSnapshot(s.timestamp_ns, {"cam2": s.observations["cam2"]})
                                     for s in d.snapshots if "cam2" in s.observations])  # fmt: skip
    with pytest.raises(ValueError, match="no snapshot links two rigid groups"):
        calibrate_cluster(only_one, sim.initial)
    drop_cam1 = [ClusterSnapshot(s.timestamp_ns, {c: o for c, o in s.observations.items() if c != "cam1"})
                 for s in d.snapshots]  # fmt: skip
    no_cam1 = replace(d, snapshots=drop_cam1)
    with pytest.raises(ValueError, match=r"cam1 never see the target together"):
        calibrate_cluster(no_cam1, sim.initial)
    with pytest.raises(ValueError, match="no intrinsics for camera"):
        calibrate_cluster(replace(d, cameras={"cam0": d.cameras["cam0"]}), sim.initial)
    with pytest.raises(ValueError, match="seen in 2 usable snapshots"):
        calibrate_cluster(replace(d, snapshots=d.snapshots[:2]), sim.initial)
    mounts = {"cam0": None, "cam1": None, "cam2": "gimbal"}
    with pytest.raises(ValueError, match="cam1 never share a snapshot with cam0"):
        auto_initialize_cluster(no_cam1, mounts, {"gimbal": 2})


# ------------------------------------------------------------------ files and the command line


def test_cli_simulate_cluster_round_trip(tmp_path: Path) -> None:
    """``dcc-fg simulate calibration --cluster gimbal-pair`` writes a detection folder that reads back
    into the simulated corners and calibrates to the ground truth it writes."""
    out = tmp_path / "sim"
    assert main(["simulate", "calibration", "--cluster", "gimbal-pair", "--snapshots", "16", "--seed", "2",
                 "--out", str(out)]) == 0  # fmt: skip
    cluster = CameraCluster.from_dict(yaml.safe_load((out / "cluster.yaml").read_text()), "cluster.yaml")
    intrinsics = {c.name: c.camera for c in cluster.cameras if c.camera is not None}
    data = read_cluster_detections(out / "detections", intrinsics, load_target(out / "target.yaml"))
    truth = yaml.safe_load((out / "ground_truth.yaml").read_text())
    assert [s.cameras for s in data.snapshots] == [s["cameras"] for s in truth["snapshots"]]
    res = calibrate_cluster(data, cluster, ClusterOptions(pixel_sigma=SIGMA))
    true_cluster = CameraCluster.from_dict(truth["cluster"], "ground_truth.yaml")
    assert res.T_cs_covariances is not None
    for c in ("cam1", "cam2"):
        for k, snap in enumerate(truth["snapshots"]):
            T_true = true_cluster.T_cs(c, snap["theta"])
            e = gtsam.Pose3(T_true).localCoordinates(gtsam.Pose3(res.T_cs(c, k)))
            assert np.all(np.abs(e) < 5.0 * np.sqrt(np.diag(res.T_cs_covariances[c][k])))
    # an existing data set is not overwritten (exit code 2, one-line message)
    assert main(["simulate", "calibration", "--cluster", "gimbal-pair", "--snapshots", "4", "--out", str(out)]) == 2
    assert main(["simulate", "calibration", "--cluster", "gimbal-pair", "--target", "checkerboard",
                 "--out", str(tmp_path / "cb")]) == 2  # fmt: skip


def test_cluster_detection_folder_errors(tmp_path: Path) -> None:
    sim = small("stereo+gimbal", n=4)
    cams = dict(sim.data.cameras)
    with pytest.raises(ValueError, match="AprilGrid"):
        read_cluster_detections(tmp_path, cams, sim.config.target)
    grid = TargetGeometry.aprilgrid(6, 6, 0.06, 0.3)
    with pytest.raises(ValueError, match="no camera folder"):
        read_cluster_detections(tmp_path, cams, grid)
    (tmp_path / "cam0").mkdir()
    obs = Observation([0, 1, 2, 3], np.ones((4, 2)))
    write_detection_table(tmp_path / "cam0" / "100.csv", 100, (6, 6, 0.06, 0.3), obs.ids, obs.pixels, grid.points[:4])
    with pytest.raises(ValueError, match="is not"):
        read_cluster_detections(tmp_path, cams, TargetGeometry.aprilgrid(5, 6, 0.06, 0.3))
    write_detection_table(tmp_path / "cam0" / "200.csv", 200, (6, 6, 0.06, 0.3), obs.ids, obs.pixels, grid.points[:4])
    with pytest.raises(ValueError, match="two frames"):
        read_cluster_detections(tmp_path, cams, grid)
    data = read_cluster_detections(tmp_path, cams, grid, tolerance_ns=50)
    assert [s.timestamp_ns for s in data.snapshots] == [100, 200]


def test_robust_loss_resists_outlier_corners() -> None:
    """20 corners moved by 15 px: the Huber loss keeps T_cs near the truth, the plain cost does not."""
    sim = small("stereo+gimbal", seed=4, n=24)
    rng = np.random.default_rng(0)
    snaps = []
    for k, s in enumerate(sim.data.snapshots):
        obs = dict(s.observations)
        if k < 20:
            o = obs["cam2"] if "cam2" in obs else obs["cam1"]
            pix = o.pixels.copy()
            pix[rng.integers(len(pix))] += 15.0
            obs["cam2" if "cam2" in obs else "cam1"] = Observation(o.ids, pix)
        snaps.append(ClusterSnapshot(s.timestamp_ns, obs, s.joints))
    bad = SimulatedCluster(replace(sim.data, snapshots=snaps), sim.truth, sim.initial, sim.joints, sim.T_st,
                           sim.ranges, sim.preset, sim.seed, sim.config)  # fmt: skip

    def worst(res) -> float:  # type: ignore[no-untyped-def]
        return max(CameraAccuracy.rms(a.errors)[0] for a in cluster_accuracy(bad, res).values())

    plain = calibrate_cluster(bad.data, sim.initial, ClusterOptions(pixel_sigma=SIGMA, compute_covariance=False))
    robust = calibrate_cluster(bad.data, sim.initial, ClusterOptions(pixel_sigma=SIGMA, robust="huber", robust_k=1.0))
    clean = calibrate_cluster(sim.data, sim.initial, ClusterOptions(pixel_sigma=SIGMA, compute_covariance=False))
    print(f"\nworst rotation RMS: plain {worst(plain):.2e}, huber {worst(robust):.2e}, clean {worst(clean):.2e} rad")
    assert worst(robust) < 0.5 * worst(plain)
    assert worst(robust) < 2.0 * worst(clean)
