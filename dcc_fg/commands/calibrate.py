"""``dcc-fg calibrate`` / ``dcc-fg validate``: files in, calibration files out.

Inputs (paths) stay on the command line; options come from :class:`CalibrateConfig` /
:class:`ValidateConfig` (defaults, ``--config FILE``, then flags). Every ``summary.json`` records
the version, the command line, the inputs and the effective options (see
:func:`dcc_fg.util.provenance.run_record`) and the result's ``health``
(:func:`~dcc_fg.calibration_health.calibration_health`). The outputs are written as one set
(:class:`~dcc_fg.io.output_set.OutputSet`): ``--out`` is checked before any work, and nothing is
written when the run fails, is interrupted or its result is unhealthy (unless
``output.accept_unhealthy``).
"""

from __future__ import annotations

import argparse
import io
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from dcc_fg.calibrate import CalibrationOptions, CalibrationResult, calibrate
from dcc_fg.calibration_health import calibration_health
from dcc_fg.commands import calibrate_incremental, common
from dcc_fg.commands.calibrate_cluster import add_cluster_flags, calibrate_cluster_command, wants_cluster
from dcc_fg.commands.incremental_settings import IncrementalSettings
from dcc_fg.data import CalibrationDataset, common_corners
from dcc_fg.degeneracy import NOMINALS
from dcc_fg.global_fit import calibrate_global
from dcc_fg.io.camchain import CamchainEntry
from dcc_fg.io.output_set import OutputSet
from dcc_fg.io.outputs import plain, write_text_atomic
from dcc_fg.model import GimbalCalibration, load_calibration
from dcc_fg.planning.predict import INFORMATION_FILE, RangeAccuracy, accuracy_table, range_accuracy
from dcc_fg.plots.accuracy_map import accuracy_figure
from dcc_fg.plots.common import save_figure
from dcc_fg.plots.output import write_calibration_outputs
from dcc_fg.report import parameter_table, run_summary_table
from dcc_fg.sources.dataset import load_dataset, load_streams
from dcc_fg.sync import SyncOptions
from dcc_fg.time_offset import MAX_SNAPSHOTS, calibrate_streams
from dcc_fg.util.config import ConfigError
from dcc_fg.util.parallel import resolve_jobs
from dcc_fg.util.provenance import run_record
from dcc_fg.viz.images import DYNAMIC_DIR, STATIC_DIR, ImageSource
from dcc_fg.viz.rerun_log import RerunOptions, record_calibration

#: What ``--rerun`` shows of a calibration or validation (help text).
RERUN_SHOWS = (
    "per snapshot, both camera images (where the data hold images) with the detected and reprojected corners, the "
    "chain's frames (static camera, gimbal base, DH links, gimbal camera) and the target in 3D, joint angles and "
    "residuals over the snapshots"
)

#: Default of ``--min-common-points``: a snapshot needs this many target points seen by both cameras.
MIN_COMMON_POINTS = 8


