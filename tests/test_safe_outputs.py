"""Safe outputs (issue 13, item 4): every command writes its --out folder as one set.

Each case asserts the exit code, that the message names the culprit (path / option), and that
nothing was written or overwritten (every file's bytes and mtime, and the listing, hidden entries
included, compared before and after). The estimators are replaced by a cached result of a small
simulated problem (8 snapshots), so the cases test the output handling, not the estimators.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

import dcc_fg.commands.calibrate as calibrate_cmd
import dcc_fg.commands.intrinsics as intrinsics_cmd
import dcc_fg.io.output_set as output_set
import dcc_fg.sim.flight_bag as flight_bag
import dcc_fg.sim.write_dataset as write_dataset
from dcc_fg.calibrate import CalibrationOptions, CalibrationResult, calibrate
from dcc_fg.cli import main
from dcc_fg.io.output_set import MANIFEST, DeferredInterrupt, OutputPathError, OutputSet, folder_owner
from dcc_fg.sim.calibration_scene import SceneConfig, SimulatedCalibration, simulate_calibration
from dcc_fg.util.health import HealthReport

Snapshot = dict[str, tuple[bytes, int] | None]


def snapshot(root: Path) -> Snapshot:
    """Every entry under ``root`` (hidden ones included): files -> (bytes, mtime_ns), folders -> None."""
    if not root.exists():
        return {}
    out: Snapshot = {}
    for p in sorted(root.rglob("*")):
        rel = str(p.relative_to(root))
        out[rel] = (p.read_bytes(), p.stat().st_mtime_ns) if p.is_file() else None
    return out


def no_staging_left(*folders: Path) -> bool:
    return not any(
        output_set.STAGING_TAG in p.name or output_set.REPLACED_TAG in p.name
        for f in folders
        if f.exists()
        for p in f.iterdir()
    )


@pytest.fixture(scope="module")
def small() -> tuple[SimulatedCalibration, CalibrationResult]:
    sim = simulate_calibration(1, SceneConfig(n_calibration=8, n_validation=1))
    return sim, calibrate(sim.calibration_set, sim.initial, CalibrationOptions())


@pytest.fixture
def inputs(tmp_path: Path) -> dict[str, Path]:
    """Input files of a calibrate run (never read: the loader is replaced)."""
    data = tmp_path / "data"
    (data / "cam0").mkdir(parents=True)
    (data / "cam1").mkdir()
    files = {"data": data}
    for name in ("camchain", "target", "gimbal"):
        files[name] = tmp_path / "in" / f"{name}.yaml"
        files[name].parent.mkdir(exist_ok=True)
        files[name].write_text(f"{name}: input\n")
    return files


class Pipeline:
    """The calibrate/validate pipeline with the data loading and the estimator replaced."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, small: tuple[SimulatedCalibration, CalibrationResult]):
        self.sim, self.result = small
        self.calls: list[str] = []
        self.health = HealthReport("calibration")
        self.estimator: Callable[..., CalibrationResult] = lambda *a, **k: self.result
        mp = monkeypatch

        def load(*args: Any, **kwargs: Any) -> Any:
            self.calls.append("load")
            return self.sim.calibration_set

        mp.setattr(calibrate_cmd, "load_calibration_data", load)
        mp.setattr(calibrate_cmd, "initial_values", lambda inputs, init, mode, data: (self.sim.initial, data))
        mp.setattr(calibrate_cmd, "load_calibration", lambda path: self.sim.initial)
        mp.setattr(calibrate_cmd, "calibrate", lambda *a, **k: self.estimator(*a, **k))
        mp.setattr(calibrate_cmd, "calibrate_global", lambda *a, **k: self.estimator(*a, **k))
        mp.setattr(calibrate_cmd, "calibration_health", lambda **kw: self.health)

        def figures(out: Path, *args: Any, **kwargs: Any) -> list[Path]:  # quick stand-ins for the real figures
            paths = [out / "calibration_residuals.png", out / "report.pdf"]
            for p in paths:
                p.write_bytes(b"figure")
            return paths

        mp.setattr(calibrate_cmd, "write_calibration_outputs", figures)


@pytest.fixture
def pipeline(monkeypatch: pytest.MonkeyPatch, small: tuple[SimulatedCalibration, CalibrationResult]) -> Pipeline:
    return Pipeline(monkeypatch, small)


