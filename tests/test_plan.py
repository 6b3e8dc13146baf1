"""Next-best-view planning (dcc_fg.planning.plan), --range / --tolerance parsing, and ``dcc-fg plan``
end to end on a small rendered calibration."""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest
import yaml

from dcc_fg.calibrate import CalibrationOptions, calibrate
from dcc_fg.cli import main
from dcc_fg.data import CalibrationDataset, Observation, Snapshot
from dcc_fg.planning.plan import _candidate_factors, plan_snapshots, view_factors
from dcc_fg.planning.predict import (
    INFORMATION_FILE,
    KinematicsInformation,
    accuracy_over_range,
    kinematics_information,
    predict,
    scaled_pinv,
)
from dcc_fg.planning.range_spec import Tolerance, default_range, parse_range, parse_tolerance
from dcc_fg.sim.calibration_scene import SceneConfig, SimulatedCalibration, simulate_calibration

DEG = np.pi / 180.0


# ------------------------------------------------------------------ option strings


def test_range_and_tolerance_parse() -> None:
    r = parse_range("-30:30, -20:45", 2)
    assert np.allclose(np.degrees(r), [[-30, 30], [-20, 45]])
    assert np.allclose(np.degrees(parse_range("60:120deg", 1)), [[60, 120]])
    t = parse_tolerance("1mrad,1mm")
    assert np.isclose(t.rotation, 1e-3) and np.isclose(t.translation, 1e-3)
    t = parse_tolerance("2 mm, 0.1deg")  # either order, units decide
    assert np.isclose(t.rotation, 0.1 * DEG) and np.isclose(t.translation, 2e-3)
    assert np.isclose(parse_tolerance("500urad,0.5cm").translation, 5e-3)


@pytest.mark.parametrize(
    ("text", "n", "message"),
    [
        ("-30:30", 2, "1 joint range"),
        ("-30:30,10", 2, "joint 2 '10' is not lo:hi"),
        ("30:-30", 1, "needs lo < hi"),
        ("0:400", 1, "more than one turn"),
        ("a:b", 1, "is not lo:hi"),
        ("", 1, "empty"),
    ],
)
def test_bad_range_strings_name_the_option(text: str, n: int, message: str) -> None:
    with pytest.raises(ValueError, match="--range") as exc:
        parse_range(text, n)
    assert message in str(exc.value)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("1mrad", "expected two values"),
        ("1mrad,2mrad", "one rotation and one translation"),
        ("1mrad,1furlong", "unit 'furlong' is not one of"),
        ("-1mrad,1mm", "must be a positive number"),
        ("1,1mm", "is not a number with a unit"),
        ("0mrad,1mm", "must be a positive number"),
    ],
)
def test_bad_tolerance_strings_name_the_option(text: str, message: str) -> None:
    with pytest.raises(ValueError, match="--tolerance") as exc:
        parse_tolerance(text)
    assert message in str(exc.value)


def test_default_range_is_the_data_plus_a_margin() -> None:
    th = np.radians([[10.0, -5.0], [50.0, 5.0]])
    r = np.degrees(default_range(th))
    assert np.allclose(r, [[6.0, 54.0], [-7.0, 7.0]])  # 10 % of 40 deg; at least 2 deg


# ------------------------------------------------------------------ planning


@lru_cache(maxsize=2)
def _start(L: int) -> tuple[SimulatedCalibration, KinematicsInformation]:
    sim = simulate_calibration(4, SceneConfig(n_joints=L, n_calibration=10, n_validation=0))
    res = calibrate(sim.calibration_set, sim.truth, CalibrationOptions())
    return sim, kinematics_information(res, sim.calibration_set)


def test_candidate_update_is_the_snapshots_information() -> None:
    """The planner's rank update U U^T equals the Schur complement (joint angles eliminated) of the
    candidate's information J^T Lambda J on (kin, theta), and the Woodbury covariance after a pick equals
    the pseudo-inverse of the updated information."""
    _, info = _start(2)
    th = np.radians([[70.0, 10.0]])
    pred = predict(info, th)
    U = _candidate_factors(pred)[0]
    Jx = np.concatenate([pred.J_kin[0], pred.J_theta[0]], axis=1)
    H = Jx.T @ pred.view_info[0] @ Jx
    nf = pred.J_kin.shape[2]
    schur = H[:nf, :nf] - H[:nf, nf:] @ np.linalg.solve(H[nf:, nf:], H[nf:, :nf])
    assert np.allclose(U @ U.T, schur, rtol=1e-7, atol=1e-9 * np.abs(schur).max())
    # the planner's prediction after its pick equals a fresh prediction from the updated information
    plan = plan_snapshots(info, default_range(info.joint_angles), Tolerance(1e-6, 1e-6), 1, mode="kinematics")
    p = plan.snapshots[0]
    U = view_factors(info, p.theta[None], np.array(p.target["T_st"])[None])[0]
    new = KinematicsInformation(info.kin, 2, info.free, info.information + U @ U.T, info.view, info.joint_angles)
    acc = accuracy_over_range(new, default_range(info.joint_angles), per_axis=15, cap=1000)
    rot, tra = acc.prediction.sigmas("kinematics")
    assert np.isclose(rot.max(), p.worst_rotation, rtol=1e-6) and np.isclose(tra.max(), p.worst_translation, rtol=1e-6)
    assert np.allclose(scaled_pinv(new.information), new.covariance)