@dataclass
class ReaderOptions:
    """How snapshots are read from the data.

    ``sync_tolerance_ms``: largest time difference (milliseconds) between a static and a dynamic
    image of one snapshot; ``min_common_points``: a snapshot is used only if both cameras see at least
    this many of the same target corners; ``corners``: ``all`` detected corners of each camera or only
    the ``common`` ones both cameras see. ``sync``: ``tolerance`` pairs images whose stamps agree within
    ``sync_tolerance_ms`` (synchronized cameras, a rig held still); ``interpolate`` detects every frame
    of each camera and gives each gimbal frame the static camera's corners interpolated to its exposure
    time (:mod:`dcc_fg.sync`; unsynchronized cameras, continuous motion), with the inter-camera offset
    ``t_d - t_s`` from ``time_offsets`` (T_S, T_D in s, ``t_imu = t_stamp + t_offset``) estimated
    around them (:mod:`dcc_fg.time_offset`) unless ``fix_time_offsets``; at most ``max_snapshots``
    gimbal frames, evenly spaced, are used. ``jobs``: processes detecting the target (0: every usable
    core; 1: this process only; the same corners either way, :mod:`dcc_fg.sources.parallel_detection`).
    """

    sync_tolerance_ms: float = 5.0
    min_common_points: int = MIN_COMMON_POINTS
    corners: str = "all"
    sync: str = "tolerance"
    time_offsets: tuple[float, float] | None = None
    fix_time_offsets: bool = False
    max_snapshots: int = MAX_SNAPSHOTS
    jobs: int = 0

    def __post_init__(self) -> None:
        resolve_jobs(self.jobs)  # >= 0
        if self.corners not in ("all", "common"):
            raise ValueError(f"corners must be all or common, got {self.corners!r}")
        if self.sync not in ("tolerance", "interpolate"):
            raise ValueError(f"sync must be tolerance or interpolate, got {self.sync!r}")
        if self.time_offsets is not None:
            if len(self.time_offsets) != 2 or not all(np.isfinite(x) and abs(x) < 0.5 for x in self.time_offsets):
                raise ValueError(
                    f"time_offsets must be two finite offsets T_S,T_D in seconds with |offset| < 0.5, got "
                    f"{self.time_offsets!r}"
                )
            if self.sync != "interpolate":
                raise ValueError("time_offsets need sync interpolate (--sync interpolate)")
        if self.fix_time_offsets and self.time_offsets is None:
            raise ValueError("fix_time_offsets needs the offsets (--time-offsets T_S,T_D)")
        if self.max_snapshots < 1:
            raise ValueError(f"max_snapshots must be at least 1, got {self.max_snapshots}")
        if not (np.isfinite(self.sync_tolerance_ms) and self.sync_tolerance_ms > 0):
            raise ValueError(f"sync_tolerance_ms must be a positive number of ms, got {self.sync_tolerance_ms}")
        if self.min_common_points < 1:
            raise ValueError(f"min_common_points must be at least 1, got {self.min_common_points}")


@dataclass
class InitOptions:
    """Initial values: ``method`` ``gimbal`` (the ``--gimbal`` YAML) or ``auto`` (per-snapshot PnP;
    needs ``joints``); None picks gimbal when a ``--gimbal`` file is given, else auto. ``search``:
    ``global`` (default) also solves from every automatic start and keeps the lowest cost
    (:mod:`dcc_fg.global_fit`); ``single`` solves from the ``--gimbal`` start alone."""

    method: str | None = None
    joints: int | None = None
    search: str = "global"

    def __post_init__(self) -> None:
        if self.method == "file":
            raise ValueError("--init file starts an N-camera calibration from its --cluster file: give --cluster")
        if self.method not in (None, "auto", "gimbal"):
            raise ValueError(f"method must be auto or gimbal, got {self.method!r}")
        if self.search not in ("global", "single"):
            raise ValueError(f"search must be global or single, got {self.search!r}")
        if self.joints is not None and not 0 <= self.joints <= 6:
            raise ValueError(f"joints must be between 0 and 6, got {self.joints}")


@dataclass
class OutputOptions:
    """``report``: also save the figures (``OUT/calibration_*.png``) and ``OUT/report.pdf``;
    ``accept_unhealthy``: write a result that failed its health checks (marked ``health.healthy:
    false`` in ``summary.json``) instead of refusing it."""

    report: bool = False
    accept_unhealthy: bool = False


@dataclass
class CalibrateConfig:
    """Every option of ``dcc-fg calibrate`` (sections of the ``--config`` YAML)."""

    init: InitOptions = field(default_factory=InitOptions)
    reader: ReaderOptions = field(default_factory=ReaderOptions)
    solver: CalibrationOptions = field(default_factory=CalibrationOptions)
    output: OutputOptions = field(default_factory=OutputOptions)
    incremental: IncrementalSettings = field(default_factory=IncrementalSettings)


@dataclass
class ValidateConfig:
    """Every option of ``dcc-fg validate`` (the kinematics are held at ``--calibration``)."""

    reader: ReaderOptions = field(default_factory=ReaderOptions)
    output: OutputOptions = field(default_factory=OutputOptions)


@dataclass(frozen=True)
class CalibrationInputs:
    """Input files of a calibrate/validate run (``camchain`` may already be parsed entries)."""

    data: str
    camchain: Any = None
    target: str | None = None
    gimbal: str | None = None
    calibration: str | None = None

    def paths(self) -> dict[str, str | None]:
        camchain = self.camchain if isinstance(self.camchain, str | Path) else None
        return {
            "data": self.data,
            "camchain": camchain,
            "target": self.target,
            "gimbal": self.gimbal,
            "calibration": self.calibration,
        }

    def by_option(self, config_file: str | Path | None = None) -> dict[str, str | Path | None]:
        """The input paths by the option that gave them (``--config`` included), for the output checks."""
        p = self.paths()
        return {
            "DATA": p["data"],
            "--camchain": p["camchain"],
            "--target": p["target"],
            "--gimbal": p["gimbal"],
            "--calibration": p["calibration"],
            "--config": config_file,
        }


