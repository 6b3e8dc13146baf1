"""Calibrate as you record (dcc_fg.incremental, dcc-fg calibrate --incremental)."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import gtsam
import numpy as np
import pytest

from dcc_fg import cli, incremental
from dcc_fg.calibrate import CalibrationOptions
from dcc_fg.commands import calibrate as calibrate_cmd
from dcc_fg.commands.calibrate_incremental import (
    IncrementalSettings,
    SnapshotSource,
    feed,
    run_incremental,
)
from dcc_fg.data import CalibrationDataset, with_joints
from dcc_fg.global_fit import calibrate_global, data_cost
from dcc_fg.incremental import IncrementalCalibration, IncrementalOptions, Update
from dcc_fg.io.camchain import CamchainEntry, camchain_to_yaml
from dcc_fg.model_selection import EXACT, offset_entries
from dcc_fg.planning.range_spec import Tolerance
from dcc_fg.sim.calibration_scene import SceneConfig, SimulatedCalibration, simulate_calibration
from dcc_fg.sim.write_dataset import CalibrationSimSpec, write_calibration_dataset
from dcc_fg.sources import dataset as dataset_module
from dcc_fg.sources.dataset import load_dataset
from dcc_fg.sources.detections import write_detection_csv
from dcc_fg.targets import TargetGeometry

GRID = TargetGeometry.aprilgrid(6, 5, 0.05, 0.3)


def _scene(
    n: int, seed: int = 3, target: TargetGeometry | None = None
) -> tuple[SimulatedCalibration, CalibrationDataset]:
    cfg = SceneConfig(n_calibration=n, n_validation=1)
    if target is not None:
        cfg = replace(cfg, target=target)
    sim = simulate_calibration(seed, cfg)
    data = sim.calibration_set
    return sim, with_joints(data, None)  # encoderless, no guesses


def _tangent(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.asarray(gtsam.Pose3(a).localCoordinates(gtsam.Pose3(b)))


@pytest.fixture(scope="module")
def grown() -> tuple[SimulatedCalibration, CalibrationDataset, IncrementalCalibration, list[Update]]:
    """24 snapshots fed one at a time: the first solve at 8, warm iSAM2 updates after it."""
    sim, data = _scene(24)
    opt = IncrementalOptions(start_snapshots=8, global_until=0, tolerance=Tolerance(1e-4, 1e-4))
    inc = IncrementalCalibration(replace(data, snapshots=[]), 2, opt)
    updates = [inc.add(s) for s in data.snapshots]
    return sim, data, inc, updates


def test_updates_collect_then_solve_and_print(grown) -> None:  # noqa: ANN001
    _, _, inc, updates = grown
    assert [u.strategy for u in updates[:7]] == ["collect"] * 7
    assert updates[0].needed == 7 and "7 more snapshot(s)" in updates[0].line()
    assert updates[7].strategy == "global" and updates[7].reason == "first"
    warm = updates[8:]
    assert all(u.strategy == "warm" for u in warm)
    for u in warm:
        assert 0.2 < u.rms_px < 0.8  # the scene's corner noise is 0.4 px per axis
        assert np.isfinite(u.worst_rotation) and u.worst_rotation >= u.mean_rotation > 0
        line = u.line()
        assert line.startswith(f"[{u.n_snapshots:4d}] warm:") and "worst 1-sigma" in line and "mrad" in line
        assert u.suggestion is not None and "next: joints (" in line  # tolerance 0.1 mrad: not reached yet
    # more data, smaller predicted uncertainty
    assert warm[-1].worst_rotation < updates[7].worst_rotation
    assert len(inc.updates) == 24 and inc.solving


def test_final_result_is_the_batch_calibration(grown) -> None:  # noqa: ANN001
    """finish() reaches the batch (global-strategy) minimum: the same cost, T_ds(theta_i) within their
    1-sigma, and both agree with the simulator's ground truth."""
    sim, data, inc, _ = grown
    final = inc.finish()
    batch = calibrate_global(data, 2, CalibrationOptions())
    assert data_cost(final) == pytest.approx(data_cost(batch), rel=1e-6)
    assert final.T_ds_covariances is not None and batch.T_ds_covariances is not None
    for i in range(len(data.snapshots)):
        e = _tangent(batch.T_ds(i), final.T_ds(i))
        sd = np.sqrt(np.diag(batch.T_ds_covariances[i]))
        assert np.all(np.abs(e) <= sd), (i, e, sd)
        truth = sim.truth.T_ds(sim.joints_calibration[i])
        err = _tangent(truth, final.T_ds(i))
        assert np.all(np.abs(err) <= 5.0 * np.sqrt(np.diag(final.T_ds_covariances[i])) + 1e-9), (i, err)
    assert final.extra["incremental"]["global_solves"] == 1
    assert final.calibration.statistics["incremental"]["snapshots"] == 24