def test_plan_beats_random_snapshots_and_stops() -> None:
    """K planned snapshots reduce the predicted worst 1-sigma over the range more than K random ones
    (with a view); the stopping rule: a met tolerance proposes nothing, a tight one below the snapshot's
    own noise is refused in snapshot mode, an intermediate one stops before K."""
    _, info = _start(2)
    rng_ = default_range(info.joint_angles)
    tight = Tolerance(1e-6, 1e-6)
    plan = plan_snapshots(info, rng_, tight, 4)
    assert len(plan.snapshots) == 4 and not plan.reached
    worst = max(plan.snapshots[-1].worst_rotation / 1e-3, plan.snapshots[-1].worst_translation / 1e-3)
    rng = np.random.default_rng(0)
    cand = rng_[:, 0] + rng.uniform(size=(40, 2)) * (rng_[:, 1] - rng_[:, 0])
    ok = predict(info, cand).placement.ok
    cand = cand[ok][:4]
    U = _candidate_factors(predict(info, cand))
    new = KinematicsInformation(
        info.kin, 2, info.free, info.information + sum(u @ u.T for u in U), info.view, info.joint_angles
    )
    rot, tra = accuracy_over_range(new, rng_, per_axis=15, cap=1000).prediction.sigmas("calibration")
    assert worst < max(rot.max() / 1e-3, tra.max() / 1e-3)
    # stopping rule
    now = plan.now
    loose = Tolerance(2 * now["worst_rotation_mrad"] * 1e-3, 2 * now["worst_translation_mm"] * 1e-3)
    done = plan_snapshots(info, rng_, loose, 4)
    assert done.reached and not done.snapshots and "already meets" in done.reason
    mid = Tolerance(plan.snapshots[1].worst_rotation * 1.0001, plan.snapshots[1].worst_translation * 1.0001)
    stop = plan_snapshots(info, rng_, mid, 10)
    assert stop.reached and len(stop.snapshots) <= 2
    floor = plan_snapshots(info, rng_, tight, 4, mode="snapshot")
    assert not floor.snapshots and "below a single snapshot's own precision" in floor.reason
    with pytest.raises(ValueError, match="--objective"):
        plan_snapshots(info, rng_, tight, 2, objective="median")
    with pytest.raises(ValueError, match="--k"):
        plan_snapshots(info, rng_, tight, 0)


@pytest.mark.parametrize("L", [1, 2])
def test_the_planned_target_poses_beat_the_facing_pose(L: int) -> None:
    """Where to hold the target matters: the plan's snapshots with its chosen target poses reduce the
    predicted worst 1-sigma over the range more than the same joint angles with the board facing both
    cameras (place_targets, the pose a planner without a pose choice would propose)."""
    _, info = _start(L)
    rng_ = default_range(info.joint_angles)
    plan = plan_snapshots(info, rng_, Tolerance(1e-6, 1e-6), 4)
    th = np.array([p.theta for p in plan.snapshots])
    chosen = view_factors(info, th, np.array([p.target["T_st"] for p in plan.snapshots]))
    facing = _candidate_factors(predict(info, th))

    def worst_after(U: np.ndarray) -> float:
        new = KinematicsInformation(
            info.kin, L, info.free, info.information + sum(u @ u.T for u in U), info.view, info.joint_angles
        )
        rot, tra = accuracy_over_range(new, rng_, per_axis=15, cap=1000).prediction.sigmas("calibration")
        return max(float(np.nanmax(rot)) / 1e-3, float(np.nanmax(tra)) / 1e-3)

    assert worst_after(chosen) < worst_after(facing)
    assert np.isclose(
        worst_after(chosen),
        max(plan.snapshots[-1].worst_rotation, plan.snapshots[-1].worst_translation) / 1e-3,
        rtol=0.05,
    )


def _simulate_at(
    sim: SimulatedCalibration, info: KinematicsInformation, thetas: np.ndarray, poses: np.ndarray, seed: int
) -> list:
    """Corner-level snapshots at true joint angles with the target at ``poses`` (T_st, where the plan
    says; noise 0.4 px)."""
    rng = np.random.default_rng(seed)
    out = []
    for k, (th, T_st) in enumerate(zip(thetas, poses, strict=True)):
        T_ds = sim.truth.T_ds(th)
        pts = info.view.target_points
        p_s = pts @ T_st[:3, :3].T + T_st[:3, 3]
        p_d = p_s @ T_ds[:3, :3].T + T_ds[:3, 3]
        ids = np.arange(len(pts))
        uv_s = info.view.static_camera.project(p_s, False)[0] + rng.normal(scale=0.4, size=(len(ids), 2))
        uv_d = info.view.dynamic_camera.project(p_d, False)[0] + rng.normal(scale=0.4, size=(len(ids), 2))
        out.append(Snapshot(10**12 + k, Observation(ids, uv_s), Observation(ids, uv_d), th.copy()))
    return out