def calibrate_argv(inputs: dict[str, Path], out: Path, *extra: str) -> list[str]:
    return [
        "calibrate", str(inputs["data"]), "--camchain", str(inputs["camchain"]), "--target", str(inputs["target"]),
        "--gimbal", str(inputs["gimbal"]), "--out", str(out), "-q", *extra,
    ]  # fmt: skip


def refused(
    argv: list[str], capsys: pytest.CaptureFixture[str], watched: list[Path], *needles: str, code: int = 2
) -> str:
    """Run ``argv``; assert the exit code, the needles in stderr and that nothing under ``watched`` changed."""
    before = [snapshot(w) for w in watched]
    assert main(argv) == code
    err = capsys.readouterr().err
    for needle in needles:
        assert needle in err, f"{needle!r} not in {err!r}"
    assert [snapshot(w) for w in watched] == before
    return err


# ---------------------------------------------------------------------------------------------- before any work


def test_out_is_an_existing_file_fails_before_loading(pipeline: Pipeline, inputs, tmp_path, capsys) -> None:  # noqa: ANN001
    out = tmp_path / "result.txt"
    out.write_text("not a folder\n")
    t0 = time.perf_counter()
    refused(calibrate_argv(inputs, out), capsys, [tmp_path], str(out), "is a file")
    assert pipeline.calls == [] and time.perf_counter() - t0 < 5.0  # refused before any data were read


def test_out_below_a_file_fails_before_loading(pipeline: Pipeline, inputs, tmp_path, capsys) -> None:  # noqa: ANN001
    blocker = tmp_path / "blocker"
    blocker.write_text("x")
    refused(calibrate_argv(inputs, blocker / "sub"), capsys, [tmp_path], str(blocker), "is a file, not a folder")
    assert pipeline.calls == []


@pytest.mark.parametrize("where", ["same", "inside"])
def test_out_is_or_is_inside_the_data_folder(pipeline: Pipeline, inputs, tmp_path, capsys, where) -> None:  # noqa: ANN001
    out = inputs["data"] if where == "same" else inputs["data"] / "calibration"
    needle = "is the input DATA" if where == "same" else "is inside the input DATA folder"
    refused(calibrate_argv(inputs, out), capsys, [tmp_path], needle, str(inputs["data"]))
    assert pipeline.calls == []


def test_out_is_the_folder_of_the_gimbal_input(pipeline: Pipeline, inputs, tmp_path, capsys) -> None:  # noqa: ANN001
    """``calibrate --gimbal X/calibration.yaml --out X`` would replace its own input."""
    x = tmp_path / "x"
    x.mkdir()
    gimbal = x / "calibration.yaml"
    gimbal.write_text("joints: 2\n")
    argv = calibrate_argv({**inputs, "gimbal": gimbal}, x)
    refused(argv, capsys, [tmp_path], "--gimbal", str(gimbal), "holds the input")
    assert pipeline.calls == []


def test_config_file_inside_out_is_protected(pipeline: Pipeline, inputs, tmp_path, capsys) -> None:  # noqa: ANN001
    out = tmp_path / "out"
    out.mkdir()
    cfg = out / "summary.json"
    cfg.write_text("{}\n")
    refused(calibrate_argv(inputs, out, "--config", str(cfg)), capsys, [tmp_path], "--config", str(cfg))
    assert pipeline.calls == []


def test_validate_into_the_calibration_folder(pipeline: Pipeline, inputs, tmp_path, capsys) -> None:  # noqa: ANN001
    cal_dir = tmp_path / "cal"
    assert main(calibrate_argv(inputs, cal_dir)) == 0
    assert json.loads((cal_dir / MANIFEST).read_text())["command"] == "calibrate"
    pipeline.calls.clear()
    argv = ["validate", str(inputs["data"]), "--calibration", str(cal_dir / "calibration.yaml"), "--camchain",
            str(inputs["camchain"]), "-q"]  # fmt: skip
    # the calibration's own folder: holds the input --calibration
    refused([*argv, "--out", str(cal_dir)], capsys, [tmp_path], "--calibration", str(cal_dir / "calibration.yaml"))
    # another calibrate result folder: not a validate folder
    other = tmp_path / "cal2"
    assert main(calibrate_argv(inputs, other)) == 0
    pipeline.calls.clear()
    refused([*argv, "--out", str(other)], capsys, [tmp_path], str(other), "result folder of 'dcc-fg calibrate'")
    assert pipeline.calls == []


