"""One configuration: options dataclasses <-> YAML, --config with flag overrides, provenance in
summary.json, runs reproduced from a written config, logging and CLI error reporting."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

import dcc_fg
import dcc_fg.commands.calibrate as calibrate_command
from dcc_fg.calibrate import CalibrationOptions
from dcc_fg.cli import main
from dcc_fg.commands.calibrate import CalibrateConfig, ValidateConfig
from dcc_fg.commands.config import CONFIGS, config_text
from dcc_fg.commands.vio import VioConfig
from dcc_fg.sim.write_dataset import CalibrationSimSpec, RenderedCalibration, write_calibration_dataset
from dcc_fg.util.config import ConfigError, apply_overrides, from_dict, load_yaml_config, to_plain
from dcc_fg.util.errors import EstimatorError, stage
from dcc_fg.util.logs import configure_logging


@dataclass
class _Inner:
    sigma: float = 1.0
    angles: tuple[float, ...] | None = None
    name: str = "a"
    flag: bool = False
    count: int = 3


@dataclass
class _Outer:
    inner: _Inner = field(default_factory=_Inner)


@pytest.mark.parametrize("command", sorted(CONFIGS))
def test_printed_defaults_load_back_to_the_defaults(tmp_path: Path, command: str) -> None:
    path = tmp_path / "cfg.yaml"
    path.write_text(config_text(command))
    assert load_yaml_config(path, CONFIGS[command], command) == CONFIGS[command]()


def test_from_dict_converts_types_and_keeps_unset_defaults() -> None:
    got = from_dict(_Outer, {"inner": {"sigma": 2, "angles": [0.5, 1], "count": 4.0}})
    assert got.inner == _Inner(sigma=2.0, angles=(0.5, 1.0), count=4)
    assert isinstance(got.inner.sigma, float) and isinstance(got.inner.count, int)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"inner": {"sigmaa": 1.0}}, "f.yaml.inner: unknown option(s) sigmaa"),
        ({"inner": {"sigma": "x"}}, "f.yaml.inner.sigma: expected a number"),
        ({"inner": {"flag": 1}}, "f.yaml.inner.flag: expected true or false"),
        ({"inner": {"count": 2.5}}, "f.yaml.inner.count: expected an integer"),
        ({"inner": {"name": None}}, "f.yaml.inner.name: must not be empty"),
        ({"other": {}}, "f.yaml: unknown option(s) other"),
    ],
)
def test_bad_values_name_the_file_and_key(data: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        from_dict(_Outer, data, "f.yaml")


def test_options_own_checks_apply() -> None:
    with pytest.raises(ConfigError, match="solver: .*pixel_sigma must be a positive number of pixels"):
        from_dict(CalibrateConfig, {"solver": {"pixel_sigma": -1.0}}, "cfg")


def test_flags_override_the_file(tmp_path: Path) -> None:
    path = tmp_path / "c.yaml"
    path.write_text("command: calibrate\nsolver:\n  robust: huber\n  robust_k: 3.0\nreader:\n  corners: common\n")
    config = load_yaml_config(path, CalibrateConfig, "calibrate")
    config = apply_overrides(config, {"solver.robust_k": 1.5})
    assert config.solver == CalibrationOptions(robust="huber", robust_k=1.5)
    assert config.reader.corners == "common"


def test_a_config_for_another_command_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "v.yaml"
    path.write_text(config_text("vio"))
    with pytest.raises(ConfigError, match="configuration for 'dcc-fg vio', not 'dcc-fg calibrate'"):
        load_yaml_config(path, CalibrateConfig, "calibrate")


def test_vio_config_refuses_derived_and_unknown_frontend_options(tmp_path: Path, capsys) -> None:
    for text, message in [
        ("smoother:\n  sigma: 0.01\n", "smoother.sigma is computed; set run.pixel_sigma"),
        ("frontend:\n  max_featurs: 10\n", "frontend: unknown option(s) max_featurs"),
    ]:
        path = tmp_path / "v.yaml"
        path.write_text("command: vio\n" + text)
        argv = ["vio", str(tmp_path), "--calibration", str(path), "--out", str(tmp_path / "o"), "--config", str(path)]
        assert main(argv) == 2
        assert message in capsys.readouterr().err


def test_version_comes_from_the_installed_package() -> None:
    assert dcc_fg.__version__ != "unknown" and dcc_fg.__version__[0].isdigit()


# ---------------------------------------------------------------------------------- runs


@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> RenderedCalibration:
    spec = CalibrationSimSpec("checkerboard", "folder", seed=3, n_snapshots=12)
    return write_calibration_dataset(tmp_path_factory.mktemp("small"), spec)


def _calibrate_argv(r: RenderedCalibration, out: Path, *extra: str) -> list[str]:
    return [
        "calibrate", str(r.data), "--camchain", str(r.camchain), "--target", str(r.target),
        "--gimbal", str(r.gimbal), "--out", str(out), "-q", *extra,
    ]  # fmt: skip


@pytest.mark.slow
def test_calibrate_summary_records_version_options_inputs_and_reproduces(small: RenderedCalibration, tmp_path: Path):
    first = tmp_path / "first"
    assert main(_calibrate_argv(small, first, "--robust", "huber", "--robust-k", "3", "--corners", "common")) == 0
    summary = json.loads((first / "summary.json").read_text())
    assert summary["dcc_fg_version"] == dcc_fg.__version__
    assert summary["command"] == "calibrate"
    assert summary["command_line"][-6:] == ["--robust", "huber", "--robust-k", "3", "--corners", "common"]
    assert summary["inputs"]["data"] == str(Path(small.data).resolve())
    assert summary["inputs"]["gimbal"] == str(Path(small.gimbal).resolve())
    assert summary["options"]["solver"]["robust"] == "huber" and summary["options"]["solver"]["robust_k"] == 3.0
    assert summary["options"]["reader"]["corners"] == "common"
    assert summary["options"] == to_plain(CalibrateConfig()) | {
        "solver": to_plain(CalibrationOptions(robust="huber", robust_k=3.0)),
        "reader": {**to_plain(CalibrateConfig().reader), "corners": "common"},
    }

    cfg = tmp_path / "cfg.yaml"
    assert main(["config", "--print", "calibrate", "--from", str(first / "summary.json"), "--out", str(cfg)]) == 0
    second = tmp_path / "second"
    assert main(_calibrate_argv(small, second, "--config", str(cfg))) == 0
    assert (second / "joint_angles.csv").read_text() == (first / "joint_angles.csv").read_text()
    again = json.loads((second / "summary.json").read_text())
    assert again["options"] == summary["options"]
    assert again["reprojection_error_px"] == summary["reprojection_error_px"]

    # a flag overrides the config file
    third = tmp_path / "third"
    assert main(_calibrate_argv(small, third, "--config", str(cfg), "--corners", "all")) == 0
    assert json.loads((third / "summary.json").read_text())["options"]["reader"]["corners"] == "all"


def test_config_print_refuses_to_overwrite(tmp_path: Path, capsys) -> None:
    out = tmp_path / "c.yaml"
    out.write_text("keep")
    assert main(["config", "--print", "vio", "--out", str(out)]) == 2
    assert out.read_text() == "keep" and "exists" in capsys.readouterr().err


# ------------------------------------------------------------------------- errors, logging


def test_estimator_failure_is_one_line_with_stage_and_hint(small, tmp_path, monkeypatch, capsys) -> None:
    def failing(*args, **kwargs):
        with stage("calibration solve", hint="give --gimbal with better initial values"):
            raise RuntimeError("Indeterminant linear system detected while working near variable 7")

    monkeypatch.setattr(calibrate_command, "calibrate_global", failing)
    assert main(_calibrate_argv(small, tmp_path / "o")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("dcc-fg calibrate: error: calibration solve failed: Indeterminant linear system")
    assert "hint: give --gimbal" in err[-1] and "Traceback" not in "\n".join(err)
    assert not (tmp_path / "o" / "calibration.yaml").exists()


def test_unwrapped_numerical_failure_is_reported_too(small, tmp_path, monkeypatch, capsys) -> None:
    def failing(*args, **kwargs):
        raise np.linalg.LinAlgError("Singular matrix")

    monkeypatch.setattr(calibrate_command, "calibrate_global", failing)
    assert main(_calibrate_argv(small, tmp_path / "o")) == 2
    assert "calibrate failed in the estimator: Singular matrix (hint:" in capsys.readouterr().err


def test_programming_errors_are_not_relabelled(small, tmp_path, monkeypatch) -> None:
    def buggy(*args, **kwargs):
        raise KeyError("a bug")

    monkeypatch.setattr(calibrate_command, "calibrate_global", buggy)
    with pytest.raises(KeyError):
        main(_calibrate_argv(small, tmp_path / "o"))


def test_stage_keeps_the_innermost_name_and_passes_other_errors() -> None:
    with pytest.raises(EstimatorError) as info:
        with stage("outer"):
            with stage("inner", hint="h"):
                raise RuntimeError("boom")
    assert info.value.stage == "inner" and str(info.value) == "inner failed: boom (hint: h)"
    with pytest.raises(TypeError):
        with stage("outer"):
            raise TypeError("bug")


LEVELS = [(0, False, {"INFO", "WARNING"}), (1, False, {"DEBUG", "INFO", "WARNING"}), (0, True, {"WARNING"})]


@pytest.mark.parametrize(("verbose", "quiet", "shown"), LEVELS)
def test_logging_levels(capsys, verbose: int, quiet: bool, shown: set[str]) -> None:
    configure_logging(verbose, quiet)
    configure_logging(verbose, quiet)  # idempotent: one handler
    log = logging.getLogger("dcc_fg.test")
    log.debug("d-msg")
    log.info("i-msg")
    log.warning("w-msg")
    err = capsys.readouterr().err
    seen = {lvl for lvl, msg in [("DEBUG", "d-msg"), ("INFO", "i-msg"), ("WARNING", "w-msg")] if msg in err}
    assert seen == shown
    assert err.count("w-msg") == 1 and "WARNING dcc_fg.test: w-msg" in err
    configure_logging()


@pytest.mark.slow
def test_validate_accepts_a_config(small: RenderedCalibration, tmp_path: Path) -> None:
    cal = tmp_path / "cal"
    assert main(_calibrate_argv(small, cal)) == 0
    cfg = tmp_path / "val.yaml"
    cfg.write_text("command: validate\nreader:\n  min_common_points: 10\n")
    val = tmp_path / "val"
    argv = ["validate", str(small.data), "--calibration", str(cal / "calibration.yaml"), "--camchain"]
    argv += [str(small.camchain), "--target", str(small.target), "--out", str(val), "--config", str(cfg), "-q"]
    assert main(argv) == 0
    summary = json.loads((val / "summary.json").read_text())
    reader = {**to_plain(ValidateConfig().reader), "min_common_points": 10}
    assert summary["options"] == to_plain(ValidateConfig()) | {"reader": reader}
    assert summary["input"]["min_common_points"] == 10


def test_vio_defaults_match_the_former_command_line_defaults() -> None:
    c = VioConfig()
    assert (c.smoother.mode, c.smoother.keyframe_every) == ("dcc", 3)
    # persistence and window chosen per run from the cameras' timing (VioOptions.resolved); was all, 1.5 s
    assert (c.smoother.persistent_landmarks, c.smoother.lag) == ("auto", None)
    assert (c.smoother.resolved(False).persistent_landmarks, c.smoother.resolved(False).lag) == ("all", 1.5)
    assert (c.smoother.resolved(True).persistent_landmarks, c.smoother.resolved(True).lag) == ("none", 2.5)
    assert (c.run.pixel_sigma, c.run.frontend_worker) == (1.0, "auto")
    # pairing by exposure time with an automatic tolerance (was 5 ms), time offsets estimated from 0 / the calibration
    assert c.run.sync_tolerance_ms is None
    assert c.smoother.time_offsets is None and c.smoother.estimate_time_offsets


@pytest.mark.slow
def test_vio_run_reproduced_from_its_summary(tmp_path: Path) -> None:
    """A short rendered flight: the options of run 1 (recorded in summary.json) -> config -> run 2."""
    flight = tmp_path / "flight"
    argv = ["simulate", "flight", "--out", str(flight), "--duration", "10", "--scale", "0.5", "-q"]
    assert main(argv) == 0
    base = ["vio", str(flight / "flight"), "--calibration", str(flight / "calibration.yaml"), "-q"]
    first = tmp_path / "first"
    assert main([*base, "--out", str(first), "--frontend", "inline", "--keyframe-every", "2", "--lag", "1.2"]) == 0
    summary = json.loads((first / "summary.json").read_text())
    assert summary["command"] == "vio" and summary["dcc_fg_version"] == dcc_fg.__version__
    assert summary["options"]["smoother"]["keyframe_every"] == 2 and summary["options"]["smoother"]["lag"] == 1.2
    assert summary["options"]["run"]["frontend_worker"] == "inline" and "sigma" not in summary["options"]["smoother"]
    assert summary["effective_options"]["smoother"]["sigma"] > 0
    assert summary["effective_options"]["pipeline"]["frontend"]["max_features"] > 0
    assert summary["inputs"]["calibration"] == str((flight / "calibration.yaml").resolve())

    cfg = tmp_path / "vio.yaml"
    assert main(["config", "--print", "vio", "--from", str(first / "summary.json"), "--out", str(cfg)]) == 0
    second = tmp_path / "second"
    assert main([*base, "--out", str(second), "--config", str(cfg)]) == 0
    assert (second / "trajectory.tum").read_text() == (first / "trajectory.tum").read_text()
    assert (second / "joint_angles.csv").read_text() == (first / "joint_angles.csv").read_text()
    assert json.loads((second / "summary.json").read_text())["effective_options"] == summary["effective_options"]


@pytest.mark.slow
def test_vio_with_structureless_landmarks_and_their_refusals(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--landmarks smart`` runs a short rendered flight and is recorded; with the offsets held it is refused
    before any work with a message naming the conflict."""
    flight = tmp_path / "flight"
    assert main(["simulate", "flight", "--out", str(flight), "--duration", "10", "--scale", "0.5", "-q"]) == 0
    base = ["vio", str(flight / "flight"), "--calibration", str(flight / "calibration.yaml"), "-q"]
    out = tmp_path / "smart"
    assert main([*base, "--out", str(out), "--landmarks", "smart", "--lag", "2.5"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["options"]["smoother"]["landmarks"] == "smart" and (out / "trajectory.tum").is_file()
    assert summary["failed_updates"] == 0 and summary["health"]["healthy"]
    held = tmp_path / "held"
    capsys.readouterr()
    assert main([*base, "--out", str(held), "--landmarks", "smart", "--fix-time-offsets"]) == 2
    assert "landmarks 'smart' needs" in capsys.readouterr().err and not held.exists()


def test_summary_json_as_config_needs_options_of_the_same_command(tmp_path: Path) -> None:
    old = tmp_path / "old.json"
    old.write_text(json.dumps({"dcc_fg_version": "0.0.9", "mode": "dcc"}))
    with pytest.raises(ConfigError, match="a summary.json without 'options'"):
        load_yaml_config(old, VioConfig, "vio")
    vio_run = tmp_path / "vio.json"
    vio_run.write_text(json.dumps({"dcc_fg_version": "0.1.0", "command": "vio", "options": {}}))
    with pytest.raises(ConfigError, match="configuration for 'dcc-fg vio', not 'dcc-fg calibrate'"):
        load_yaml_config(vio_run, CalibrateConfig, "calibrate")
    assert load_yaml_config(vio_run, VioConfig, "vio") == VioConfig()