def test_lm_backend_and_prediction_every_few_snapshots() -> None:
    sim, data = _scene(14, seed=4)
    opt = IncrementalOptions(backend="lm", start_snapshots=8, global_until=0, predict_every=3)
    inc = IncrementalCalibration(replace(data, snapshots=data.snapshots[:8]), 2, opt)  # the first ones at once
    assert inc.solving and inc.updates[-1].strategy == "global"
    ups = [inc.add(s) for s in data.snapshots[8:]]
    assert [u.predicted for u in ups] == [False, False, True, False, False, True]
    assert ups[0].worst_rotation == inc.updates[7].worst_rotation  # repeated until the next prediction
    assert all(u.strategy == "warm" and 1 <= u.iterations <= opt.warm_iterations for u in ups)
    batch = calibrate_global(data, 2, CalibrationOptions(compute_covariance=False))
    final = inc.finish()
    assert data_cost(final) == pytest.approx(data_cost(batch), rel=1e-6)


def test_global_resolve_on_doubling_and_residual_jump(monkeypatch) -> None:  # noqa: ANN001
    _, data = _scene(17, seed=5)
    inc = IncrementalCalibration(replace(data, snapshots=[]), 2, IncrementalOptions(start_snapshots=8, global_until=40))
    ups = [inc.add(s) for s in data.snapshots]
    assert [u.n_snapshots for u in ups if u.strategy == "global"] == [8, 16]
    assert ups[15].reason == "doubled"
    # a snapshot whose factor the warm update cannot fit makes the RMS jump: the global strategy runs again
    monkeypatch.setattr(inc, "_global_rms", 1e-3)
    more = _scene(18, seed=5)[1].snapshots[17]
    u = inc.add(more)
    assert u.strategy == "global" and u.reason == "residual jump"

    # a global re-solve that fails keeps the warm (polished) estimate and every snapshot
    def failing(*_args, **_kwargs):  # noqa: ANN002, ANN003, ANN202
        raise ValueError("no start converged")

    monkeypatch.setattr(incremental, "calibrate_global", failing)
    monkeypatch.setattr(inc, "_global_rms", 1e-3)
    u = inc.add(_scene(19, seed=5)[1].snapshots[18])
    assert u.strategy == "warm" and u.reason == "polished" and np.isfinite(u.rms_px)
    assert len(inc.snapshots) == 19 and len(inc.current()[1]) == 19


