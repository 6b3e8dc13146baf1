"""End to end on rendered images: ``dcc-fg simulate calibration`` -> ``dcc-fg calibrate`` -> ground truth.

Criterion (issue 3): per-snapshot T_ds errors within 1.5x of the corner-level result of the same
scenario.  Measure: the RMS over snapshots of the rotation (rad) and of the translation (m) part
of Log(T_ds_true^-1 T_ds_est), compared separately.

What is fair.  The rendered data set is made *from* the corner-level simulation (same seed: same
true mechanism, joint angles, board poses and perturbed gimbal.yaml), so the two calibrations
differ only in their corner measurements.  Two comparisons are asserted:

1. the literal one: rendered <= 1.5 x the corner-level calibration of the same scenario with the
   simulator's 0.4 px noise.  It is easily met because detected corners are far less noisy
   (about 0.025 px per axis on these images), so on its own it says little;
2. the fair one, at matched noise: rendered <= 1.5 x the *expected* corner-level error with
   Gaussian pixel noise equal to the rendered run's detection noise (its per-axis RMS
   reprojection residual, from summary.json), i.e. the Cramer-Rao bound of the same scenario at
   that sigma, which the corner-level estimator attains (tests/test_statistics.py).  A single
   corner-level realization is not used as the yardstick here because it scatters too much: over
   12 seeds of the 25-snapshot folder case its RMS ranged from 0.56x to 2.0x the bound (while
   rendered / bound ranged from 0.35x to 1.47x, mean 1.0).  This checks that the image pipeline
   (rendering through the distorted camera, detection, id order, pairing, bag/folder I/O) adds no
   error beyond what its pixel noise explains; a 0.5 px convention error, a mirrored tag or a
   wrong distortion would blow it by orders of magnitude.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from dcc_fg.calibrate import CalibrationOptions, calibrate
from dcc_fg.cli import main
from dcc_fg.io.outputs import read_joint_angles_csv
from dcc_fg.model import load_calibration
from dcc_fg.sim.calibration_scene import simulate_calibration
from dcc_fg.sim.write_dataset import CalibrationSimSpec, load_ground_truth, write_calibration_dataset
from dcc_fg.studies.calibration_accuracy import T_ds_errors, cramer_rao_bound

RATIO = 1.5


def _rms(err: np.ndarray) -> np.ndarray:
    """[rotation RMS rad, translation RMS m] over snapshots of (K, 6) tangent errors."""
    return np.array([np.sqrt(np.mean(np.sum(err[:, :3] ** 2, 1))), np.sqrt(np.mean(np.sum(err[:, 3:] ** 2, 1)))])


def _corner_level(sim_config, seed: int, sigma: float) -> np.ndarray:  # noqa: ANN001
    """T_ds error RMS of the corner-level calibration of the same scenario with pixel noise sigma."""
    sim = simulate_calibration(seed, replace(sim_config, pixel_sigma=sigma))
    res = calibrate(sim.calibration_set, sim.initial, CalibrationOptions(compute_covariance=False))
    return _rms(T_ds_errors(sim.truth, sim.joints_calibration, res.calibration, res.joint_angles))


def _bound(sim_config, seed: int, sigma: float) -> np.ndarray:  # noqa: ANN001
    """Expected (Cramer-Rao) T_ds error RMS [rot, trans] of the same scenario with pixel noise sigma."""
    sim = simulate_calibration(seed, replace(sim_config, pixel_sigma=sigma))
    crb = cramer_rao_bound(sim.calibration_set, sim.truth, sim.joints_calibration, sim.T_st_calibration, sigma)
    return np.array([crb.rotation_rms, crb.translation_rms])


def _end_to_end(tmp: Path, target: str, fmt: str, n: int, seed: int, storage: str = "sqlite3") -> dict:
    spec = CalibrationSimSpec(target, fmt, seed, n, storage=storage)  # type: ignore[arg-type]
    r = write_calibration_dataset(tmp / "sim", spec)
    out = tmp / "out"
    argv = ["calibrate", str(r.data), "--camchain", str(r.camchain), "--target", str(r.target)]
    argv += ["--gimbal", str(r.gimbal), "--out", str(out), "--quiet"]
    assert main(argv) == 0
    cal = load_calibration(out / "calibration.yaml")
    stamps, thetas = read_joint_angles_csv(out / "joint_angles.csv")
    gt = load_ground_truth(r.ground_truth)
    rendered = _rms(T_ds_errors(gt.kinematics, gt.theta_at(stamps), cal, thetas))
    summary = json.loads((out / "summary.json").read_text())
    sigma = summary["reprojection_error_px"]["all"]["rms_per_axis"]
    bound = _bound(r.sim.config, seed, sigma)
    paper_noise = _corner_level(r.sim.config, seed, 0.4)
    print(
        f"\n{target} {fmt}: {len(stamps)}/{n} snapshots, detection noise {sigma:.3f} px/axis; T_ds RMS rendered "
        f"rot {rendered[0]:.3e} rad trans {rendered[1]:.3e} m; expected corner-level at {sigma:.3f} px (CRB) rot "
        f"{bound[0]:.3e} trans {bound[1]:.3e} (ratio {rendered[0] / bound[0]:.2f} / {rendered[1] / bound[1]:.2f}); "
        f"corner-level at 0.4 px rot {paper_noise[0]:.3e} trans {paper_noise[1]:.3e} "
        f"(ratio {rendered[0] / paper_noise[0]:.3f} / {rendered[1] / paper_noise[1]:.3f})"
    )
    assert 0.005 < sigma < 0.2  # sub-pixel detection on blurred, noisy renderings
    assert np.all(rendered <= RATIO * paper_noise)
    assert np.all(rendered <= RATIO * bound)
    return {"r": r, "summary": summary, "n_used": len(stamps)}


@pytest.mark.slow
def test_chessboard_folder_full_scenario(tmp_path: Path) -> None:
    """81 snapshots, image folder: the paper's calibration set size."""
    res = _end_to_end(tmp_path, "checkerboard", "folder", 81, seed=0)
    assert res["n_used"] == 81  # every pair detected (both cameras see the whole board)
    assert res["summary"]["input"]["unpaired_static"] == 0 and res["summary"]["input"]["rejected"] == 0


@pytest.mark.slow
def test_aprilgrid_folder(tmp_path: Path) -> None:
    res = _end_to_end(tmp_path, "aprilgrid", "folder", 36, seed=1)
    assert res["n_used"] == 36
    assert res["summary"]["reprojection_error_px"]["all"]["count"] == 36 * 2 * 144  # every tag corner found


@pytest.mark.slow
def test_chessboard_ros1_bag(tmp_path: Path) -> None:
    res = _end_to_end(tmp_path, "checkerboard", "ros1", 25, seed=2)
    assert res["n_used"] == 25 and res["summary"]["input"]["layout"] == "ros1_bag"


@pytest.mark.slow
@pytest.mark.parametrize("storage", ["mcap"])
def test_aprilgrid_ros2_bag(tmp_path: Path, storage: str) -> None:
    res = _end_to_end(tmp_path, "aprilgrid", "ros2", 25, seed=3, storage=storage)
    assert res["n_used"] == 25 and res["summary"]["input"]["layout"] == "ros2_bag"
    assert res["summary"]["reprojection_error_px"]["all"]["count"] == 25 * 2 * 144