def load_calibration_data(
    inputs: CalibrationInputs, camchain: Any, reader: ReaderOptions, progress: bool, report: dict[str, Any]
) -> CalibrationDataset:
    """The CalibrationDataset of ``inputs.data``; ``reader.corners == 'common'`` keeps only the
    corners both cameras of a snapshot see. ``report`` receives the reader's counts."""
    report["min_common_points"] = reader.min_common_points
    report["corners"] = reader.corners
    dataset = load_dataset(
        inputs.data,
        camchain=camchain,
        target=inputs.target,
        tolerance_ns=int(round(reader.sync_tolerance_ms * 1e6)),
        min_common_points=reader.min_common_points,
        progress=progress,
        report=report,
        jobs=resolve_jobs(reader.jobs),
    )
    return common_corners(dataset) if reader.corners == "common" else dataset


def T_ds_std_summary(result: CalibrationResult) -> dict[str, dict[str, float]] | None:
    """Median / max over snapshots of the T_ds 1-sigma (rotation mrad, translation mm; root of the
    trace of each 3x3 block of the Pose3 tangent covariance [omega, v])."""
    cov = result.T_ds_covariances
    if cov is None or len(cov) == 0 or not np.all(np.isfinite(cov)):
        return None
    rot = 1e3 * np.sqrt(np.trace(cov[:, :3, :3], axis1=1, axis2=2))
    tra = 1e3 * np.sqrt(np.trace(cov[:, 3:, 3:], axis1=1, axis2=2))
    return {
        "rotation_mrad": {"median": float(np.median(rot)), "max": float(rot.max())},
        "translation_mm": {"median": float(np.median(tra)), "max": float(tra.max())},
    }


def observability_summary(cal: GimbalCalibration) -> dict[str, Any] | None:
    """Observable / gauge-fixed / gauge-dependent kinematic parameter names (see dcc_fg.calibrate), and the
    link offsets held at zero by the exactly intersecting model (:mod:`dcc_fg.model_selection`)."""
    if cal.observable is None:
        return None
    fixed = cal.gauge_fixed if cal.gauge_fixed is not None else np.zeros(len(cal.names), dtype=bool)
    held_zero = list((cal.statistics.get("model_selection") or {}).get("held_at_zero", []))
    return {
        "n_parameters": len(cal.names),
        "n_observable": int(np.count_nonzero(cal.observable)),
        "observable": [n for n, o in zip(cal.names, cal.observable, strict=True) if o],
        "gauge_fixed": [n for n, f in zip(cal.names, fixed, strict=True) if f],
        "gauge_dependent": [
            n
            for n, o, f in zip(cal.names, cal.observable, fixed, strict=True)
            if not o and not f and n not in held_zero
        ],
        "held_at_zero": held_zero,
    }


def joint_angles_csv_text(result: CalibrationResult) -> str:
    """``timestamp_ns,theta_1..theta_L`` (integer ns, rad) of every snapshot."""
    buf = io.StringIO()
    L = result.joint_angles.shape[1] if result.joint_angles.ndim == 2 else 0
    buf.write(",".join(["timestamp_ns"] + [f"theta_{j + 1}" for j in range(L)]) + "\n")
    for t, th in zip(result.timestamps_ns, result.joint_angles, strict=True):
        buf.write(",".join([str(int(t))] + [f"{x:.12g}" for x in th]) + "\n")
    return buf.getvalue()