def test_bad_options_and_snapshots_are_refused() -> None:
    with pytest.raises(ValueError, match="encoderless only"):
        IncrementalOptions(solver=CalibrationOptions(mode="encoders"))
    with pytest.raises(ValueError, match="bundle"):
        IncrementalOptions(solver=CalibrationOptions(formulation="two_way"))
    with pytest.raises(ValueError, match="backend"):
        IncrementalOptions(backend="fast")
    with pytest.raises(ValueError, match="warm_iterations"):
        IncrementalOptions(warm_iterations=0)
    with pytest.raises(ValueError, match="jump_ratio"):
        IncrementalOptions(jump_ratio=1.0)
    with pytest.raises(ValueError, match="--poll-seconds"):
        IncrementalSettings(poll_seconds=0.0)
    with pytest.raises(ValueError, match="--idle-timeout"):
        IncrementalSettings(idle_timeout=-1.0)
    with pytest.raises(ValueError):
        IncrementalSettings(tolerance="1 parsec")
    _, data = _scene(3)
    with pytest.raises(ValueError, match="L >= 1"):
        IncrementalCalibration(replace(data, snapshots=[]), 0)
    inc = IncrementalCalibration(replace(data, snapshots=[]), 2)
    inc.add(data.snapshots[0])
    with pytest.raises(ValueError, match="no solution yet"):
        inc.finish()
    few = replace(data.snapshots[1], static=replace(data.snapshots[1].static, ids=data.snapshots[1].static.ids[:3],
                  pixels=data.snapshots[1].static.pixels[:3]))  # fmt: skip
    with pytest.raises(ValueError, match="only 3 corners"):
        inc.add(few)
    assert len(inc.snapshots) == 1  # the refused snapshot was not kept


# ---------------------------------------------------------------------------- the command


def _write_pair(root: Path, snap, target: TargetGeometry) -> None:  # noqa: ANN001
    for cam, obs in (("cam0", snap.static), ("cam1", snap.dynamic)):
        (root / cam).mkdir(parents=True, exist_ok=True)
        tmp = root / cam / f".{snap.timestamp_ns}.tmp"
        write_detection_csv(tmp, snap.timestamp_ns, obs, target)
        tmp.rename(root / cam / f"{snap.timestamp_ns}.csv")


def _camchain(data: CalibrationDataset) -> dict[str, CamchainEntry]:
    return {"cam0": CamchainEntry(data.static_camera), "cam1": CamchainEntry(data.dynamic_camera)}


def test_background_solves_do_not_block_the_updates() -> None:
    """Background mode: the first solve runs in another process while snapshots are collected; when it
    is adopted, the snapshots that came meanwhile join at most ``catch_up`` + 1 per update; a doubled
    re-solve is adopted the same way; finish() reaches the batch calibration's minimum."""
    _, data = _scene(24)
    opt = IncrementalOptions(start_snapshots=8, global_until=16, background=True, catch_up=2)
    with IncrementalCalibration(replace(data, snapshots=[]), 2, opt) as inc:
        ups = [inc.add(s) for s in data.snapshots[:12]]
        assert ups[7].strategy == "collect" and ups[7].needed == 0
        assert ups[7].line() == "[   8] collecting: the first solve is running in the background"
        adopted = inc.wait()
        firsts = [u for u in inc.updates if u.strategy == "global"]
        assert len(firsts) == 1 and firsts[0].reason.startswith("first solve on 8 snapshots")
        if adopted is not None:  # adopted by wait(): 3 of the 4 waiting snapshots joined, one waits
            assert inc.current()[1].shape[0] == 11 and "1 snapshot(s) waiting" in adopted.reason
            assert 0.2 < adopted.rms_px < 0.8 and np.isfinite(adopted.worst_rotation)
        while inc.poll() is not None:  # the rest join without a new snapshot
            pass
        assert inc.current()[1].shape[0] == 12
        for s in data.snapshots[12:]:
            inc.add(s)
        inc.wait()
        assert any(u.strategy == "global" and u.reason.startswith("doubled solve on 16") for u in inc.updates)
        final = inc.finish()
    batch = calibrate_global(data, 2, CalibrationOptions())
    assert data_cost(final) == pytest.approx(data_cost(batch), rel=1e-6)
    assert len(final.timestamps_ns) == 24
    with pytest.raises(ValueError, match="catch_up"):
        IncrementalOptions(catch_up=0)