def test_result_folder_of_an_older_version_is_recognized(pipeline: Pipeline, inputs, tmp_path, capsys) -> None:  # noqa: ANN001
    """No manifest: the 'command' of summary.json identifies the folder."""
    vio = tmp_path / "vio_run"
    vio.mkdir()
    (vio / "summary.json").write_text(json.dumps({"command": "vio"}))
    (vio / "trajectory.tum").write_text("0 0 0 0 0 0 0 1\n")
    refused(calibrate_argv(inputs, vio), capsys, [tmp_path], str(vio), "result folder of 'dcc-fg vio'", "summary.json")
    assert pipeline.calls == []


def test_corrupt_manifest_is_named(pipeline: Pipeline, inputs, tmp_path, capsys) -> None:  # noqa: ANN001
    out = tmp_path / "out"
    out.mkdir()
    (out / MANIFEST).write_text("{not json")
    refused(calibrate_argv(inputs, out), capsys, [tmp_path], str(out / MANIFEST), "not a readable dcc-fg manifest")


# ---------------------------------------------------------------------------------------------- writing one set


def test_rerun_replaces_the_previous_set(pipeline: Pipeline, inputs, tmp_path, capsys) -> None:  # noqa: ANN001
    """A re-run without --report removes the previous report and figures; the user's own files stay."""
    out = tmp_path / "out"
    assert main(calibrate_argv(inputs, out, "--report")) == 0
    assert (out / "report.pdf").is_file() and (out / "calibration_residuals.png").is_file()
    (out / "notes.txt").write_text("mine\n")
    assert main(calibrate_argv(inputs, out)) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == [
        MANIFEST, "calibration.yaml", "joint_angles.csv", "kinematics_information.npz", "notes.txt", "summary.json"
    ]  # fmt: skip
    manifest = json.loads((out / MANIFEST).read_text())
    assert manifest["command"] == "calibrate"
    assert manifest["files"] == ["calibration.yaml", "joint_angles.csv", "kinematics_information.npz", "summary.json"]
    assert (out / "notes.txt").read_text() == "mine\n" and no_staging_left(out, tmp_path)


def test_rerun_into_a_folder_of_an_older_version(pipeline: Pipeline, inputs, tmp_path, capsys) -> None:  # noqa: ANN001
    """No manifest, summary.json says calibrate: its known outputs (stale report.pdf, figures) are replaced."""
    out = tmp_path / "old"
    out.mkdir()
    (out / "summary.json").write_text(json.dumps({"command": "calibrate"}))
    (out / "report.pdf").write_bytes(b"stale")
    (out / "calibration_chain.png").write_bytes(b"stale")
    (out / "README").write_text("kept\n")
    assert main(calibrate_argv(inputs, out)) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == [
        MANIFEST, "README", "calibration.yaml", "joint_angles.csv", "kinematics_information.npz", "summary.json"
    ]  # fmt: skip


def test_failure_while_writing_leaves_out_unchanged(
    pipeline: Pipeline, inputs, tmp_path, capsys, monkeypatch: pytest.MonkeyPatch
) -> None:  # noqa: ANN001
    out = tmp_path / "out"
    assert main(calibrate_argv(inputs, out, "--report")) == 0

    def disk_full(out_dir: Path, *args: Any, **kwargs: Any) -> list[Path]:
        (out_dir / "calibration_residuals.png").write_bytes(b"half")
        raise OSError(errno.ENOSPC, "No space left on device", str(out_dir / "report.pdf"))

    monkeypatch.setattr(calibrate_cmd, "write_calibration_outputs", disk_full)
    refused(
        calibrate_argv(inputs, out, "--report"), capsys, [tmp_path], "report.pdf", "No space left", "free some disk"
    )
    assert no_staging_left(out, tmp_path)


def test_failure_during_the_commit_is_rolled_back(
    pipeline: Pipeline, inputs, tmp_path, capsys, monkeypatch: pytest.MonkeyPatch
) -> None:  # noqa: ANN001
    """The manifest is written last; if that fails, the previous set is moved back in place."""
    out = tmp_path / "out"
    assert main(calibrate_argv(inputs, out, "--report")) == 0
    real_replace = os.replace

    def failing_replace(src: Any, dst: Any) -> None:
        if Path(dst).name == MANIFEST:
            raise OSError(errno.EACCES, "Permission denied", str(dst))
        real_replace(src, dst)

    monkeypatch.setattr(output_set.os, "replace", failing_replace)
    refused(calibrate_argv(inputs, out), capsys, [tmp_path], str(out), "Permission denied")
    assert no_staging_left(out, tmp_path)