def write_calibration_files(
    out: Path,
    result: CalibrationResult,
    reader_report: dict[str, Any],
    provenance: dict[str, Any],
    health: dict[str, Any] | None = None,
) -> list[Path]:
    """Write calibration.yaml, joint_angles.csv and summary.json (with ``health``, the result's health
    checks) into ``out`` (the staging folder of the run's output set); every text is serialized before
    the first file is touched. Returns the paths written."""
    stats = result.calibration.statistics
    if reader_report:
        stats["input"] = dict(reader_report)
    if result.options.mode != "validate":
        obs = observability_summary(result.calibration)
        if obs is not None:
            stats["observability"] = obs
    tds = T_ds_std_summary(result)
    if tds is not None:
        stats["T_ds_std"] = tds
    cal_text = yaml.safe_dump(result.calibration.to_dict(), sort_keys=False)
    csv_text = joint_angles_csv_text(result)
    summary = {**provenance, **stats}
    if health is not None:
        summary["health"] = health
    json_text = json.dumps(plain(summary), indent=2) + "\n"
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "calibration.yaml", out / "joint_angles.csv", out / "summary.json"]
    for path, text in zip(paths, (cal_text, csv_text, json_text), strict=True):
        write_text_atomic(path, text)
    return paths


def write_report(
    out: Path, result: CalibrationResult, data: CalibrationDataset, accuracy: RangeAccuracy | None = None
) -> list[Path]:
    """The calibration figures as ``OUT/calibration_*.png`` and ``OUT/report.pdf``; with ``accuracy`` also its
    table in the report and ``OUT/calibration_accuracy.png`` (:mod:`dcc_fg.planning.predict`). The paths written."""
    text = run_summary_table(result.calibration.statistics) + "\n\n" + parameter_table(result.calibration)
    if accuracy is not None:
        text += "\n\n" + accuracy_table(accuracy)
    paths = write_calibration_outputs(out, result, text, target_points=data.target_points, data=data)
    if accuracy is not None:
        paths.append(save_figure(accuracy_figure(accuracy, result.joint_angles), out / "calibration_accuracy.png"))
    return paths


def write_calibration_set(
    outputs: OutputSet,
    result: CalibrationResult,
    data: CalibrationDataset,
    reader_report: dict[str, Any],
    provenance: dict[str, Any],
    config: CalibrateConfig | ValidateConfig,
) -> list[Path]:
    """Judge the result's health (:func:`~dcc_fg.calibration_health.calibration_health`; an unhealthy
    result raises :class:`~dcc_fg.util.health.UnhealthyResultError` unless
    ``config.output.accept_unhealthy``), then write the files (and, with ``config.output.report``, the
    figures and report) into the staging folder of ``outputs``. Returns the final paths."""
    health = calibration_health(result=result, data=data, reader_report=reader_report)
    health_block = common.judge_health(health, config.output.accept_unhealthy)
    accuracy = range_accuracy(result, data)  # predicted T_ds accuracy over the range (None for validate)
    if accuracy is not None:
        result.calibration.statistics["accuracy_over_range"] = accuracy[1].summary()
    paths = write_calibration_files(outputs.path, result, reader_report, provenance, health_block)
    if accuracy is not None:
        paths.append(accuracy[0].save(outputs.path / INFORMATION_FILE))
    if config.output.report:
        paths += write_report(outputs.path, result, data, accuracy[1] if accuracy is not None else None)
    return [outputs.final(p) for p in paths]


def print_written(result: CalibrationResult, paths: list[Path], quiet: bool) -> None:
    """The summary table and the files written (unless ``quiet``)."""
    if not quiet:
        print(run_summary_table(result.calibration.statistics))
        print("wrote " + ", ".join(str(p) for p in paths))


def initial_values(
    inputs: CalibrationInputs, init: InitOptions, mode: str, data: CalibrationDataset
) -> tuple[GimbalCalibration | None, CalibrationDataset]:
    """The ``--gimbal`` kinematics (method ``gimbal``), or None for the automatic starts (``auto``, the
    default without ``--gimbal``; needs ``joints``), and the data."""
    method = init.method or ("gimbal" if inputs.gimbal else "auto")
    if method == "gimbal":
        if inputs.gimbal is None:
            raise ValueError("--init gimbal needs --gimbal G.yaml")
        return load_calibration(inputs.gimbal), data
    if init.joints is None:
        raise ValueError("--joints L is required when no --gimbal G.yaml is given (automatic initialization)")
    return None, data


def solve_calibration(
    initial: GimbalCalibration | None, data: CalibrationDataset, init: InitOptions, solver: CalibrationOptions
) -> CalibrationResult:
    """The calibration from ``initial`` (None: automatic starts only) with the global strategy
    (:func:`dcc_fg.global_fit.calibrate_global`; ``init.search == "single"``: from ``initial`` alone)."""
    if initial is None:
        assert init.joints is not None
        return calibrate_global(data, int(init.joints), solver)
    return calibrate_global(data, initial.n_joints, solver, initial=initial, automatic=init.search == "global")


