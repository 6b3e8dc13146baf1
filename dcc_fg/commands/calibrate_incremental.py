"""``dcc-fg calibrate --incremental``: calibrate as you record (:mod:`dcc_fg.incremental`).

Snapshots arrive one at a time and the calibration is re-solved after each (warm start; the global
strategy at the first solve and occasionally after); after each one a line is printed with the solve
time, the RMS residual (px), the predicted worst and mean 1-sigma of ``T_ds`` over the operating range
(mrad / mm) and the next suggested joint angles (deg), or ``DONE`` when the worst 1-sigma is within
``--tolerance``: a person recording by hand knows when to stop.

Sources (DATA as for ``calibrate``):

* an image folder or detection folder (``cam0/``, ``cam1/``) is **polled** every ``--poll-seconds``
  for new files; a poll that finds a file added or changed re-reads the folder listing (an image file
  already read, same path, size and modification time, is neither decoded nor detected again), pairs
  the frames as the normal reader does and feeds the pairs not fed before in time order. A file that cannot be read
  yet (still being written) makes the poll wait for the next one: write each file under a temporary
  name and rename it into place. The run
  stops after ``--idle-timeout`` seconds without a new snapshot, or at Ctrl-C;
* a ROS1/ROS2 bag (a finished recording) is read once and its pairs are fed in order, as if arriving.

Then the final calibration of all snapshots (:meth:`dcc_fg.incremental.IncrementalCalibration.finish`,
the batch result, with covariances) is written exactly as ``dcc-fg calibrate`` writes it (one output
set, health checks); ``summary.json`` gets ``input.incremental`` (the per-update log).
Encoderless, bundle formulation, ``--sync tolerance`` only.
"""

from __future__ import annotations

import argparse
import hashlib
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from numpy.typing import NDArray

from dcc_fg.calibrate import CalibrationResult
from dcc_fg.commands import calibrate as calibrate_cmd
from dcc_fg.commands import common
from dcc_fg.commands.incremental_settings import IncrementalSettings
from dcc_fg.data import CalibrationDataset, Observation, Snapshot, common_corners
from dcc_fg.detection import detect_target
from dcc_fg.incremental import IncrementalCalibration, IncrementalOptions, Update
from dcc_fg.io.layout import detect_layout
from dcc_fg.io.output_set import DeferredInterrupt, OutputSet
from dcc_fg.model import GimbalCalibration
from dcc_fg.planning.range_spec import parse_range, parse_tolerance
from dcc_fg.sources.dataset import FileDetections, load_dataset
from dcc_fg.targets import TargetGeometry
from dcc_fg.util.config import ConfigError
from dcc_fg.util.provenance import run_record

FOLDER_LAYOUTS = ("image_folder", "detection_folder")


class SnapshotSource:
    """New snapshots of DATA, poll by poll (module docstring). ``template`` holds the cameras and the
    target once a poll succeeded; ``finished`` once a bag was read; ``last_error`` the reader's last
    complaint (a folder not complete yet); ``report`` the reader's counts of the last poll."""

    def __init__(
        self, path: str | Path, camchain: Any, target: str | None, reader: calibrate_cmd.ReaderOptions
    ) -> None:
        self.path = Path(path)
        self.camchain = camchain
        self.target = target
        self.reader = reader
        self.template: CalibrationDataset | None = None
        self.finished = False
        self.last_error = ""
        self.report: dict[str, Any] = {}
        self._seen: set[int] = set()
        self._detections: dict[bytes, Observation] = {}
        self._file_detections: FileDetections = {}  # image folders: by (path, size, mtime)
        self._listing: tuple[tuple[str, int, int], ...] | None = None
        # a folder that does not exist yet or is still empty is polled; a bag is read once
        self.is_folder = not self.path.exists() or (self.path.is_dir() and not (self.path / "metadata.yaml").exists())
        if not self.is_folder:
            self.is_folder = detect_layout(self.path) in FOLDER_LAYOUTS

    def _detect(self, image: NDArray[Any], target: TargetGeometry) -> Observation:
        """:func:`dcc_fg.detection.detect_target`, each distinct image detected once."""
        key = hashlib.blake2b(image.tobytes(), digest_size=16).digest() + str(image.shape).encode()
        if key not in self._detections:
            self._detections[key] = detect_target(image, target)
        return self._detections[key]

    def listing(self) -> tuple[tuple[str, int, int], ...]:
        """(relative path, size in bytes, modification time in ns) of every file of the folder, sorted."""
        if not self.path.is_dir():
            return ()
        out = []
        for f in self.path.rglob("*"):
            try:
                st = f.stat()
            except OSError:  # removed or renamed meanwhile
                continue
            if f.is_file():
                out.append((str(f.relative_to(self.path)), int(st.st_size), int(st.st_mtime_ns)))
        return tuple(sorted(out))

    def poll(self) -> list[Snapshot]:
        """The snapshots not returned before, in time order (none when the folder cannot be read yet, or
        when no file changed since the last successful read)."""
        if self.finished:
            return []
        listing = self.listing() if self.is_folder else None
        if listing is not None and listing == self._listing:
            return []
        report: dict[str, Any] = {}
        try:
            data = load_dataset(
                self.path,
                camchain=self.camchain,
                target=self.target,
                tolerance_ns=int(round(self.reader.sync_tolerance_ms * 1e6)),
                min_common_points=self.reader.min_common_points,
                detector=self._detect,
                progress=False,
                report=report,
                jobs=1 if self.is_folder else max(self.reader.jobs, 1),
                file_cache=self._file_detections if self.is_folder else None,
            )
        except (ValueError, OSError) as exc:
            if not self.is_folder:
                raise
            self.last_error = str(exc)
            return []
        self.finished = not self.is_folder
        self._listing = listing
        self.last_error = ""
        self.report = report
        if self.reader.corners == "common":
            data = common_corners(data)
        self.template = replace(data, snapshots=[])
        new = sorted((s for s in data.snapshots if s.timestamp_ns not in self._seen), key=lambda s: s.timestamp_ns)
        self._seen.update(s.timestamp_ns for s in new)
        return new


