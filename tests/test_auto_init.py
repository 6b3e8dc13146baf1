"""Automatic initialization (no gimbal.yaml): random 2-DOF geometries, L = 1 and L = 3.

Each random mechanism is calibrated twice on the same corners: from the automatic initialization
and from the truth-perturbed initial guess (the "hand-measured" start). Success means the automatic
start reaches the same optimum: per-snapshot T_ds errors within 1.5x of the reference run's.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest

from dcc_fg.auto_init import auto_initialize
from dcc_fg.calibrate import CalibrationOptions, CalibrationResult, calibrate
from dcc_fg.data import CalibrationDataset
from dcc_fg.sim.calibration_scene import SceneConfig, random_mechanism, simulate_calibration
from dcc_fg.sim.evaluation import evaluate_against_truth

N_GEOMETRIES = 50
N_REQUIRED = 48
FAST = CalibrationOptions(compute_covariance=False)


def calibrate_auto(data: CalibrationDataset, n_joints: int) -> CalibrationResult:
    """The `--init auto` path: automatic initial values, then the full corner-level calibration."""
    initial, thetas, _ = auto_initialize(
        replace(data, snapshots=[replace(s, joints=None) for s in data.snapshots]), n_joints
    )
    seeded = replace(data, snapshots=[replace(s, joints=t) for s, t in zip(data.snapshots, thetas, strict=True)])
    return calibrate(seeded, initial, FAST)


def same_accuracy(sim, auto: CalibrationResult, ref: CalibrationResult) -> tuple[bool, float, float]:
    ea = evaluate_against_truth(auto, sim.truth, sim.joints_calibration)
    er = evaluate_against_truth(ref, sim.truth, sim.joints_calibration)
    r_rot, r_tr = ea.rotation_rms / er.rotation_rms, ea.translation_rms / er.translation_rms
    return bool(r_rot <= 1.5 and r_tr <= 1.5), r_rot, r_tr


def test_random_two_joint_geometries_converge_without_gimbal_yaml() -> None:
    rng = np.random.default_rng(2024)
    ok, lines = 0, []
    t0 = time.perf_counter()
    for g in range(N_GEOMETRIES):
        mech = random_mechanism(rng, 2)
        sim = simulate_calibration(100 + g, SceneConfig(n_calibration=25, n_validation=1), mechanism=mech)
        try:
            auto = calibrate_auto(sim.calibration_set, 2)
            ref = calibrate(sim.calibration_set, sim.initial, FAST)
            good, r_rot, r_tr = same_accuracy(sim, auto, ref)
            lines.append(
                f"{g}: {good} rot x{r_rot:.3f} tr x{r_tr:.3f} cost {auto.final_error:.2f}/{ref.final_error:.2f}"
            )
        except ValueError as exc:  # e.g. a degenerate draw refused as unobservable
            good = False
            lines.append(f"{g}: error {exc}")
        ok += good
    print("\n".join(lines))
    print(f"{ok}/{N_GEOMETRIES} converged, {time.perf_counter() - t0:.1f} s")
    assert ok >= N_REQUIRED


@pytest.mark.parametrize("n_joints", [1, 3])
def test_pinned_mechanisms_converge_without_gimbal_yaml(n_joints: int) -> None:
    sim = simulate_calibration(7, SceneConfig(n_joints=n_joints, n_validation=1))
    auto = calibrate_auto(sim.calibration_set, n_joints)
    ref = calibrate(sim.calibration_set, sim.initial, FAST)
    good, r_rot, r_tr = same_accuracy(sim, auto, ref)
    print(f"L={n_joints}: rot x{r_rot:.3f} tr x{r_tr:.3f} cost {auto.final_error:.3f} / {ref.final_error:.3f}")
    assert good
    assert auto.final_error <= ref.final_error * (1 + 1e-6)


def test_cli_calibrate_without_gimbal_yaml(tmp_path, capsys) -> None:
    """`dcc-fg calibrate DETECTIONS --camchain C --joints 2` (no --gimbal): automatic initialization."""
    from dcc_fg import load_calibration
    from dcc_fg.cli import main
    from dcc_fg.io.camchain import CamchainEntry, camchain_to_yaml
    from dcc_fg.io.detections import write_detection_csv
    from dcc_fg.io.outputs import read_joint_angles_csv
    from dcc_fg.sim.evaluation import T_ds_errors
    from dcc_fg.targets import TargetGeometry

    grid = TargetGeometry.aprilgrid(6, 5, 0.06, 0.3)
    sim = simulate_calibration(4, SceneConfig(n_calibration=30, n_validation=1, target=grid))
    data = sim.calibration_set
    root = tmp_path / "detections"
    for cam in ("cam0", "cam1"):
        (root / cam).mkdir(parents=True)
    for s in data.snapshots:
        write_detection_csv(root / "cam0" / f"{s.timestamp_ns}.csv", s.timestamp_ns, s.static, grid)
        write_detection_csv(root / "cam1" / f"{s.timestamp_ns}.csv", s.timestamp_ns, s.dynamic, grid)
    camchain = tmp_path / "camchain.yaml"
    camchain.write_text(
        camchain_to_yaml({"cam0": CamchainEntry(data.static_camera), "cam1": CamchainEntry(data.dynamic_camera)})
    )
    out = tmp_path / "out"
    assert main(["calibrate", str(root), "--camchain", str(camchain), "--out", str(out)]) == 2
    assert "--joints" in capsys.readouterr().err
    assert main(["calibrate", str(root), "--camchain", str(camchain), "--joints", "2", "--out", str(out)]) == 0
    cal = load_calibration(out / "calibration.yaml")
    _, th = read_joint_angles_csv(out / "joint_angles.csv")
    ref = calibrate(data, sim.initial, FAST)
    e_auto = T_ds_errors(sim.truth, sim.joints_calibration, cal, th)
    e_ref = T_ds_errors(sim.truth, sim.joints_calibration, ref.calibration, ref.joint_angles)
    rms = lambda e: np.sqrt(np.mean(np.sum(e * e, axis=1)))  # noqa: E731
    assert rms(e_auto[:, :3]) <= 1.5 * rms(e_ref[:, :3]) and rms(e_auto[:, 3:]) <= 1.5 * rms(e_ref[:, 3:])
