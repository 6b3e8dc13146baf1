"""``dcc-fg calibrate --cluster``: N-camera calibration from the command line (dcc_fg/commands/calibrate_cluster.py).

Simulated clusters (``dcc-fg simulate calibration --cluster``) are calibrated through :func:`dcc_fg.cli.main`;
every camera's ``T_cs`` (s = cam0 -> camera, metres) read back from the written ``calibration.yaml`` and
``joint_angles.csv`` (rad) must lie within a few reported sigma of ``ground_truth.yaml``.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

import dcc_fg
from dcc_fg.cli import main
from dcc_fg.cluster import CameraCluster

SNAPSHOTS = "30"
N_SIGMA = 5.0
CAMCHAIN_KEYS = ("camera_model", "intrinsics", "distortion_model", "distortion_coeffs", "resolution")


def simulate(root: Path, preset: str) -> Path:
    out = root / preset.replace("+", "_")
    assert (
        main(["simulate", "calibration", "--cluster", preset, "--out", str(out), "--snapshots", SNAPSHOTS, "-q"]) == 0
    )
    return out


def camchain_of(sim: Path, out: Path) -> Path:
    """A Kalibr camchain with the intrinsics of the simulated cluster's cameras (no extrinsics)."""
    d = yaml.safe_load((sim / "cluster.yaml").read_text())
    entries = {c: {k: v for k, v in e.items() if k in CAMCHAIN_KEYS} for c, e in d["cameras"].items()}
    out.write_text(yaml.safe_dump(entries))
    return out


def read_joint_csv(path: Path) -> tuple[list[str], dict[int, np.ndarray]]:
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    rows = {}
    for ln in lines[1:]:
        f = ln.split(",")
        rows[int(f[0])] = np.array([float(x) for x in f[1:]])
    return header, rows


def rotation_angle(R: np.ndarray) -> float:
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def check_against_truth(sim: Path, out: Path) -> dict[str, Any]:
    """Every camera's T_cs from OUT within N_SIGMA reported sigma of the ground truth; returns summary.json."""
    summary = json.loads((out / "summary.json").read_text())
    gt = yaml.safe_load((sim / "ground_truth.yaml").read_text())
    truth = CameraCluster.from_dict(gt["cluster"], "ground_truth.yaml")
    cal = dcc_fg.load_calibration(out / "calibration.yaml")
    est = cal.cluster()
    header, rows = read_joint_csv(out / "joint_angles.csv")
    assert header == ["timestamp_ns"] + [f"theta_{k + 1}" for k in range(est.joint_count)]
    assert summary["joint_columns"] == [f"{c.name}.theta_{k + 1}" for c in est.chains for k in range(c.n_joints)]
    std = summary["T_cs_std_over_snapshots"]
    static_std = summary["T_cs_std"]["static"]
    checked = 0
    for cam in est.camera_names[1:]:
        mount = est.camera(cam)
        if mount.is_static:
            s = np.array(static_std[cam], dtype=float)
            err_r = rotation_angle(cal.T_cs(cam)[:3, :3] @ truth.T_cs(cam)[:3, :3].T)
            err_t = float(np.linalg.norm(cal.T_cs(cam)[:3, 3] - truth.T_cs(cam)[:3, 3]))
            assert err_r < N_SIGMA * np.linalg.norm(s[:3]), (cam, err_r, s)
            assert err_t < N_SIGMA * np.linalg.norm(s[3:]), (cam, err_t, s)
            checked += 1
            continue
        sl = est.joint_slices()[mount.chain]
        rot_sigma, tra_sigma = 1e-3 * std[cam]["rotation_mrad_max"], 1e-3 * std[cam]["translation_mm_max"]
        for snap in gt["snapshots"]:
            theta = rows.get(int(snap["timestamp_ns"]))
            if theta is None or cam not in snap["cameras"] or not np.all(np.isfinite(theta[sl])):
                continue
            T_est = cal.T_cs(cam, theta)  # the flat vector of every chain's joints (rad)
            T_true = truth.T_cs(cam, snap["theta"])
            assert rotation_angle(T_est[:3, :3] @ T_true[:3, :3].T) < N_SIGMA * rot_sigma, (cam, snap["timestamp_ns"])
            assert np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]) < N_SIGMA * tra_sigma, (cam, snap["timestamp_ns"])
            checked += 1
    assert checked > 10
    return summary