def incremental_options(
    config: calibrate_cmd.CalibrateConfig, settings: IncrementalSettings, n_joints: int
) -> IncrementalOptions:
    """The estimator's options from the calibrate configuration and the ``--incremental`` settings."""
    ranges = parse_range(settings.range, n_joints) if settings.range else None
    return IncrementalOptions(
        solver=config.solver,
        ranges=ranges,
        tolerance=parse_tolerance(settings.tolerance),
        background=settings.background,
    )


def feed(
    source: SnapshotSource,
    make: Callable[[CalibrationDataset], IncrementalCalibration],
    settings: IncrementalSettings,
    emit: Callable[[str], None] = print,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
) -> IncrementalCalibration | None:
    """Poll ``source`` and add every new snapshot to the calibration (made by ``make`` from the first
    poll's cameras and target), printing each update's line through ``emit``; until a bag is read,
    ``settings.idle_timeout`` passes without a new snapshot, or Ctrl-C (which never interrupts an update
    halfway). Returns the calibration (None when no snapshot arrived)."""
    inc: IncrementalCalibration | None = None
    last_new = clock()
    try:
        while True:
            for snap in source.poll():
                if inc is None:
                    assert source.template is not None
                    inc = make(source.template)
                with DeferredInterrupt():
                    try:
                        update: Update = inc.add(snap)
                    except ValueError as exc:  # an unusable snapshot: skipped, said
                        emit(f"skipped snapshot t={snap.timestamp_ns} ns: {exc}")
                        continue
                emit(update.line())
                last_new = clock()
            if inc is not None:  # a background solve that finished while no snapshot came
                with DeferredInterrupt():
                    adopted = inc.poll()
                if adopted is not None:
                    emit(adopted.line())
            if source.finished or clock() - last_new >= settings.idle_timeout:
                if source.is_folder:
                    emit(f"no new snapshot for {settings.idle_timeout:g} s: stopping")
                break
            sleep(settings.poll_seconds)
    except KeyboardInterrupt:
        emit("interrupted (Ctrl-C): stopping and writing the calibration of the snapshots so far")
    return inc