def calibrate_unsynchronized(
    inputs: CalibrationInputs, config: CalibrateConfig, progress: bool, report: dict[str, Any]
) -> tuple[CalibrationResult, CalibrationDataset]:
    """``--sync interpolate``: every frame of each camera detected on its own, each gimbal frame paired
    with the static corners interpolated to its exposure time, the inter-camera offset estimated (or
    held at ``--time-offsets`` with ``--fix-time-offsets``). ``report`` gets ``sync`` (what happened to
    the gimbal frames) and ``time_offset`` (estimate, 1-sigma, the search); both also go into the
    calibration's statistics (summary.json)."""
    reader = config.reader
    if config.solver.mode != "encoderless":
        raise ConfigError("--sync interpolate calibrates encoderless (joint readings are not interpolated yet)")
    if inputs.target is None:
        raise ValueError(f"{inputs.data}: --sync interpolate detects the target in the images; give --target")
    initial = load_calibration(inputs.gimbal) if inputs.gimbal and config.init.method != "auto" else None
    if initial is None and config.init.joints is None:
        raise ValueError("--joints L is required when no --gimbal G.yaml is given (automatic initialization)")
    n_joints = initial.n_joints if initial is not None else int(config.init.joints)  # type: ignore[arg-type]
    streams = load_streams(
        inputs.data, inputs.camchain, inputs.target, progress=progress, jobs=resolve_jobs(reader.jobs)
    )
    t_s, t_d = reader.time_offsets if reader.time_offsets is not None else (0.0, 0.0)
    out = calibrate_streams(
        streams.static,
        streams.dynamic,
        (streams.entries[0].camera, streams.entries[1].camera),
        streams.target.points,
        n_joints,
        config.solver,
        initial=initial,
        delta_s=t_d - t_s,
        estimate=not reader.fix_time_offsets,
        sync=SyncOptions(min_common_points=reader.min_common_points),
        max_snapshots=reader.max_snapshots,
        source=str(inputs.data),
    )
    data = common_corners(out.data) if reader.corners == "common" else out.data
    report.update(
        layout="unsynchronized streams",
        min_common_points=reader.min_common_points,
        corners=reader.corners,
        frames_static=int(streams.static.stamps_ns.size),
        frames_dynamic=int(streams.dynamic.stamps_ns.size),
        kept=len(out.data.snapshots),
        sync=out.sync.to_dict(),
        time_offset={**out.offset.to_dict(), "convention": "t_imu = t_stamp + t_offset; delta = t_d - t_s"},
    )
    out.result.calibration.statistics["time_offset"] = report["time_offset"]
    out.result.calibration.statistics["sync"] = report["sync"]
    return out.result, data


def image_source(
    inputs: CalibrationInputs, camchain: Any, reader: ReaderOptions, report: dict[str, Any]
) -> ImageSource:
    """Where the images of the snapshots are, for ``--rerun``: paired frames within the sync tolerance;
    with ``--sync interpolate`` the gimbal frame stamped ``q - (t_d - t_s)`` for a snapshot at static time
    ``q`` and a static image only where one was exposed within 0.5 ms of ``q`` (corners interpolated
    elsewhere)."""
    if reader.sync == "interpolate":
        delta_ns = int(round(float(report.get("time_offset", {}).get("delta_s", 0.0)) * 1e9))
        return ImageSource(inputs.data, camchain, {STATIC_DIR: 500_000, DYNAMIC_DIR: 500_000}, -delta_ns)
    tol = int(round(reader.sync_tolerance_ms * 1e6))
    return ImageSource(inputs.data, camchain, {STATIC_DIR: tol, DYNAMIC_DIR: tol})