def test_polling_a_growing_detection_folder(tmp_path: Path) -> None:
    """Files written between polls are picked up; the run stops after the idle timeout."""
    _, data = _scene(12, seed=6, target=GRID)
    root = tmp_path / "rec"
    pending = list(data.snapshots)
    for s in pending[:3]:
        _write_pair(root, s, GRID)
    del pending[:3]
    now = [0.0]

    def sleep(dt: float) -> None:  # the recording goes on while the command waits
        now[0] += dt
        for s in pending[:4]:
            _write_pair(root, s, GRID)
        del pending[:4]

    reader = calibrate_cmd.ReaderOptions()
    source = SnapshotSource(root, _camchain(data), None, reader)
    assert source.is_folder
    lines: list[str] = []
    settings = IncrementalSettings(poll_seconds=1.0, idle_timeout=2.5)
    opt = IncrementalOptions(start_snapshots=8, global_until=0)
    inc = feed(source, lambda t: IncrementalCalibration(t, 2, opt), settings, lines.append, lambda: now[0], sleep)
    assert inc is not None and len(inc.snapshots) == 12
    ts = [s.timestamp_ns for s in inc.snapshots]
    assert ts == sorted(ts) == [s.timestamp_ns for s in data.snapshots]
    assert sum("collecting" in x for x in lines) == 7 and sum(" warm: " in x for x in lines) == 4
    assert lines[-1] == "no new snapshot for 2.5 s: stopping"
    assert source.poll() == []  # nothing changed: the folder is not read again


def test_polling_waits_for_a_folder_that_is_not_there_yet(tmp_path: Path) -> None:
    _, data = _scene(3, seed=6, target=GRID)
    source = SnapshotSource(tmp_path / "later", _camchain(data), None, calibrate_cmd.ReaderOptions())
    assert source.is_folder and source.poll() == [] and source.last_error
    lines: list[str] = []
    inc = feed(source, lambda t: IncrementalCalibration(t, 2), IncrementalSettings(idle_timeout=0.0), lines.append)
    assert inc is None and lines == ["no new snapshot for 0 s: stopping"]