def test_following_the_plan_gives_the_predicted_accuracy() -> None:
    """Simulate the planned snapshots (true angles: the planned ones, the simulation's joint-angle
    convention is the calibration's up to the gauge offsets, which calibrate from the truth removes),
    recalibrate: the new calibration's predicted worst 1-sigma over the range is what the plan predicted
    (first order, within 25 %)."""
    sim, info = _start(2)
    rng_ = default_range(info.joint_angles)
    plan = plan_snapshots(info, rng_, Tolerance(1e-6, 1e-6), 4)
    planned = np.array([s.theta for s in plan.snapshots])
    data = sim.calibration_set
    poses = np.array([s.target["T_st"] for s in plan.snapshots])
    snaps = list(data.snapshots) + _simulate_at(sim, info, planned, poses, 7)
    data2 = CalibrationDataset(data.static_camera, data.dynamic_camera, data.target_points, snaps, "planned")
    res2 = calibrate(data2, sim.truth, CalibrationOptions())
    info2 = kinematics_information(res2, data2)
    rot, tra = accuracy_over_range(info2, rng_, per_axis=15, cap=1000).prediction.sigmas("calibration")
    last = plan.snapshots[-1]
    assert rot.max() == pytest.approx(last.worst_rotation, rel=0.25)
    assert tra.max() == pytest.approx(last.worst_translation, rel=0.25)
    assert rot.max() < plan.now["worst_rotation_mrad"] * 1e-3


# ------------------------------------------------------------------ command line


def test_plan_command_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """simulate (rendered, 10 pairs) -> calibrate (writes kinematics_information.npz and the accuracy
    summary) -> plan (plan.yaml schema, figure, printed list); bad options exit 2 naming the option."""
    sim, cal, out = tmp_path / "sim", tmp_path / "cal", tmp_path / "plan"
    assert main(["simulate", "calibration", "--snapshots", "10", "--format", "folder", "--out", str(sim), "-q"]) == 0
    argv = ["calibrate", str(sim / "images"), "--camchain", str(sim / "camchain.yaml"), "--target",
            str(sim / "target.yaml"), "--gimbal", str(sim / "gimbal.yaml"), "--search", "single",
            "--out", str(cal)]  # fmt: skip
    assert main([*argv, "-q"]) == 0
    assert (cal / INFORMATION_FILE).exists()
    summary = json.loads((cal / "summary.json").read_text())
    acc = summary["accuracy_over_range"]
    for mode in ("snapshot", "calibration", "kinematics"):
        assert acc[mode]["worst_rotation_mrad"] >= acc[mode]["mean_rotation_mrad"] > 0
        assert acc[mode]["worst_translation_mm"] >= acc[mode]["mean_translation_mm"] > 0
    assert acc["range_source"] == "data range plus margin" and len(acc["range_deg"]) == 2
    code = main(["plan", str(cal), "--range=60:120,-15:15", "--tolerance", "1urad,1um", "--k", "3", "--out", str(out)])
    assert code == 0
    printed = capsys.readouterr().out
    assert "  1. theta_1 = " in printed and "NOT YET" in printed
    doc = yaml.safe_load((out / "plan.yaml").read_text())
    assert doc["format"] == "dcc-fg plan 1" and doc["objective"] == "worst" and doc["prediction"] == "calibration"
    assert doc["range_deg"] == [[60.0, 120.0], [-15.0, 15.0]]
    assert doc["tolerance"] == {"rotation_mrad": pytest.approx(1e-3), "translation_mm": pytest.approx(1e-3)}
    assert len(doc["snapshots"]) == 3 and doc["stop"]["tolerance_reached"] is False
    for i, s in enumerate(doc["snapshots"]):
        assert s["index"] == i + 1 and len(s["joint_angles_deg"]) == 2
        assert np.allclose(np.radians(s["joint_angles_deg"]), s["joint_angles_rad"], atol=1e-6)
        assert all(60.0 - 1e-9 <= s["joint_angles_deg"][0] <= 120.0 + 1e-9 for s in doc["snapshots"])
        t = s["target"]
        assert 0.3 < t["distance_m"] < 3.0 and 0.0 <= t["tilt_deg"] < 60.0 and np.array(t["T_st"]).shape == (4, 4)
        assert s["predicted_after"]["worst_rotation_mrad"] <= doc["predicted_now"]["worst_rotation_mrad"]
    assert (out / "accuracy.png").stat().st_size > 1000
    # bad options: exit 2, one line naming the option
    assert main(["plan", str(cal), "--range", "10:0,0:1", "--out", str(tmp_path / "p2")]) == 2
    assert "--range" in capsys.readouterr().err
    assert main(["plan", str(cal), "--tolerance", "1mm", "--out", str(tmp_path / "p3")]) == 2
    assert "--tolerance" in capsys.readouterr().err
    assert main(["plan", str(sim), "--out", str(tmp_path / "p4")]) == 2
    assert INFORMATION_FILE in capsys.readouterr().err