def run_calibrate(
    inputs: CalibrationInputs,
    out: Path,
    config: CalibrateConfig,
    progress: bool = False,
    quiet: bool = False,
    config_file: str | Path | None = None,
    rerun: RerunOptions | None = None,
) -> CalibrationResult:
    """Calibrate from ``inputs`` with ``config``; writes ``out`` as one output set
    (:class:`~dcc_fg.io.output_set.OutputSet`: ``out`` is checked before any work, nothing is written
    when the run fails, is interrupted or its result is unhealthy and not accepted).
    ``config_file``: the ``--config`` file, protected like the inputs. ``rerun``: also record the run for
    Rerun (:mod:`dcc_fg.viz.rerun_log`; written before the health checks, so an unhealthy result can be
    inspected)."""
    if config.solver.mode not in ("encoderless", "encoders"):
        raise ConfigError(f"solver.mode must be encoderless or encoders for calibrate, got {config.solver.mode!r}")
    if (
        inputs.gimbal is not None and Path(inputs.gimbal).is_file()
    ):  # an N-camera --gimbal file: refused before the work
        load_calibration(inputs.gimbal).require_two_cameras("calibration")
    outputs = OutputSet(out, "calibrate", inputs.by_option(config_file))
    with outputs:
        report: dict[str, Any] = {}
        if config.reader.sync == "interpolate":
            result, data = calibrate_unsynchronized(inputs, config, progress, report)
        else:
            data = load_calibration_data(inputs, inputs.camchain, config.reader, progress, report)
            initial, data = initial_values(inputs, config.init, config.solver.mode, data)
            result = solve_calibration(initial, data, config.init, config.solver)
        if rerun is not None:
            record_calibration(rerun, result, data, image_source(inputs, inputs.camchain, config.reader, report))
        provenance = run_record("calibrate", inputs.paths(), config)
        paths = write_calibration_set(outputs, result, data, report, provenance, config)
    print_written(result, paths, quiet)
    return result


def validation_camchain(inputs: CalibrationInputs, cal: GimbalCalibration) -> Any:
    """``--camchain``, or the intrinsics stored in the calibration (no image topics: folders only)."""
    if inputs.camchain is not None:
        return inputs.camchain
    if cal.static_camera is None or cal.dynamic_camera is None:
        raise ValueError(f"{inputs.calibration}: has no cam0/cam1 intrinsics; give --camchain")
    return {"cam0": CamchainEntry(cal.static_camera), "cam1": CamchainEntry(cal.dynamic_camera)}


def run_validate(
    inputs: CalibrationInputs,
    out: Path,
    config: ValidateConfig,
    progress: bool = False,
    quiet: bool = False,
    config_file: str | Path | None = None,
    rerun: RerunOptions | None = None,
) -> CalibrationResult:
    """Hold ``inputs.calibration`` fixed and estimate the joint angles of ``inputs.data``; writes
    ``out`` as one output set (see :func:`run_calibrate`, also for ``rerun``)."""
    if inputs.calibration is None:
        raise ValueError("validate needs --calibration")
    cal = load_calibration(inputs.calibration).require_two_cameras("validation", allow_subset=True)  # before the work
    outputs = OutputSet(out, "validate", inputs.by_option(config_file))
    with outputs:
        report: dict[str, Any] = {}
        camchain = validation_camchain(inputs, cal)
        data = load_calibration_data(inputs, camchain, config.reader, progress, report)
        result = calibrate(data, cal, CalibrationOptions(mode="validate"))
        if rerun is not None:
            record_calibration(rerun, result, data, image_source(inputs, camchain, config.reader, report))
        provenance = run_record("validate", inputs.paths(), config)
        paths = write_calibration_set(outputs, result, data, report, provenance, config)
    print_written(result, paths, quiet)
    return result


# ----------------------------------------------------------------------------------------------
# command line