def test_run_incremental_writes_the_calibration(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    _, data = _scene(10, seed=7, target=GRID)
    root = tmp_path / "rec"
    for s in data.snapshots:
        _write_pair(root, s, GRID)
    config = calibrate_cmd.CalibrateConfig(init=calibrate_cmd.InitOptions(joints=2))
    inputs = calibrate_cmd.CalibrationInputs(str(root), camchain=_camchain(data))
    out = tmp_path / "cal"
    settings = IncrementalSettings(idle_timeout=0.0, tolerance="2mrad,2mm", background=False)
    res = run_incremental(inputs, out, config, settings)
    printed = capsys.readouterr().out
    assert "collecting" in printed and "global (first)" in printed and "wrote " in printed
    # the default: the first solve in the background; the snapshots that came meanwhile join after it
    res_bg = run_incremental(inputs, tmp_path / "cal_bg", config, replace(settings, background=True))
    printed = capsys.readouterr().out
    assert "first solve is running in the background" in printed
    assert "global (first solve on 8 snapshots" in printed and "wrote " in printed
    assert res_bg.final_error == pytest.approx(res.final_error, rel=1e-6)
    assert (out / "calibration.yaml").exists() and (out / "kinematics_information.npz").exists()
    assert len(res.timestamps_ns) == 10
    summary = (out / "summary.json").read_text()
    assert '"incremental"' in summary
    # too few snapshots: a clear error, nothing written
    few = tmp_path / "few"
    for s in data.snapshots[:3]:
        _write_pair(few, s, GRID)
    with pytest.raises(ValueError, match="3 usable snapshot"):
        run_incremental(calibrate_cmd.CalibrationInputs(str(few), camchain=_camchain(data)), tmp_path / "o2",
                        config, settings)  # fmt: skip
    assert not (tmp_path / "o2").exists()


def test_run_incremental_refuses_other_modes(tmp_path: Path) -> None:
    inputs = calibrate_cmd.CalibrationInputs(str(tmp_path))
    enc = calibrate_cmd.CalibrateConfig(solver=CalibrationOptions(mode="encoders"))
    with pytest.raises(ValueError, match="encoderless"):
        run_incremental(inputs, tmp_path / "o", enc, IncrementalSettings())
    interp = calibrate_cmd.CalibrateConfig(reader=calibrate_cmd.ReaderOptions(sync="interpolate"))
    with pytest.raises(ValueError, match="--sync tolerance"):
        run_incremental(inputs, tmp_path / "o", interp, IncrementalSettings())
    with pytest.raises(ValueError, match="--joints"):
        run_incremental(inputs, tmp_path / "o", calibrate_cmd.CalibrateConfig(), IncrementalSettings())


def test_cli_calibrate_incremental_on_a_detection_folder(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    _, data = _scene(10, seed=7, target=GRID)
    root = tmp_path / "rec"
    for s in data.snapshots:
        _write_pair(root, s, GRID)
    camchain = tmp_path / "camchain.yaml"
    camchain.write_text(camchain_to_yaml(_camchain(data)))
    out = tmp_path / "cal"
    argv = ["calibrate", str(root), "--camchain", str(camchain), "--joints", "2", "--out", str(out),
            "--incremental", "--blocking-solves", "--idle-timeout", "0", "--poll-seconds", "0.1",
            "--tolerance", "5mrad,5mm"]  # fmt: skip
    assert cli.main(argv) == 0
    printed = capsys.readouterr().out
    assert "[  10] warm" in printed and (out / "calibration.yaml").exists()
    assert cli.main(argv[:-2] + ["--tolerance", "5 parsec"]) != 0
    assert "--tolerance '5 parsec'" in capsys.readouterr().err
    # the same options from a --config file (section incremental:); a flag still overrides it
    config = tmp_path / "calibrate.yaml"
    config.write_text("command: calibrate\nincremental: {idle_timeout: 0, poll_seconds: 0.1, tolerance: '5mrad,5mm'}\n")
    base = [str(tmp_path / "cal2") if a == str(out) else a for a in argv[: argv.index("--blocking-solves")]]
    assert cli.main([*base, "--config", str(config)]) == 0
    summary = json.loads((tmp_path / "cal2" / "summary.json").read_text())
    assert summary["input"]["incremental"]["settings"]["idle_timeout_s"] == 0
    config.write_text("command: calibrate\nincremental: {poll_seconds: -1}\n")
    assert cli.main([*base, "--config", str(config)]) == 2
    assert "incremental" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_calibrate_incremental_on_a_rendered_bag(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    """A finished ROS1 bag is fed pair by pair; the result equals the batch calibration of the bag."""
    write_calibration_dataset(tmp_path / "sim", CalibrationSimSpec(fmt="ros1", n_snapshots=24, seed=2))
    bag, camchain, target = (tmp_path / "sim" / n for n in ("images.bag", "camchain.yaml", "target.yaml"))
    common_args = [str(bag), "--camchain", str(camchain), "--target", str(target), "--joints", "2"]
    assert cli.main(["calibrate", *common_args, "--out", str(tmp_path / "inc"), "--incremental"]) == 0
    printed = capsys.readouterr().out
    assert "global (first" in printed and "no new snapshot" not in printed
    assert cli.main(["calibrate", *common_args, "--out", str(tmp_path / "batch")]) == 0
    inc = json.loads((tmp_path / "inc" / "summary.json").read_text())
    batch = json.loads((tmp_path / "batch" / "summary.json").read_text())
    assert inc["snapshots"] == batch["snapshots"]
    assert inc["reprojection_error_px"]["all"]["rms_per_axis"] == pytest.approx(
        batch["reprojection_error_px"]["all"]["rms_per_axis"], rel=1e-6
    )


def test_ctrl_c_while_waiting_stops_the_feed(tmp_path: Path) -> None:
    _, data = _scene(9, seed=6, target=GRID)
    root = tmp_path / "rec"
    for s in data.snapshots:
        _write_pair(root, s, GRID)

    def interrupted(_dt: float) -> None:
        raise KeyboardInterrupt

    source = SnapshotSource(root, _camchain(data), None, calibrate_cmd.ReaderOptions())
    lines: list[str] = []
    opt = IncrementalOptions(start_snapshots=8)
    inc = feed(
        source, lambda t: IncrementalCalibration(t, 2, opt), IncrementalSettings(), lines.append, sleep=interrupted
    )
    assert inc is not None and inc.solving and len(inc.snapshots) == 9
    assert lines[-1].startswith("interrupted (Ctrl-C)")
    assert len(inc.finish().timestamps_ns) == 9


def test_polling_an_image_folder_reads_each_image_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A growing image folder: each poll reads (decodes, detects) only the image files it has not read
    before (same path, size, modification time); a file rewritten is read again; the snapshots equal a
    one-shot read of the whole folder."""
    r = write_calibration_dataset(tmp_path / "sim", CalibrationSimSpec("checkerboard", "folder", seed=5, n_snapshots=8))
    root = tmp_path / "rec"
    files = {cam: sorted((r.data / cam).glob("*.png")) for cam in ("cam0", "cam1")}
    reads: list[Path] = []
    real_read = dataset_module.read_image
    monkeypatch.setattr(dataset_module, "read_image", lambda p: reads.append(Path(p)) or real_read(p))

    def add(n0: int, n1: int) -> None:
        for cam, fs in files.items():
            (root / cam).mkdir(parents=True, exist_ok=True)
            for f in fs[n0:n1]:
                shutil.copy2(f, root / cam / f.name)

    source = SnapshotSource(root, str(r.camchain), str(r.target), calibrate_cmd.ReaderOptions())
    add(0, 4)
    first = source.poll()
    assert len(reads) == 8 and len(first) == 4
    add(4, 8)
    second = source.poll()
    assert len(reads) == 16 and len(second) == 4  # only the 8 new files
    assert source.poll() == [] and len(reads) == 16
    (root / "cam0" / files["cam0"][0].name).write_bytes(files["cam0"][1].read_bytes())  # rewritten
    source._listing = None  # noqa: SLF001 - force a read although the listing check would see the change too
    source.poll()
    assert len(reads) == 17
    whole = load_dataset(r.data, str(r.camchain), str(r.target))
    got = {s.timestamp_ns: s for s in first + second}
    for s in whole.snapshots:
        assert np.array_equal(got[s.timestamp_ns].static.ids, s.static.ids)
        assert np.array_equal(got[s.timestamp_ns].static.pixels, s.static.pixels)
        assert np.array_equal(got[s.timestamp_ns].dynamic.pixels, s.dynamic.pixels)


def test_the_model_kept_by_the_global_solve_is_used_to_the_end(monkeypatch) -> None:  # noqa: ANN001
    """When the global solve keeps the exactly intersecting model (dcc_fg.model_selection), the warm
    updates and the final solve hold the link offsets at zero too (not the general model again)."""
    _, data = _scene(10, seed=5)
    real = incremental.calibrate_global

    def exact_kept(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        res = real(*args, **kwargs)
        res.extra["model_selection"] = {"model": EXACT}
        return res

    monkeypatch.setattr(incremental, "calibrate_global", exact_kept)
    inc = IncrementalCalibration(replace(data, snapshots=[]), 2, IncrementalOptions(start_snapshots=8, global_until=0))
    for s in data.snapshots:
        inc.add(s)
    res = inc.finish()
    assert res.extra["nominal"] == EXACT and res.extra["model_selection"]["model"] == EXACT
    assert abs(res.calibration.kin[offset_entries(2)[0]]) < 1e-5  # a_1 held at zero (1 um prior)
