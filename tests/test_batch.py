"""``dcc-fg batch``: a small study on a local Dask cluster of 2 workers, run twice; study-file validation.

The study: one simulated 8 s flight (one 16 m x 8 m loop, 320x240 images) in dcc, scc (the same body
trajectory with the gimbal locked: a second flight) and mono, plus a recording that is a garbage
file. The first invocation must finish the three runs and report the broken one with its error; the
second must reuse the three finished runs (their files untouched) and only retry the broken one. The
table's numbers must be those of each run's ``summary.json`` and ``evaluation.json``.
"""

from __future__ import annotations

import json
import math
import textwrap
from pathlib import Path
from typing import Any

import pytest
import yaml
from distributed import LocalCluster

from dcc_fg import cli
from dcc_fg.batch import BatchOptions, load_study, run_study
from dcc_fg.batch.study import spec_hash
from dcc_fg.batch.table import read_csv
from dcc_fg.data.vio import ImuConfig
from dcc_fg.sim.flight_bag import scaled_flight_calibration
from dcc_fg.sim.trajectory import default_static_mount
from dcc_fg.util.config import ConfigError

STUDY = """\
out: out
defaults:
  options: {keyframe_every: 3}
runs:
  - name: loop
    simulate: {kind: flight, duration: 8, seed: 1, scale: 0.5}
    modes: [dcc, scc, mono]
  - name: broken
    bag: corrupt.bag
    calibration: calibration.yaml
    ground_truth: ground_truth.tum
    modes: [dcc]
"""


def calibration_text() -> str:
    """A valid flight calibration with its imu: section (what simulate flight writes)."""
    d = scaled_flight_calibration(0.5).to_dict()
    d["imu"] = ImuConfig(T_sI=default_static_mount()).to_dict()
    return yaml.safe_dump(d, sort_keys=False)


def write_inputs(folder: Path, study: str = STUDY) -> Path:
    """The study file and the broken run's inputs: a garbage bag, a valid calibration, a ground truth."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "corrupt.bag").write_bytes(bytes(range(256)) * 20)
    (folder / "calibration.yaml").write_text(calibration_text())
    (folder / "ground_truth.tum").write_text("1.0 0 0 0 0 0 0 1\n")
    path = folder / "study.yaml"
    path.write_text(study)
    return path


@pytest.fixture(scope="module")
def study_runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The study run twice: first through the Python API, then through the command line."""
    folder = tmp_path_factory.mktemp("batch")
    path = write_inputs(folder)
    first = run_study(load_study(path), BatchOptions(folder / "out", workers=2))
    finished = {r["run_id"]: (Path(r["folder"]) / "result.json").stat().st_mtime_ns for r in first.rows
                if r["status"] == "ok"}  # fmt: skip
    return {"folder": folder, "path": path, "first": first, "mtimes": finished}


def test_study_runs_every_run_and_reports_the_broken_one(study_runs: dict[str, Any]) -> None:
    first = study_runs["first"]
    by = {(r["name"], r["mode"]): r for r in first.rows}
    assert list(by) == [("loop", "dcc"), ("loop", "scc"), ("loop", "mono"), ("broken", "dcc")]
    for mode in ("dcc", "scc", "mono"):
        row = by[("loop", mode)]
        assert row["status"] == "ok", row
        assert 0 < row["normalized_translation_rmse_percent"] < 1.0
        assert 0 < row["real_time_factor"] < 5
    assert len(by[("loop", "dcc")]["joint_rmse_rad"]) == 2
    assert max(by[("loop", "dcc")]["joint_rmse_rad"]) < 0.02
    broken = by[("broken", "dcc")]
    assert broken["status"] == "failed" and broken["error"]
    assert "corrupt.bag: truncated or corrupt bag" in broken["error"]
    assert (first.executed, first.failed, first.reused, first.simulated) == (4, 1, 0, 2)
    assert first.workers == 2
    assert first.serial_s > 0 and first.wall_s > 0 and first.speedup is not None