def add_reader_flags(p: argparse.ArgumentParser) -> None:
    """Options shared by calibrate and validate: image pairing, snapshot selection, report."""
    opt = common.add_option
    opt(p, "--sync-tolerance", "reader.sync_tolerance_ms", type=float, metavar="MS", help="largest time difference "
        "between a static and a dynamic image of one snapshot, milliseconds; frames without a partner are reported "
        "(default 5)")  # fmt: skip
    opt(p, "--sync", "reader.sync", choices=["tolerance", "interpolate"], help="tolerance (default): pair images "
        "whose stamps agree within --sync-tolerance (synchronized cameras or a rig held still); interpolate: detect "
        "every frame of each camera and give each gimbal frame the static camera's corners interpolated to its "
        "exposure time (unsynchronized cameras, continuous motion), estimating the inter-camera offset")  # fmt: skip
    opt(p, "--time-offsets", "reader.time_offsets", type=common.float_pair, metavar="T_S,T_D", help="each camera's "
        "time offset in seconds (t_imu = t_stamp + t_offset, as Kalibr's timeshift_cam_imu and OpenVINS); only "
        "T_D - T_S matters here: the centre of the offset search (--sync interpolate), or the offset used with "
        "--fix-time-offsets")  # fmt: skip
    opt(p, "--fix-time-offsets", "reader.fix_time_offsets", action="store_true",
        help="use --time-offsets as given instead of estimating the inter-camera offset")  # fmt: skip
    opt(p, "--max-snapshots", "reader.max_snapshots", type=int, metavar="N", help="--sync interpolate: use at most "
        f"N gimbal frames, evenly spaced in time (default {MAX_SNAPSHOTS})")  # fmt: skip
    opt(p, "--jobs", "reader.jobs", type=int, metavar="N", help="processes detecting the target in the images "
        "(default 0: every usable core; 1: this process only); the same corners either way")  # fmt: skip
    opt(p, "--min-common-points", "reader.min_common_points", type=int, metavar="N",
        help="use a snapshot only if both cameras see at least N of the same target corners (default 8)")  # fmt: skip
    opt(p, "--corners", "reader.corners", choices=["all", "common"], help="all: every detected corner of each camera "
        "(the maximum-likelihood use of the data, default); common: only the corners both cameras of a snapshot see, "
        "as cv2.stereoCalibrate uses them. common helps when the intrinsics fit the image periphery badly, where "
        "only one camera tends to see the board")  # fmt: skip
    opt(p, "--report", "output.report", action="store_true",
        help="also save the figures (OUT/calibration_*.png) and OUT/report.pdf")  # fmt: skip
    opt(p, "--accept-unhealthy", "output.accept_unhealthy", action="store_true", help="write a result that "
        "failed its health checks (residuals against the pixel noise, convergence, joint ranges, image pairing) "
        "instead of refusing it with exit code 3; summary.json then says health: healthy: false, with the "
        "reasons")  # fmt: skip


def add_solver_flags(c: argparse.ArgumentParser) -> None:
    """The initial-value and solver options of ``calibrate``."""
    opt = common.add_option
    opt(c, "--joints", "init.joints", type=int, help="number of joints L when no --gimbal is given")
    opt(c, "--init", "init.method", choices=["auto", "gimbal", "file"], help="initial values: 'gimbal' reads --gimbal; "
        "'auto' estimates axes, DH links, mounts and joint angles from per-snapshot PnP (needs --joints). Default: "
        "gimbal if --gimbal is given, else auto. With --cluster: auto (default) or file (the --cluster file's "
        "values)")  # fmt: skip
    opt(c, "--search", "init.search", choices=["global", "single"], help="global (default): also solve from every "
        "automatic start (distinct minima of the axis fit) and keep the lowest cost, reporting an ambiguity when "
        "another solution fits as well; single: solve from --gimbal alone")  # fmt: skip
    opt(c, "--nominal", "solver.nominal", choices=list(NOMINALS), help="hold the DH links near a nominal geometry "
        "by priors: intersecting (link offsets 0 +- 5 mm), exactly-intersecting (offsets 0 +- 1 um: the "
        "intersecting model itself), orthogonal (twists +-90 +- 2 deg), yaw-roll-pitch / pan-tilt-roll / pan-tilt "
        "(both). Directions the data do not determine are always held by a weak prior and reported (held_by_prior "
        "in calibration.yaml); without --nominal the global search tests exactly intersecting axes against free "
        "offsets when it holds any (model_selection in calibration.yaml)")  # fmt: skip
    opt(c, "--mode", "solver.mode", choices=["encoderless", "encoders"],
        help="joint angles unknown (encoderless, default) or read from joints.csv / JointState (encoders)")  # fmt: skip
    opt(c, "--formulation", "solver.formulation", choices=["bundle", "two_way"],
        help="maximum-likelihood bundle (default) or the paper's two-way error")  # fmt: skip
    opt(c, "--pixel-sigma", "solver.pixel_sigma", type=float,
        help="corner noise in pixels (1 sigma); default: estimated from the residuals")  # fmt: skip
    opt(c, "--corner-noise", "solver.corner_noise", choices=["per-image", "shared"], help="without --pixel-sigma: "
        "per-image (default) weights each image's corners by its own noise, measured from per-image target poses "
        "before the solve (cameras and views detect corners with different noise); shared: one sigma")  # fmt: skip
    opt(c, "--robust", "solver.robust", choices=["huber", "cauchy"],
        help="per-corner robust loss (default: none, plain least squares)")  # fmt: skip
    opt(c, "--robust-k", "solver.robust_k", type=float, help="robust loss threshold in pixels (default 2)")


