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

from dcc_fg import load_calibration
from dcc_fg.auto_init import SCREEN_SNAPSHOTS, auto_initialize, pnp_T_ds, rotation_ik_three_joints
from dcc_fg.calibrate import CalibrationOptions, CalibrationResult, calibrate
from dcc_fg.cli import main
from dcc_fg.data import CalibrationDataset
from dcc_fg.init import pose_level_refine
from dcc_fg.io.camchain import CamchainEntry, camchain_to_yaml
from dcc_fg.io.outputs import read_joint_angles_csv
from dcc_fg.sim.calibration_scene import SceneConfig, random_mechanism, simulate_calibration
from dcc_fg.sources.detections import write_detection_csv
from dcc_fg.studies.calibration_accuracy import T_ds_errors, evaluate_against_truth
from dcc_fg.targets import TargetGeometry
from factors import chain

N_GEOMETRIES = 50
N_REQUIRED = 48  # the requirement; 49 converge (geometry 1 is refused as unobservable, below)
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


def test_three_joint_rotation_ik_inverts_the_chain() -> None:
    """Closed-form IK of Rz(t1) Rx(a1) Rz(t2) Rx(a2) Rz(t3) (theta_3 came out negated before), and
    the theta_2 branch: the other branch fits the same rotations with the twists negated."""
    rng = np.random.default_rng(3)
    th = rng.uniform(-1.5, 1.5, size=(20, 3))
    th[:, 1] = np.abs(th[:, 1]) + 0.1
    al = np.array([1.1, -0.6, 0.0])
    Rx1, Rx2 = chain.rot_x(al[0]), chain.rot_x(al[1])
    Q = np.array([chain.rot_z(a) @ Rx1 @ chain.rot_z(b) @ Rx2 @ chain.rot_z(c) for a, b, c in th])
    out, misfit = rotation_ik_three_joints(Q, al, 1.0)
    np.testing.assert_allclose(out, th, atol=1e-9)
    assert np.abs(misfit).max() < 1e-12
    out2, misfit2 = rotation_ik_three_joints(Q, -al, -1.0)
    assert np.abs(misfit2).max() < 1e-12
    np.testing.assert_allclose(out2[:, 1], -th[:, 1], atol=1e-9)


@pytest.mark.slow
def test_two_joint_starts_ranked_on_a_subset_of_many_snapshots() -> None:
    """Above SCREEN_SNAPSHOTS snapshots the L = 2 starts are ranked on a subset; the fit on all of
    them still reaches the optimum of the pose-level fit started from the truth."""
    sim = simulate_calibration(5, SceneConfig(n_calibration=150, n_validation=1))
    assert len(sim.calibration_set.snapshots) > SCREEN_SNAPSHOTS
    T = pnp_T_ds(sim.calibration_set)
    _, _, rms = auto_initialize(sim.calibration_set, 2, T_ds=T)
    free = np.ones(18, dtype=bool)
    free[[2, 5, 15, 16, 17]] = False
    ref = pose_level_refine(sim.truth.kin, 2, T, sim.joints_calibration, free, [1], True)[2]
    assert rms <= ref + 1e-6


@pytest.mark.slow
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
        except ValueError as exc:  # a degenerate draw refused as unobservable (geometry 1, reference run too)
            good = False
            lines.append(f"{g}: error {exc}")
        ok += good
    print("\n".join(lines))
    print(f"{ok}/{N_GEOMETRIES} converged, {time.perf_counter() - t0:.1f} s")
    assert ok >= N_REQUIRED


# L = 1 and L = 3 over seeds of the pinned scenes (81 snapshots each); the seed counts keep this file's
# CI time in budget (L = 3 costs 15-50 s per seed, mostly the two corner-level solves). Measured with
# the variable-projection search of dcc_fg/auto_init.py: L = 3 seeds 0-19 all converge, L = 1 seeds
# 0-9 all converge; before it, 5 of L = 3 seeds 0-9 did.
PINNED_SEEDS = {1: (range(5), 5), 3: (range(6), 5)}  # L: (seeds, required successes)


@pytest.mark.slow
@pytest.mark.parametrize("n_joints", [1, 3])
def test_pinned_mechanisms_converge_without_gimbal_yaml(n_joints: int) -> None:
    seeds, required = PINNED_SEEDS[n_joints]
    ok, lines = 0, []
    t0 = time.perf_counter()
    for seed in seeds:
        t_seed = time.perf_counter()
        sim = simulate_calibration(seed, SceneConfig(n_joints=n_joints, n_validation=1))
        try:
            auto = calibrate_auto(sim.calibration_set, n_joints)
            ref = calibrate(sim.calibration_set, sim.initial, FAST)
            good, r_rot, r_tr = same_accuracy(sim, auto, ref)
            # the automatic start reaches the reference optimum, or a lower one
            good &= auto.final_error <= ref.final_error * (1 + 1e-6)
            lines.append(
                f"L={n_joints} seed {seed}: {good} rot x{r_rot:.3f} tr x{r_tr:.3f} "
                f"cost {auto.final_error:.3f}/{ref.final_error:.3f}, {time.perf_counter() - t_seed:.1f} s"
            )
        except ValueError as exc:
            good = False
            lines.append(f"L={n_joints} seed {seed}: error {exc}")
        ok += good
    print("\n".join(lines))
    print(f"L={n_joints}: {ok}/{len(seeds)} converged, {time.perf_counter() - t0:.1f} s")
    assert ok >= required


def test_cli_calibrate_without_gimbal_yaml(tmp_path, capsys) -> None:
    """`dcc-fg calibrate DETECTIONS --camchain C --joints 2` (no --gimbal): automatic initialization."""
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