def test_table_files_hold_the_runs_own_numbers(study_runs: dict[str, Any]) -> None:
    out = study_runs["folder"] / "out"
    for name in ("results.csv", "results.md", "results_rmse.png"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0
    rows = read_csv(out / "results.csv")
    assert [(r["name"], r["mode"], r["status"]) for r in rows] == [
        ("loop", "dcc", "ok"), ("loop", "scc", "ok"), ("loop", "mono", "ok"), ("broken", "dcc", "failed")
    ]  # fmt: skip
    for row in rows[:3]:
        summary = json.loads((Path(row["folder"]) / "summary.json").read_text())
        evaluation = json.loads((Path(row["folder"]) / "evaluation.json").read_text())
        assert summary["mode"] == row["mode"]
        assert float(row["real_time_factor"]) == summary["real_time_factor"]
        assert float(row["norm_transl_rmse_percent"]) == evaluation["normalized_translation_rmse_percent"]
        assert float(row["ape_rmse_m"]) == evaluation["ape_rmse_m"]
        if row["mode"] == "dcc":
            assert [float(row["joint_1_rmse_rad"]), float(row["joint_2_rmse_rad"])] == evaluation["joint_rmse_rad"]
        else:
            assert row["joint_1_rmse_rad"] == ""
    assert "truncated or corrupt bag" in rows[3]["error"]
    markdown = (out / "results.md").read_text()
    assert "| broken | dcc | failed: " in markdown
    assert f"{float(rows[0]['norm_transl_rmse_percent']):.4f}" in markdown
    manifest = json.loads((out / ".dcc_fg_manifest.json").read_text())
    assert manifest["command"] == "batch"


def test_second_invocation_reuses_the_finished_runs(
    study_runs: dict[str, Any], capsys: pytest.CaptureFixture[str]
) -> None:
    folder = study_runs["folder"]
    code = cli.main(["batch", str(study_runs["path"]), "--workers", "2"])
    printed = capsys.readouterr().out
    assert code == 0
    assert "3 runs reused, 1 failed" in printed
    assert "| loop | dcc | ok (reused) |" in printed
    assert "| broken | dcc | failed: " in printed
    assert "wall time" in printed and "serial sum" in printed
    for run_id, mtime in study_runs["mtimes"].items():  # finished runs were not redone
        assert (folder / "out" / "runs" / run_id / "result.json").stat().st_mtime_ns == mtime
    rows = read_csv(folder / "out" / "results.csv")
    assert [r["reused"] for r in rows] == ["True", "True", "True", "False"]
    # --strict: a failed run makes the exit code 1 (the table is still written)
    assert cli.main(["batch", str(study_runs["path"]), "--workers", "1", "--strict", "-q"]) == 1


def test_existing_scheduler_runs_the_study(tmp_path: Path) -> None:
    """``--scheduler ADDRESS``: the runs go to an existing cluster (here a one-worker local one)."""
    study = "runs:\n  - {name: broken, bag: corrupt.bag, calibration: calibration.yaml, ground_truth: ground_truth.tum}"
    path = write_inputs(tmp_path, study)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        result = run_study(load_study(path), BatchOptions(tmp_path / "out", scheduler=cluster.scheduler_address))
    assert [(r["name"], r["mode"], r["status"]) for r in result.rows] == [("broken", "dcc", "failed")]
    assert (tmp_path / "out" / "results.csv").is_file()
    assert (tmp_path / "out" / "logs").is_dir()


def error_of(tmp_path: Path, study: str) -> str:
    path = write_inputs(tmp_path, textwrap.dedent(study))
    with pytest.raises(ConfigError) as info:
        load_study(path)
    text = str(info.value)
    assert text.startswith(str(path)), text
    return text


@pytest.mark.parametrize(
    ("study", "expected"),
    [
        ("out: o\nrun: []\n", "unknown key(s) run"),
        ("runs: []\n", "runs: expected a non-empty list"),
        ("runs:\n  - {name: a, simulate: {duration: 8}, modes: [dcc, stereo]}\n", "runs[0] (a).modes[1]: expected one "
         "of dcc, scc, mono, got 'stereo'"),
        ("runs:\n  - {name: a, simulate: {duration: 8, wind: 3}}\n", "runs[0] (a).simulate: unknown key(s) wind"),
        ("runs:\n  - {name: a, simulate: {duration: 3}}\n", "runs[0] (a).simulate.duration: must exceed 4 s"),
        ("runs:\n  - {name: a, bag: missing.bag, calibration: calibration.yaml, ground_truth: ground_truth.tum}\n",
         "runs[0] (a).bag: "),
        ("runs:\n  - {name: a, bag: corrupt.bag, calibration: calibration.yaml}\n", "runs[0] (a): a bag run needs "
         "'ground_truth'"),
        ("runs:\n  - {name: a, bag: corrupt.bag, simulate: {}, calibration: calibration.yaml}\n", "exactly one of"),
        ("runs:\n  - {name: a, simulate: {}, options: {mode: scc}}\n", "runs[0] (a).options.mode: set by the study"),
        ("runs:\n  - {name: a, simulate: {}, options: {lagg: 2}}\n", "runs[0] (a).options: unknown option(s) lagg"),
        ("runs:\n  - {name: a, simulate: {}, options: {theta_fixed: [1, 2, 3]}, modes: [scc]}\n",
         "runs[0] (a).options.theta_fixed: the simulated gimbal has 2 joints"),
        ("runs:\n  - {name: a, simulate: {}, options: 5}\n", "runs[0] (a).options: expected a mapping, got int 5"),
        ("runs:\n  - {name: a, simulate: {}, vio: {run: {pixel_sigma: -1}}}\n", "runs[0] (a).vio.run: pixel_sigma"),
        ("runs:\n  - {name: a, simulate: {}}\n  - {name: a, simulate: {seed: 2}}\n", "repeated run names: a (dcc)"),
        ("runs:\n  - {name: 'a b', simulate: {}}\n", "runs[0].name: expected a name"),
        ("runs:\n  - {name: a, bag: corrupt.bag, calibration: calibration.yaml, ground_truth: ground_truth.tum, "
         "modes: [scc]}\n", "runs[0] (a).modes: scc needs the locked joint angles"),
    ],
)  # fmt: skip
def test_study_file_errors_name_the_file_and_field(tmp_path: Path, study: str, expected: str) -> None:
    assert expected in error_of(tmp_path, study)


def test_invalid_study_exits_2_before_any_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write_inputs(tmp_path, "runs:\n  - {name: a, simulate: {duration: 8}, modes: [dcc, stereo]}\n")
    assert cli.main(["batch", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert f"dcc-fg batch: error: {path}: runs[0] (a).modes[1]" in err
    assert not (tmp_path / "out").exists()
    path.write_text("runs:\n  - {name: a, simulate: {duration: 8}}\n")
    assert cli.main(["batch", str(path)]) == 2  # no out: in the file and no --out
    assert "give --out" in capsys.readouterr().err


def test_seeds_expand_and_hashes_are_stable(tmp_path: Path) -> None:
    path = write_inputs(tmp_path, "runs:\n  - {name: f, simulate: {duration: 9, seed: [3, 4]}, modes: [dcc, scc]}\n")
    study = load_study(path)
    assert [(t.name, t.mode) for t in study.tasks] == [
        ("f-seed3", "dcc"), ("f-seed3", "scc"), ("f-seed4", "dcc"), ("f-seed4", "scc")
    ]  # fmt: skip
    scc = study.tasks[1]
    assert scc.data.gimbal == "locked" and study.tasks[0].data.gimbal == "moving"  # type: ignore[union-attr]
    assert scc.config.smoother.theta_fixed is not None and len(scc.config.smoother.theta_fixed) == 2
    assert all(math.isfinite(x) for x in scc.config.smoother.theta_fixed)
    assert study.tasks[0].config.run.frontend_worker == "inline"
    again = load_study(path)
    assert [t.run_id for t in again.tasks] == [t.run_id for t in study.tasks]
    assert len({t.spec_hash for t in study.tasks}) == 4
    assert spec_hash({"b": 1, "a": [1.0, 2]}) == spec_hash({"a": [1.0, 2], "b": 1})
    path.write_text("runs:\n  - {name: f, simulate: {duration: 9, seed: [3, 4]}, modes: [dcc, scc], "
                    "options: {lag: 2.0}}\n")  # fmt: skip
    changed = load_study(path)
    assert all(a.spec_hash != b.spec_hash for a, b in zip(study.tasks, changed.tasks, strict=True))