def test_new_out_folder_and_its_parents_are_created_only_on_success(
    pipeline: Pipeline, inputs, tmp_path, capsys
) -> None:  # noqa: ANN001
    out = tmp_path / "a" / "b" / "out"
    pipeline.estimator = lambda *a, **k: (_ for _ in ()).throw(ValueError("estimator refused the data"))
    refused(calibrate_argv(inputs, out), capsys, [tmp_path], "estimator refused the data")
    assert not (tmp_path / "a").exists()
    pipeline.estimator = lambda *a, **k: pipeline.result
    assert main(calibrate_argv(inputs, out)) == 0
    assert (out / "calibration.yaml").is_file() and oct(out.stat().st_mode & 0o777) != "0o700"


def test_ctrl_c_in_the_estimator(pipeline: Pipeline, inputs, tmp_path, capsys) -> None:  # noqa: ANN001
    out = tmp_path / "out"
    assert main(calibrate_argv(inputs, out)) == 0

    def interrupted(*args: Any, **kwargs: Any) -> CalibrationResult:
        raise KeyboardInterrupt

    pipeline.estimator = interrupted
    err = refused(calibrate_argv(inputs, out), capsys, [tmp_path], code=130)
    assert err == "dcc-fg calibrate: interrupted\n"  # one line, no traceback
    assert no_staging_left(out, tmp_path)
    fresh = tmp_path / "fresh"
    refused(calibrate_argv(inputs, fresh), capsys, [tmp_path], "interrupted", code=130)
    assert not fresh.exists()


@pytest.fixture
def default_sigint() -> Iterator[None]:
    """Python's default SIGINT handler for the test: a test run started in the background by a shell
    without job control inherits SIGINT ignored, in which no Ctrl-C arrives at all."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def test_ctrl_c_during_the_commit_is_deferred(default_sigint: None) -> None:
    """A SIGINT inside DeferredInterrupt does not stop the block; KeyboardInterrupt comes at its end."""
    steps = []
    with pytest.raises(KeyboardInterrupt), DeferredInterrupt():
        os.kill(os.getpid(), signal.SIGINT)
        steps.append("after the signal")
    assert steps == ["after the signal"]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_output_set_api(tmp_path: Path) -> None:
    out = tmp_path / "o"
    with OutputSet(out, "calibrate") as s:
        (s.path / "calibration.yaml").write_text("a")
        assert s.final(s.path / "calibration.yaml") == out / "calibration.yaml"
    assert folder_owner(out).command == "calibrate" and folder_owner(out).entries == ("calibration.yaml",)
    with pytest.raises(RuntimeError, match="boom"), OutputSet(out, "calibrate") as s:
        (s.path / "calibration.yaml").write_text("b")
        raise RuntimeError("boom")
    assert (out / "calibration.yaml").read_text() == "a" and no_staging_left(out, tmp_path)
    with pytest.raises(OutputPathError, match="result folder of 'dcc-fg calibrate'"):
        OutputSet(out, "vio")
    (out / "images").mkdir()  # a folder of the user where the new set has an entry of that name
    with pytest.raises(OutputPathError, match="not written by dcc-fg calibrate"), OutputSet(out, "calibrate") as s:
        (s.path / "images").mkdir()
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST, "calibration.yaml", "images"]


# ---------------------------------------------------------------------------------------------- simulate


def _no_simulation(monkeypatch: pytest.MonkeyPatch) -> None:
    def fail(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("simulated before the output checks")

    monkeypatch.setattr(flight_bag, "simulate_flight", fail)
    monkeypatch.setattr(write_dataset, "simulate_calibration", fail)


@pytest.mark.parametrize("layout", ["manifest", "older version"])
def test_simulate_flight_refuses_an_existing_flight(tmp_path, capsys, monkeypatch, layout) -> None:  # noqa: ANN001
    out = tmp_path / "fl"
    if layout == "manifest":
        with OutputSet(out, "simulate flight") as s:
            (s.path / "flight.bag").write_bytes(b"bag")
            (s.path / "calibration.yaml").write_text("cal")
    else:
        (out / "flight").mkdir(parents=True)
        (out / "flight" / "metadata.yaml").write_text("m")
        (out / "ground_truth.tum").write_text("t")
    _no_simulation(monkeypatch)
    argv = ["simulate", "flight", "--out", str(out), "--duration", "4.5", "--scale", "0.1", "-q"]
    refused(argv, capsys, [tmp_path], str(out), "already exists", "--force")
    # simulate calibration refuses the flight folder (another command's result)
    argv = ["simulate", "calibration", "--out", str(out), "--snapshots", "2"]
    refused(argv, capsys, [tmp_path], str(out), "result folder of 'dcc-fg simulate flight'")


def test_simulate_flight_force_replaces_and_ctrl_c_keeps_the_old(tmp_path, capsys, monkeypatch) -> None:  # noqa: ANN001
    out = tmp_path / "fl"
    argv = ["simulate", "flight", "--out", str(out), "--duration", "4.5", "--scale", "0.1", "--format", "ros1", "-q"]
    assert main(argv) == 0
    assert sorted(json.loads((out / MANIFEST).read_text())["files"]) == [
        "calibration.yaml", "flight.bag", "ground_truth.tum", "ground_truth_joints.csv",
    ]  # fmt: skip
    capsys.readouterr()
    real = flight_bag._write_flight_bag

    def interrupted(bag_path: Path, *args: Any, **kwargs: Any) -> Any:
        bag_path.write_bytes(b"partial")
        raise KeyboardInterrupt

    monkeypatch.setattr(flight_bag, "_write_flight_bag", interrupted)
    err = refused([*argv, "--force", "--seed", "3"], capsys, [tmp_path], code=130)
    assert err == "dcc-fg simulate flight: interrupted\n" and no_staging_left(out, tmp_path)
    monkeypatch.setattr(flight_bag, "_write_flight_bag", real)
    old = (out / "flight.bag").read_bytes()
    assert main([*argv, "--force", "--seed", "3", "--format", "ros2"]) == 0
    names = sorted(p.name for p in out.iterdir())  # the ROS1 bag of the previous flight is gone
    assert names == [MANIFEST, "calibration.yaml", "flight", "ground_truth.tum", "ground_truth_joints.csv"]
    assert old  # (the old bag was read before being replaced)


def test_simulate_calibration_refuses_existing_names(tmp_path, capsys, monkeypatch) -> None:  # noqa: ANN001
    """A folder holding a file with one of the data set's names (not written by simulate) is refused,
    even with --force: the user's gimbal.yaml is never replaced."""
    out = tmp_path / "set"
    out.mkdir()
    (out / "gimbal.yaml").write_text("mine\n")
    _no_simulation(monkeypatch)
    argv = ["simulate", "calibration", "--out", str(out), "--snapshots", "2"]
    refused(argv, capsys, [tmp_path], str(out / "gimbal.yaml"), "already exists", "not written by dcc-fg simulate")