def add_input_flags(p: argparse.ArgumentParser, camchain_help: str, target_help: str) -> None:
    """DATA, --camchain and --target of calibrate and validate."""
    p.add_argument("data", help="ROS1 .bag, ROS2 bag folder, image folder (cam0/, cam1/) or detection folder")
    p.add_argument("--camchain", help=camchain_help)
    p.add_argument("--target", help=target_help)


def add_parsers(sub: Any, parent: argparse.ArgumentParser) -> None:
    """Register ``calibrate`` and ``validate``."""
    c = common.add_command(
        sub, "calibrate", parent, "calibrate a DCC from target snapshots (bag, image folder or detection folder)",
        "Estimate the gimbal kinematics (tau_s, tau_d in rad/m, DH d/a in m, alpha in rad) and, in encoderless mode, "
        "the joint angles (rad) of every snapshot.", calibrate_command,
    )  # fmt: skip
    add_input_flags(
        c, "Kalibr camchain YAML: cam0 (static) and cam1 (dynamic) intrinsics in pixels, distortion, resolution and, "
        "for bags, each camera's image rostopic",
        "Kalibr target YAML (checkerboard or aprilgrid; sizes in metres); detection folders carry their own",
    )  # fmt: skip
    c.add_argument("--gimbal", help="initial kinematics YAML (joints, tau_s, tau_d, dh; rad and m)")
    add_solver_flags(c)
    add_cluster_flags(c)  # --cluster, --mounts: N-camera clusters (dcc_fg/commands/calibrate_cluster.py)
    c.add_argument("--out", default="dcc_fg_calibration", help="output folder for calibration.yaml, joint_angles.csv "
                   f"(ns, rad) and summary.json (default ./dcc_fg_calibration). {common.OUT_FOLDER_HELP}")  # fmt: skip
    add_reader_flags(c)
    common.add_config_flag(c, "calibrate")
    common.add_rerun_flags(c, RERUN_SHOWS)
    calibrate_incremental.add_incremental_flags(c)  # --incremental (dcc_fg/commands/calibrate_incremental.py)

    v = common.add_command(
        sub, "validate", parent, "hold a calibration fixed and estimate only the joint angles of new snapshots",
        "The paper's validation procedure: kinematics held at --calibration, joint angles (rad) estimated.",
        validate_command,
    )  # fmt: skip
    add_input_flags(
        v, "Kalibr camchain YAML (default: the intrinsics stored in the calibration; a bag then needs --camchain for "
        "its image topics)", "Kalibr target YAML (checkerboard or aprilgrid; sizes in metres)",
    )  # fmt: skip
    v.add_argument("--calibration", required=True, help="calibration.yaml written by dcc-fg calibrate")
    v.add_argument("--out", default="dcc_fg_validation", help="output folder for calibration.yaml (the held "
                   "kinematics), joint_angles.csv (ns, rad) and summary.json (default ./dcc_fg_validation); not the "
                   f"folder of --calibration. {common.OUT_FOLDER_HELP}")  # fmt: skip
    add_reader_flags(v)
    common.add_config_flag(v, "validate")
    common.add_rerun_flags(v, RERUN_SHOWS)


def calibrate_command(args: argparse.Namespace) -> int:
    if wants_cluster(args):  # N cameras: --cluster, or --camchain with --mounts
        return calibrate_cluster_command(args)
    if getattr(args, "incremental", False):  # calibrate as you record
        return calibrate_incremental.run_incremental_command(args)
    rerun = common.rerun_options(args)
    config = common.effective_config(args, CalibrateConfig, "calibrate")
    inputs = CalibrationInputs(args.data, camchain=args.camchain, target=args.target, gimbal=args.gimbal)
    run_calibrate(inputs, Path(args.out), config, common.progress_wanted(args), args.quiet, args.config, rerun)
    return 0


def validate_command(args: argparse.Namespace) -> int:
    rerun = common.rerun_options(args)
    config = common.effective_config(args, ValidateConfig, "validate")
    inputs = CalibrationInputs(args.data, camchain=args.camchain, target=args.target, calibration=args.calibration)
    run_validate(inputs, Path(args.out), config, common.progress_wanted(args), args.quiet, args.config, rerun)
    return 0
