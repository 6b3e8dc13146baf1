"""N-camera VIO on rendered cluster flights (bags through the whole pipeline): the benchmark at a small
size, and ``dcc-fg vio`` on the stereo + gimbal bag it rendered, with the cluster's own topics."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from benchmarks.bench_vio_cluster import main
from dcc_fg.cli import main as cli
from dcc_fg.data.cameras import run_cameras
from dcc_fg.io.outputs import read_joint_angles_csv
from dcc_fg.io.tum import read_tum
from dcc_fg.model import load_calibration
from dcc_fg.vio.evaluate import evaluate_folder
from dcc_fg.viz import rerun_log
from tests.test_rerun import load_rrd, pose, scalars

pytestmark = pytest.mark.slow  # renders three 12 s flights and runs each twice (~2 min)


@pytest.fixture(scope="module")
def bench(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], Path]:
    keep = tmp_path_factory.mktemp("flights")
    # inline front end: in step with the back end, the same result every run (with the front end in its own
    # process the joint angles reach it when they arrive, and the gimbal-pair joint ratio scattered from
    # 0.91-0.96 to 1.06-1.23 between two CI runs of the same code)
    return main(["--duration", "12", "--keep", str(keep), "--worker", "inline"]), keep


def test_cluster_runs_against_two_camera_runs(bench: tuple[dict[str, Any], Path]) -> None:
    """Issue 16: stereo + gimbal translation RMSE <= the one-static-camera run of the same flight, joint RMSE
    <= 1e-2 rad; two cameras on the gimbal: joint RMSE no worse than with one (mean of the joints' ratios,
    5 % allowance as in tests/test_vio_cluster.py). Measured at 12 s with the inline front end (identical
    in two runs): stereo + gimbal translation ratio 0.66, gimbal-pair joint ratios 0.93, 1.00; with the
    front end in its own process at 12 s: 0.66 / 1.47, 1.18 (stereo + gimbal; translation / joints) and
    0.60 / 0.91, 0.96 (gimbal pair), at 20 s 0.80 / 1.01, 1.30 and 0.65 / 0.85, 0.97."""
    out, _ = bench
    sg, gp, tg = out["stereo+gimbal"], out["gimbal-pair"], out["two-gimbals"]
    for r in (sg, gp, tg):
        for run in (r["all_cameras"], r["two_cameras"]):
            assert run["failed_updates"] == 0 and max(run["joint_rmse_rad"]) <= 1e-2
            assert run["real_time_factor"] > 0
    assert sg["all_cameras"]["cameras"] == ["cam0", "cam2", "cam1"] and sg["two_cameras"]["cameras"] == ["cam0", "cam2"]
    assert sg["all_cameras"]["extra_obs"]["cam1"] > 1000 and gp["all_cameras"]["extra_obs"]["cam2"] > 1000
    assert sg["rmse_ratio"] <= 1.0
    assert sum(gp["joint_rmse_ratio"]) / 2 <= 1.05
    # two gimbals: the second chain's angles are a state of their own, followed as well as the first's
    assert max(tg["all_cameras"]["chain_joint_rmse_rad"]["gimbal2"]) <= 1e-2
    assert tg["two_cameras"]["chain_joint_rmse_rad"] == {}


def test_vio_command_on_a_cluster_bag(bench: tuple[dict[str, Any], Path], tmp_path: Path) -> None:
    """``dcc-fg vio`` reads the cluster calibration.yaml: the gimbal camera is cam2 (its topic found from
    the calibration), the stereo partner cam1 is a further camera; ``--cameras none`` leaves it out."""
    _, keep = bench
    folder = keep / "stereo_gimbal"
    args = ["vio", str(folder / "flight"), "--calibration", str(folder / "calibration.yaml"), "--quiet"]
    assert cli([*args, "--out", str(tmp_path / "all")]) == 0
    assert cli([*args, "--cameras", "none", "--out", str(tmp_path / "two")]) == 0
    s_all = json.loads((tmp_path / "all" / "summary.json").read_text())
    s_two = json.loads((tmp_path / "two" / "summary.json").read_text())
    assert (
        s_all["run"]["topics"]["dynamic"] == "/cam2/image_raw" and s_all["run"]["topics"]["cam1"] == "/cam1/image_raw"
    )
    assert s_all["run"]["cameras"]["used"] == ["cam0", "cam2", "cam1"]
    assert s_two["run"]["cameras"]["used"] == ["cam0", "cam2"] and s_two["extra_obs"] == {}
    ev_all = evaluate_folder(tmp_path / "all", folder / "flight")
    ev_two = evaluate_folder(tmp_path / "two", folder / "flight")
    assert max(ev_all["joint_rmse_rad"]) <= 1e-2
    assert ev_all["normalized_translation_rmse_percent"] <= ev_two["normalized_translation_rmse_percent"]


def test_rerun_recording_shows_every_camera(bench: tuple[dict[str, Any], Path], tmp_path: Path) -> None:
    """``--rerun`` on the two-gimbal bag: the second gimbal's camera cam2 has its tracks per frame, its image
    at every keyframe, its pose per keyframe at gimbal2's estimated angles (T_sc = T_cs(theta)^-1) and
    gimbal2's joint angles over time, equal to joint_angles_gimbal2.csv."""
    _, keep = bench
    folder = keep / "two-gimbals"
    out, rrd = tmp_path / "run", tmp_path / "run.rrd"
    args = ["vio", str(folder / "flight"), "--calibration", str(folder / "calibration.yaml"), "--out", str(out)]
    assert cli([*args, "--quiet", "--rerun", str(rrd)]) == 0
    rec = load_rrd(rrd)
    t_kf, T_kf = read_tum(out / "trajectory.tum")
    t2, theta2 = read_joint_angles_csv(out / "joint_angles_gimbal2.csv")
    np.testing.assert_array_equal(t2, t_kf)
    for j in range(2):
        np.testing.assert_allclose(scalars(rec, f"/joints/gimbal2/theta_{j + 1}"), theta2[:, j], atol=1e-9)
    poses = rec["/" + rerun_log.further_camera("cam2")]["rows"]
    (cam2,) = run_cameras(load_calibration(folder / "calibration.yaml"), "dcc")
    assert len(poses) == len(t_kf)
    for k in (0, len(t_kf) // 2, len(t_kf) - 1):
        np.testing.assert_allclose(pose(poses[k]), np.linalg.inv(cam2.T_cs_at(theta2[k])), atol=1e-5)
    image = "/" + rerun_log.further_image("cam2")
    blobs = [r for r in rec[image]["rows"] if r.get("EncodedImage:blob") is not None]
    assert [r["keyframe"] for r in blobs] == list(range(len(t_kf)))
    tracks = rec[image + "/tracks"]["rows"]
    assert len(tracks) > len(t_kf) and sum(len(r["Points2D:positions"] or []) for r in tracks) > 1000
    # dcc-fg evaluate scores the second chain against the bag's /ground_truth/joints_gimbal2
    ev = evaluate_folder(out, folder / "flight")
    assert len(ev["chain_joint_rmse_rad"]["gimbal2"]) == 2 and max(ev["chain_joint_rmse_rad"]["gimbal2"]) <= 1e-2