# ---------------------------------------------------------------------------------------------- single files


def test_config_out_checks(tmp_path, capsys) -> None:  # noqa: ANN001
    folder = tmp_path / "dir"
    folder.mkdir()
    refused(["config", "--print", "vio", "--out", str(folder)], capsys, [tmp_path], str(folder), "is a folder")
    summary = tmp_path / "summary.json"
    summary.write_text(json.dumps({"command": "vio", "options": {}}))
    argv = ["config", "--print", "vio", "--from", str(summary), "--out", str(summary), "--force"]
    refused(argv, capsys, [tmp_path], "--from", str(summary))


def test_intrinsics_out_checks_before_detection(tmp_path, capsys, monkeypatch) -> None:  # noqa: ANN001
    def fail(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("detected before the output checks")

    monkeypatch.setattr(intrinsics_cmd, "run_intrinsics", fail)
    data = tmp_path / "images"
    (data / "cam0").mkdir(parents=True)
    target = tmp_path / "target.yaml"
    target.write_text(yaml.safe_dump({"target_type": "checkerboard", "targetCols": 7, "targetRows": 6,
                                      "rowSpacingMeters": 0.05, "colSpacingMeters": 0.05}))  # fmt: skip
    base = ["intrinsics", str(data), "--target", str(target)]
    refused([*base, "--out", str(tmp_path)], capsys, [tmp_path], str(tmp_path), "is a folder")
    same = str(tmp_path / "c.yaml")
    refused([*base, "--out", same, "--summary", same], capsys, [tmp_path], "--summary", "the same file as --out")
    refused([*base, "--out", str(target)], capsys, [tmp_path], "--out", "is the input --target")
    refused([*base, "--out", str(data / "camchain.yaml")], capsys, [tmp_path], "inside the input DATA folder")


def test_unknown_names_in_a_manifest_are_never_removed(tmp_path: Path) -> None:
    """A manifest listing paths outside the folder (tampered) cannot make a re-run delete them."""
    out = tmp_path / "o"
    out.mkdir()
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    manifest = {"command": "calibrate", "files": ["../victim.txt", "/etc/passwd", "..", "calibration.yaml"]}
    (out / MANIFEST).write_text(json.dumps(manifest))
    with OutputSet(out, "calibrate") as s:
        (s.path / "calibration.yaml").write_text("new")
    assert victim.read_text() == "keep" and Path("/etc/passwd").exists()
    assert np.array_equal(sorted(p.name for p in out.iterdir()), sorted([MANIFEST, "calibration.yaml"]))


def test_real_ctrl_c_of_a_running_command(tmp_path: Path) -> None:
    """``dcc-fg simulate flight`` in its own process, SIGINT while it renders: one line, exit 130, no
    OUT folder and no staging folder left behind."""
    out = tmp_path / "fl"
    script = Path(sys.executable).parent / "dcc-fg"  # the installed command, as a user runs it
    if not script.is_file():
        pytest.skip(f"{script}: the dcc-fg command is not installed")
    argv = [str(script), "simulate", "flight", "--out", str(out), "--duration", "30", "--scale", "0.25", "-q"]
    proc = subprocess.Popen(  # SIGINT at its default even when this test run inherited it ignored
        argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    deadline = time.monotonic() + 60
    while not any(output_set.STAGING_TAG in p.name for p in tmp_path.iterdir()):  # rendering has started
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.05)
    time.sleep(0.3)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    # 130; or ended by SIGINT (-2, which a shell also shows as 130) when the signal lands while code compiled
    # from a string runs (rosbags builds its serializers with exec): CPython then re-raises SIGINT at exit
    assert proc.returncode in (130, -signal.SIGINT) and err == "dcc-fg simulate flight: interrupted\n", err
    assert list(tmp_path.iterdir()) == []


def test_evaluate_only_into_a_vio_folder(tmp_path, capsys) -> None:  # noqa: ANN001
    """evaluate attaches its files to a vio folder: a calibrate folder or a file are refused before reading."""
    cal = tmp_path / "cal"
    with OutputSet(cal, "calibrate") as s:
        (s.path / "calibration.yaml").write_text("cal")
    gt = tmp_path / "gt.tum"
    gt.write_text("not read\n")
    refused(["evaluate", str(cal), "--ground-truth", str(gt)], capsys, [tmp_path], str(cal),
            "result folder of 'dcc-fg calibrate'", "only into vio folders")  # fmt: skip
    refused(["evaluate", str(gt), "--ground-truth", str(gt)], capsys, [tmp_path], str(gt), "is a file")


def test_unwritable_parent_is_refused_before_loading(
    pipeline: Pipeline, inputs, tmp_path, capsys, monkeypatch: pytest.MonkeyPatch
) -> None:  # noqa: ANN001
    """(The tests run as root, for whom every folder is writable: os.access answers as for a user.)"""
    locked = tmp_path / "locked"
    locked.mkdir()
    monkeypatch.setattr(output_set.os, "access", lambda path, mode: Path(path) != locked)
    out = locked / "a" / "out"
    refused(calibrate_argv(inputs, out), capsys, [tmp_path], str(locked), "not writable (permission denied)")
    assert pipeline.calls == []


def test_staging_of_a_killed_run_is_cleaned_up(tmp_path: Path) -> None:
    """A run killed with SIGKILL leaves its hidden staging folder; the next run into that folder
    removes it, but never the staging folder of a live process or of another host."""
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    out = tmp_path / "o"
    out.mkdir()
    host = output_set._owner_tag().rsplit("-", 1)[0]
    killed = out / f"{output_set.STAGING_TAG}{host}-{dead.pid}.abcd1234"
    alive = out / f"{output_set.STAGING_TAG}{host}-{os.getpid()}.abcd1234"
    remote = out / f"{output_set.STAGING_TAG}elsewhere-{dead.pid}.abcd1234"
    beside = tmp_path / f".o{output_set.STAGING_TAG}{host}-{dead.pid}.abcd1234"
    for d in (killed, alive, remote, beside):
        d.mkdir()
        (d / "calibration.yaml").write_text("half")
    with OutputSet(out, "calibrate") as s:
        (s.path / "calibration.yaml").write_text("new")
    assert not killed.exists() and not beside.exists() and alive.exists() and remote.exists()
    assert (out / "calibration.yaml").read_text() == "new"