@pytest.fixture(scope="module")
def sims(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("clusters")
    return {p: simulate(root, p) for p in ("stereo+gimbal", "gimbal-pair")}


@pytest.fixture(scope="module")
def stereo_run(sims: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    sim = sims["stereo+gimbal"]
    out = tmp_path_factory.mktemp("runs") / "sg"
    args = ["calibrate", str(sim / "detections"), "--cluster", str(sim / "cluster.yaml"), "--target",
            str(sim / "target.yaml"), "--out", str(out), "-q"]  # fmt: skip
    assert main(args) == 0
    return out


def test_stereo_gimbal_auto_init(sims: dict[str, Path], stereo_run: Path) -> None:
    out = stereo_run
    for name in ("calibration.yaml", "joint_angles.csv", "summary.json", ".dcc_fg_manifest.json"):
        assert (out / name).is_file(), name
    summary = check_against_truth(sims["stereo+gimbal"], out)
    assert summary["command"] == "calibrate" and summary["init"] == "auto"
    assert summary["health"]["healthy"] is True
    assert set(summary["reprojection_rms_px"]) == {"cam0", "cam1", "cam2", "all"}
    assert all(0.3 < summary["reprojection_rms_px"][c] < 0.5 for c in ("cam0", "cam1", "cam2"))  # 0.4 px noise
    assert summary["snapshots"]["used"] + summary["snapshots"]["skipped"] == summary["snapshots"]["total"]
    assert summary["solver"]["iterations"] > 0 and summary["solver"]["total_time_s"] > 0
    assert set(summary["counts"]) == {"cam0", "cam1", "cam2"}
    assert set(summary["T_cs_std_over_snapshots"]) == {"cam1", "cam2"}
    obs = summary["observability"]
    assert "gimbal.tau_s.rz" in obs["gauge_fixed"] and obs["null_space_dim"] == obs["n_gauge"]
    d = yaml.safe_load((out / "calibration.yaml").read_text())
    assert d["chains"]["gimbal"]["tau_s_std"][2] is None  # held by the gauge
    assert d["chains"]["gimbal"]["tau_s_std"][0] > 0 and len(d["chains"]["gimbal"]["dh_std"]) == 2
    assert all(x > 0 for x in d["cameras"]["cam2"]["tau_d_std"])
    assert "intrinsics" in d["cameras"]["cam1"] and "T_cs" in d["cameras"]["cam1"]
    assert len(d["statistics"]["T_cs_std"]["static"]["cam1"]) == 6
    cal = dcc_fg.load_calibration(out / "calibration.yaml")
    assert cal.camera_names == ["cam0", "cam1", "cam2"]
    assert cal.T_cs("cam2", [0.1, -0.2]).shape == (4, 4)
    _, rows = read_joint_csv(out / "joint_angles.csv")
    assert any(np.isnan(r).all() for r in rows.values())  # snapshots without cam2: NaN


def test_export_urdf_of_cluster_result(stereo_run: Path, tmp_path: Path) -> None:
    urdf = tmp_path / "cluster.urdf"
    assert main(["export", str(stereo_run / "calibration.yaml"), "--format", "urdf", "--out", str(urdf), "-q"]) == 0
    text = urdf.read_text()
    assert "cam2" in text and "cam1" in text and "observed range" in text


def test_gimbal_pair_from_camchain_and_mounts(sims: dict[str, Path], tmp_path: Path) -> None:
    sim = sims["gimbal-pair"]
    camchain = camchain_of(sim, tmp_path / "camchain.yaml")
    out = tmp_path / "out"
    args = ["calibrate", str(sim / "detections"), "--camchain", str(camchain), "--mounts", "cam1=gimbal:2,cam2=gimbal",
            "--out", str(out), "-q"]  # fmt: skip
    assert main(args) == 0
    summary = check_against_truth(sim, out)
    assert summary["cameras"] == {"cam0": "static", "cam1": "chain gimbal", "cam2": "chain gimbal"}


def test_gimbal_pair_init_file(sims: dict[str, Path], tmp_path: Path) -> None:
    sim = sims["gimbal-pair"]
    out = tmp_path / "out"
    # no --target: the AprilGrid of the detection files
    args = ["calibrate", str(sim / "detections"), "--cluster", str(sim / "cluster.yaml"), "--init", "file",
            "--out", str(out), "-q"]  # fmt: skip
    assert main(args) == 0
    summary = check_against_truth(sim, out)
    assert summary["init"] == "file"


def test_unhealthy_exit_3_unless_accepted(sims: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    sim = sims["gimbal-pair"]
    out = tmp_path / "out"
    # the corners have 0.4 px noise
    args = ["calibrate", str(sim / "detections"), "--cluster", str(sim / "cluster.yaml"), "--pixel-sigma", "0.05",
            "--out", str(out), "-q"]  # fmt: skip
    assert main(args) == 3
    assert "residuals.pixel_sigma" in capsys.readouterr().err
    assert not out.exists()
    assert main([*args, "--accept-unhealthy"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["health"]["healthy"] is False


def _fails(args: list[str], capsys: pytest.CaptureFixture, *needles: str) -> None:
    assert main(args) == 2
    err = capsys.readouterr().err
    for n in needles:
        assert n in err, (n, err)


def test_bad_inputs(sims: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    sim = sims["stereo+gimbal"]
    cluster, det, out = sim / "cluster.yaml", sim / "detections", str(tmp_path / "out")
    # a camera folder missing from DATA
    partial = tmp_path / "partial"
    shutil.copytree(det, partial)
    shutil.rmtree(partial / "cam2")
    _fails(["calibrate", str(partial), "--cluster", str(cluster), "--out", out], capsys, "cam2/", "cameras.cam2",
           str(cluster))  # fmt: skip
    # a cluster file describing a camera the data do not have
    d = yaml.safe_load(cluster.read_text())
    d["cameras"]["cam3"] = dict(d["cameras"]["cam1"])
    bigger = tmp_path / "bigger.yaml"
    bigger.write_text(yaml.safe_dump(d, sort_keys=False))
    _fails(["calibrate", str(det), "--cluster", str(bigger), "--out", out], capsys, "cameras.cam3", str(bigger))
    # a data folder with a camera the cluster file does not describe
    extra = tmp_path / "extra"
    shutil.copytree(det, extra)
    shutil.copytree(det / "cam1", extra / "cam3")
    _fails(["calibrate", str(extra), "--cluster", str(cluster), "--out", out], capsys, str(extra / "cam3"))
    # a two-camera gimbal file given to --cluster
    two = tmp_path / "gimbal.yaml"
    two.write_text(yaml.safe_dump({"joints": 1, "tau_s": [0.0] * 6, "tau_d": [0.0] * 6, "dh": [[0.0, 0.0, 0.0]]}))
    _fails(["calibrate", str(det), "--cluster", str(two), "--out", out], capsys, str(two), "two-camera")
    # a cluster file without intrinsics
    d = yaml.safe_load(cluster.read_text())
    for key in CAMCHAIN_KEYS:
        d["cameras"]["cam2"].pop(key)
    bare = tmp_path / "bare.yaml"
    bare.write_text(yaml.safe_dump(d, sort_keys=False))
    _fails(["calibrate", str(det), "--cluster", str(bare), "--out", out], capsys, "cameras.cam2", "intrinsics")
    # image folders are not read for N cameras yet
    images = tmp_path / "images"
    for c in ("cam0", "cam1", "cam2"):
        (images / c).mkdir(parents=True)
        (images / c / "1000.png").write_bytes(b"")
    _fails(["calibrate", str(images), "--cluster", str(cluster), "--out", out], capsys, "holds images")
    # conflicting options
    camchain = camchain_of(sim, tmp_path / "camchain.yaml")
    _fails(["calibrate", str(det), "--cluster", str(cluster), "--gimbal", str(two), "--out", out], capsys, "--gimbal")
    _fails(["calibrate", str(det), "--cluster", str(cluster), "--joints", "2", "--out", out], capsys, "--joints")
    _fails(["calibrate", str(det), "--cluster", str(cluster), "--incremental", "--out", out], capsys, "--incremental")
    _fails(["calibrate", str(det), "--cluster", str(cluster), "--camchain", str(camchain), "--out", out], capsys,
           "--cluster and --camchain")  # fmt: skip
    _fails(["calibrate", str(det), "--mounts", "cam2=gimbal:2", "--out", out], capsys, "--mounts needs --camchain")
    _fails(["calibrate", str(det), "--camchain", str(camchain), "--mounts", "cam2=gimbal:2", "--init", "file",
            "--out", out], capsys, "--init file")  # fmt: skip
    _fails(["calibrate", str(det), "--camchain", str(camchain), "--mounts", "cam9=gimbal:2", "--out", out], capsys,
           "camera cam9 is not in", str(camchain))  # fmt: skip
    _fails(["calibrate", str(det), "--camchain", str(camchain), "--mounts", "cam2=gimbal", "--out", out], capsys,
           "no joint count")  # fmt: skip
    assert not Path(out).exists()