def run_incremental(
    inputs: calibrate_cmd.CalibrationInputs,
    out: Path,
    config: calibrate_cmd.CalibrateConfig,
    settings: IncrementalSettings,
    quiet: bool = False,
    config_file: str | Path | None = None,
    sleep: Callable[[float], None] = time.sleep,
) -> CalibrationResult:
    """``dcc-fg calibrate --incremental`` (module docstring): feed, then write ``out`` as ``calibrate`` does."""
    if config.solver.mode != "encoderless" or config.solver.formulation != "bundle":
        raise ConfigError("--incremental calibrates encoderless with the bundle formulation (--mode, --formulation)")
    if config.reader.sync != "tolerance":
        raise ConfigError("--incremental pairs images by --sync tolerance (not --sync interpolate)")
    initial: GimbalCalibration | None
    initial, _ = calibrate_cmd.initial_values(inputs, config.init, config.solver.mode, None)  # type: ignore[arg-type]
    if initial is not None:
        initial.require_two_cameras("calibration")
    n_joints = initial.n_joints if initial is not None else int(config.init.joints)  # type: ignore[arg-type]
    options = incremental_options(config, settings, n_joints)  # option errors before the work
    outputs = OutputSet(out, "calibrate", inputs.by_option(config_file))
    source = SnapshotSource(inputs.data, inputs.camchain, inputs.target, config.reader)
    emit: Callable[[str], None] = (lambda _line: None) if quiet else print

    def make(template: CalibrationDataset) -> IncrementalCalibration:
        return IncrementalCalibration(template, n_joints, options, initial)

    with outputs:
        inc = feed(source, make, settings, emit, sleep=sleep)
        if inc is None:
            why = f" (last reader message: {source.last_error})" if source.last_error else ""
            raise ValueError(f"{inputs.data}: no usable snapshot arrived{why}")
        try:
            if not inc.solving:
                adopted = inc.wait()  # a first solve still running in the background
                if adopted is not None:
                    emit(adopted.line())
            if not inc.solving:
                last = inc.updates[-1].reason if inc.updates else ""
                why = f" ({last})" if last else ""
                if source.last_error:
                    why += f" (last reader message: {source.last_error})"
                raise ValueError(f"{inputs.data}: {len(inc.snapshots)} usable snapshot(s) arrived, too few for a "
                                 f"calibration or no first solution{why}")  # fmt: skip
            result = inc.finish()
        finally:
            inc.close()
        data = inc.data
        report = {"min_common_points": config.reader.min_common_points, "corners": config.reader.corners}
        report.update(source.report)
        report["incremental"] = {
            "settings": {"poll_seconds": settings.poll_seconds, "idle_timeout_s": settings.idle_timeout,
                         "tolerance": settings.tolerance, "range": settings.range},
            "updates": result.extra["incremental"]["updates"],
        }  # fmt: skip
        provenance = run_record("calibrate", inputs.paths(), config)
        paths = calibrate_cmd.write_calibration_set(outputs, result, data, report, provenance, config)
    calibrate_cmd.print_written(result, paths, quiet)
    return result


def add_incremental_flags(c: argparse.ArgumentParser) -> None:
    """``--incremental`` and its options on the ``calibrate`` parser."""
    g = c.add_argument_group("calibrate as you record (--incremental)")
    g.add_argument("--incremental", action="store_true", help="re-solve as snapshots arrive (an image or detection "
                   "folder is polled for new files, a bag is read pair by pair) and print, after each, the RMS "
                   "residual, the predicted worst / mean T_ds 1-sigma over the operating range and the next suggested "
                   "joint angles, or DONE once within --tolerance; stops after --idle-timeout s without new data or at "
                   "Ctrl-C, then writes the calibration as without --incremental (encoderless, bundle)")  # fmt: skip
    opt = common.add_option
    opt(g, "--poll-seconds", "incremental.poll_seconds", type=float, metavar="S",
        help="--incremental: seconds between polls of a folder (default 1)")  # fmt: skip
    opt(g, "--idle-timeout", "incremental.idle_timeout", type=float, metavar="S",
        help="--incremental: stop after S seconds without a new snapshot (default 30)")  # fmt: skip
    opt(g, "--tolerance", "incremental.tolerance", metavar="ROT,TRANS", help="--incremental: largest acceptable "
        "worst-case 1-sigma of T_ds over the range, rotation (urad|mrad|rad|deg) and translation (um|mm|cm|m), "
        "default 1mrad,1mm")  # fmt: skip
    opt(g, "--blocking-solves", "incremental.background", action="store_false",
        help="--incremental: run the global solves inside the updates (default: in a background process, so "
        "no update waits for one)")  # fmt: skip
    opt(g, "--range", "incremental.range", metavar="LO:HI,...", help="--incremental: operating range, degrees per "
        "joint (the calibration's joint-angle convention); default: the data's range plus a margin")  # fmt: skip


def run_incremental_command(args: argparse.Namespace) -> int:
    """The ``--incremental`` branch of ``calibrate_command``."""
    if getattr(args, "rerun", None) or getattr(args, "rerun_spawn", False):
        raise ValueError("--incremental does not record for Rerun; run without --incremental for --rerun")
    config = common.effective_config(args, calibrate_cmd.CalibrateConfig, "calibrate")
    settings = config.incremental
    inputs = calibrate_cmd.CalibrationInputs(args.data, camchain=args.camchain, target=args.target, gimbal=args.gimbal)
    run_incremental(inputs, Path(args.out), config, settings, args.quiet, args.config)
    return 0
