"""Health checks wired into the commands (issue 13, item 1): exit code 3 and nothing written for an
unhealthy result; ``--accept-unhealthy`` writes it marked ``health.healthy: false``.

The health functions are replaced by fixed reports (their thresholds are tested in
tests/test_health.py) and the estimators by cached results of small simulated problems, so these
cases test the wiring: what is printed, the exit code and what is (not) written.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

import dcc_fg.commands.calibrate as calibrate_cmd
import dcc_fg.commands.vio as vio_cmd
from dcc_fg.calibrate import CalibrationOptions, CalibrationResult, calibrate
from dcc_fg.cli import build_parser, main
from dcc_fg.commands.calibrate import CalibrateConfig, CalibrationInputs, run_calibrate
from dcc_fg.data.vio import ImuConfig
from dcc_fg.io.output_set import MANIFEST
from dcc_fg.io.tum import write_tum
from dcc_fg.sim.calibration_scene import SceneConfig, SimulatedCalibration, simulate_calibration
from dcc_fg.sim.trajectory import default_static_mount, flight_calibration
from dcc_fg.util.health import EXIT_UNHEALTHY, HealthCheck, HealthReport, UnhealthyResultError
from dcc_fg.vio.backend import VioResult


def unhealthy(subject: str) -> HealthReport:
    report = HealthReport(subject)
    report.add(HealthCheck("convergence", True, "12 iterations"))
    report.add(HealthCheck("residuals.dynamic", False, "residuals 10.4 px RMS for 0.4 px noise", "try --joints 2",
                           10.4 / 0.4, 1.5))  # fmt: skip
    report.add(HealthCheck("joint_range", False, "joint 1 spans 40 rad", "joints.csv in radians"))
    return report


def healthy(subject: str) -> HealthReport:
    return HealthReport(subject, [HealthCheck("convergence", True, "12 iterations", value=12, threshold=500)])


def snapshot(root: Path) -> dict[str, tuple[bytes, int] | None]:
    if not root.exists():
        return {}
    return {
        str(p.relative_to(root)): (p.read_bytes(), p.stat().st_mtime_ns) if p.is_file() else None
        for p in sorted(root.rglob("*"))
    }


# ---------------------------------------------------------------------------------------------- calibrate / validate


@pytest.fixture(scope="module")
def small() -> tuple[SimulatedCalibration, CalibrationResult]:
    sim = simulate_calibration(1, SceneConfig(n_calibration=8, n_validation=1))
    return sim, calibrate(sim.calibration_set, sim.initial, CalibrationOptions())


@pytest.fixture
def cal_run(monkeypatch: pytest.MonkeyPatch, small, tmp_path: Path) -> dict[str, Any]:  # noqa: ANN001
    """calibrate/validate with the loading and estimator replaced; ``state['health']`` is returned by
    calibration_health, whose keyword arguments are recorded in ``state['calls']``."""
    sim, result = small
    state: dict[str, Any] = {"health": healthy("calibration"), "calls": []}

    def load(inputs: Any, camchain: Any, reader: Any, progress: bool, report: dict[str, Any]) -> Any:
        report["pairing"] = {"pairs": 8}
        return sim.calibration_set

    def health(**kwargs: Any) -> HealthReport:
        state["calls"].append(kwargs)
        return state["health"]

    monkeypatch.setattr(calibrate_cmd, "load_calibration_data", load)
    monkeypatch.setattr(calibrate_cmd, "initial_values", lambda inputs, init, mode, data: (sim.initial, data))
    monkeypatch.setattr(calibrate_cmd, "load_calibration", lambda path: sim.initial)
    monkeypatch.setattr(calibrate_cmd, "calibrate", lambda *a, **k: result)
    monkeypatch.setattr(calibrate_cmd, "calibration_health", health)
    data = tmp_path / "data"
    data.mkdir()
    files = {}
    for name in ("camchain", "target", "gimbal"):
        files[name] = tmp_path / f"{name}.yaml"
        files[name].write_text(f"{name}: input\n")
    state["argv"] = ["calibrate", str(data), *(x for k, v in files.items() for x in (f"--{k}", str(v))), "-q"]
    state["data"], state["files"] = data, files
    return state


def test_unhealthy_calibration_exits_3_and_writes_nothing(cal_run, tmp_path, capsys) -> None:  # noqa: ANN001
    cal_run["health"] = unhealthy("calibration")
    out = tmp_path / "out"
    assert main([*cal_run["argv"], "--out", str(out)]) == EXIT_UNHEALTHY == 3
    err = capsys.readouterr().err
    assert err.startswith("dcc-fg calibrate: error: the calibration failed 2 health checks; nothing was written")
    assert "  - residuals.dynamic: residuals 10.4 px RMS for 0.4 px noise (try: try --joints 2)" in err
    assert "  - joint_range: joint 1 spans 40 rad (try: joints.csv in radians)" in err
    assert "--accept-unhealthy" in err and "convergence" not in err  # passed checks are not listed
    assert not out.exists() and not [p for p in tmp_path.iterdir() if "dcc_fg" in p.name]
    # the health check saw the result, the data and the reader's report (pairing statistics)
    (call,) = cal_run["calls"]
    assert set(call) == {"result", "data", "reader_report"} and call["reader_report"]["pairing"] == {"pairs": 8}


def test_unhealthy_rerun_keeps_the_previous_result(cal_run, tmp_path, capsys) -> None:  # noqa: ANN001
    out = tmp_path / "out"
    assert main([*cal_run["argv"], "--out", str(out)]) == 0
    before = snapshot(out)
    cal_run["health"] = unhealthy("calibration")
    assert main([*cal_run["argv"], "--out", str(out)]) == 3
    assert snapshot(out) == before


def test_accept_unhealthy_writes_and_marks_it(cal_run, tmp_path, capsys) -> None:  # noqa: ANN001
    cal_run["health"] = unhealthy("calibration")
    out = tmp_path / "out"
    assert main([*cal_run["argv"], "--out", str(out), "--accept-unhealthy"]) == 0
    err = capsys.readouterr().err
    warnings = [ln for ln in err.splitlines() if "unhealthy calibration accepted" in ln]
    assert len(warnings) == 2 and "residuals.dynamic" in warnings[0] and "joint_range" in warnings[1]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["health"]["healthy"] is False
    assert summary["health"]["failures"] == [
        "residuals.dynamic: residuals 10.4 px RMS for 0.4 px noise", "joint_range: joint 1 spans 40 rad",
    ]  # fmt: skip
    assert summary["health"]["checks"][1]["value"] == pytest.approx(26.0)
    assert summary["options"]["output"]["accept_unhealthy"] is True
    assert (out / "calibration.yaml").is_file() and (out / MANIFEST).is_file()


def test_accept_unhealthy_from_a_config_file(cal_run, tmp_path, capsys) -> None:  # noqa: ANN001
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(yaml.safe_dump({"output": {"accept_unhealthy": True}}))
    cal_run["health"] = unhealthy("calibration")
    out = tmp_path / "out"
    assert main([*cal_run["argv"], "--out", str(out), "--config", str(cfg)]) == 0
    assert json.loads((out / "summary.json").read_text())["health"]["healthy"] is False


def test_healthy_run_records_its_health(cal_run, tmp_path, capsys) -> None:  # noqa: ANN001
    out = tmp_path / "out"
    assert main([*cal_run["argv"], "--out", str(out)]) == 0
    health = json.loads((out / "summary.json").read_text())["health"]
    assert health == {
        "healthy": True,
        "failures": [],
        "warnings": [],
        "checks": [healthy("calibration").checks[0].to_dict()],
    }
    assert "accepted" not in capsys.readouterr().err


def test_a_warning_is_logged_and_recorded_but_the_run_stays_healthy(cal_run, tmp_path, capsys) -> None:  # noqa: ANN001
    report = healthy("calibration")
    report.add(HealthCheck("residuals.snapshots", False, "3 of 30 snapshots fit far worse", "drop them",
                           3.0, 2.0, severity="warning"))  # fmt: skip
    cal_run["health"] = report
    out = tmp_path / "out"
    assert main([*cal_run["argv"], "--out", str(out)]) == 0
    assert "calibration health warning: residuals.snapshots: 3 of 30" in capsys.readouterr().err
    health = json.loads((out / "summary.json").read_text())["health"]
    assert health["healthy"] is True and health["failures"] == []
    assert health["warnings"] == ["residuals.snapshots: 3 of 30 snapshots fit far worse"]
    assert health["checks"][1]["severity"] == "warning"


def test_unhealthy_validation(cal_run, tmp_path, capsys) -> None:  # noqa: ANN001
    cal_run["health"] = unhealthy("validation")
    out = tmp_path / "val"
    argv = ["validate", str(cal_run["data"]), "--calibration", str(cal_run["files"]["gimbal"]), "--camchain",
            str(cal_run["files"]["camchain"]), "--out", str(out), "-q"]  # fmt: skip
    assert main(argv) == 3
    assert "the validation failed 2 health checks" in capsys.readouterr().err and not out.exists()
    assert main([*argv, "--accept-unhealthy"]) == 0
    assert json.loads((out / "summary.json").read_text())["health"]["healthy"] is False


def test_python_api_raises_unhealthy(cal_run, tmp_path) -> None:  # noqa: ANN001
    cal_run["health"] = unhealthy("calibration")
    files = cal_run["files"]
    inputs = CalibrationInputs(str(cal_run["data"]), str(files["camchain"]), str(files["target"]), str(files["gimbal"]))
    with pytest.raises(UnhealthyResultError) as info:
        run_calibrate(inputs, tmp_path / "out", CalibrateConfig(), quiet=True)
    assert info.value.report.healthy is False and not (tmp_path / "out").exists()


def test_help_documents_exit_codes_and_outputs() -> None:
    parser = build_parser()
    text = " ".join(parser.format_help().split())
    assert "3 the result failed its health checks" in text and "130 interrupted" in text and "0 success" in text
    sub = parser._subparsers._group_actions[0].choices  # type: ignore[union-attr]
    for name in ("calibrate", "validate", "vio", "demo"):
        help_text = " ".join(sub[name].format_help().split())
        assert "staging folder" in help_text and ".dcc_fg_manifest.json" in help_text, name
    for name in ("calibrate", "validate", "vio"):
        assert "--accept-unhealthy" in sub[name].format_help()


# ---------------------------------------------------------------------------------------------- vio


@pytest.fixture
def vio_run(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> dict[str, Any]:
    """``dcc-fg vio`` on a stand-in bag: run_vio_bag returns a straight-line trajectory, vio_health
    ``state['health']``."""
    cal = flight_calibration()
    d = cal.to_dict()
    d["imu"] = ImuConfig(T_sI=default_static_mount()).to_dict()
    cal_path = tmp_path / "flight" / "calibration.yaml"
    cal_path.parent.mkdir()
    cal_path.write_text(yaml.safe_dump(d, sort_keys=False))
    bag = tmp_path / "flight" / "flight.bag"
    bag.write_bytes(b"bag")
    n = 40
    t_ns = 1_600_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 100_000_000
    T = np.repeat(np.eye(4)[None], n, axis=0)
    T[:, 0, 3] = np.linspace(0.0, 4.0, n)
    T[:, 1, 3] = np.sin(np.linspace(0.0, 3.0, n))
    theta = np.zeros((n, cal.n_joints))
    result = VioResult(t_ns, T, np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3)), theta, "dcc", {"landmarks": 7})
    state: dict[str, Any] = {"health": healthy("trajectory"), "T": T, "t_ns": t_ns}
    monkeypatch.setattr(vio_cmd, "run_vio_bag", lambda *a, **k: (result, {"frames": n}))
    monkeypatch.setattr(vio_cmd, "vio_health", lambda result, imu, options: state["health"])
    state["argv"] = ["vio", str(bag), "--calibration", str(cal_path), "-q"]
    return state


def test_unhealthy_vio_exits_3_and_accept_writes(vio_run, tmp_path, capsys) -> None:  # noqa: ANN001
    vio_run["health"] = unhealthy("trajectory")
    out = tmp_path / "vio"
    assert main([*vio_run["argv"], "--out", str(out)]) == 3
    err = capsys.readouterr().err
    assert "dcc-fg vio: error:" in err and "the trajectory failed 2 health checks" in err and not out.exists()
    assert main([*vio_run["argv"], "--out", str(out), "--accept-unhealthy"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["health"]["healthy"] is False and summary["options"]["output"]["accept_unhealthy"] is True
    assert sorted(json.loads((out / MANIFEST).read_text())["files"]) == [
        "joint_angles.csv", "summary.json", "trajectory.tum",
    ]  # fmt: skip


def test_vio_rerun_removes_the_stale_evaluation(vio_run, tmp_path, capsys) -> None:  # noqa: ANN001
    out = tmp_path / "vio"
    assert main([*vio_run["argv"], "--out", str(out)]) == 0
    assert json.loads((out / "summary.json").read_text())["health"]["healthy"] is True
    gt = tmp_path / "gt.tum"
    write_tum(gt, vio_run["t_ns"], vio_run["T"])
    assert main(["evaluate", str(out), "--ground-truth", str(gt)]) == 0
    manifest = json.loads((out / MANIFEST).read_text())
    assert manifest["command"] == "vio" and "evaluation.json" in manifest["attached"]["evaluate"]
    assert (out / "evaluation.json").is_file() and (out / "vio_trajectory.png").is_file()
    # evaluate refuses a ground truth that its outputs would replace, and a folder of another command
    capsys.readouterr()
    before = snapshot(out)
    assert main(["evaluate", str(out), "--ground-truth", str(out / "evaluation.json")]) == 2
    assert "evaluation.json" in capsys.readouterr().err and snapshot(out) == before
    # a new vio run into the folder removes the evaluation of the previous trajectory
    assert main([*vio_run["argv"], "--out", str(out)]) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == [MANIFEST, "joint_angles.csv", "summary.json", "trajectory.tum"]


def test_vio_out_is_the_flight_folder(vio_run, tmp_path, capsys) -> None:  # noqa: ANN001
    """``vio F/flight.bag --calibration F/calibration.yaml --out F``: refused before the run."""
    flight = tmp_path / "flight"
    before = snapshot(flight)
    assert main([*vio_run["argv"], "--out", str(flight)]) == 2
    err = capsys.readouterr().err
    assert "holds the input" in err and str(flight) in err and snapshot(flight) == before
