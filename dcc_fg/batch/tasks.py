"""What a Dask worker runs for ``dcc-fg batch``: simulate a flight, or run, evaluate and record one VIO run.

Both are plain top-level functions of picklable arguments (paths are absolute strings: a worker on
another machine needs the same file system) that never raise for a problem of the run itself: a
failure comes back as a row with ``status: failed`` and its error, so one bad recording cannot stop
the study. Each VIO run writes, into its own folder ``OUT/runs/NAME-MODE-HASH``:

* the ``dcc-fg vio`` outputs (``trajectory.tum``, ``joint_angles.csv``, ``summary.json`` with the
  real-time factor; :func:`dcc_fg.commands.vio.run_vio`),
* ``evaluation.json`` attached like ``dcc-fg evaluate`` (APE / normalized RMSE / joint RMSE against the
  ground truth; :func:`dcc_fg.commands.evaluate.evaluation`),
* ``result.json`` last: the table row and the hashed spec. A folder with ``summary.json`` and a
  ``result.json`` of status ``ok`` and the same spec hash is a *finished* run, reused next time.

The dcc_fg log of each run goes to ``OUT/logs/NAME-MODE-HASH.log`` (tracebacks of unexpected errors
included), not to the worker's stderr.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import socket
import time
from pathlib import Path
from typing import Any

import yaml

from dcc_fg.batch.study import BagSpec, FlightSpec, RunTask
from dcc_fg.commands.evaluate import evaluation
from dcc_fg.commands.vio import VioInputs, run_vio
from dcc_fg.io.output_set import OutputSet
from dcc_fg.io.outputs import write_json
from dcc_fg.sim.flight_bag import write_flight
from dcc_fg.sim.trajectory import FlightConfig, locked_gimbal
from dcc_fg.util.config import ConfigError
from dcc_fg.util.errors import EstimatorError
from dcc_fg.util.health import UnhealthyResultError
from dcc_fg.util.logs import DATE_FORMAT, FORMAT
from dcc_fg.util.provenance import set_command_line

#: Files of a finished run folder.
RESULT_NAME = "result.json"
SUMMARY_NAME = "summary.json"
EVALUATION_NAME = "evaluation.json"
#: Marker of a complete simulated flight folder (its spec).
DATASET_NAME = "dataset.json"
LOGGERS = ("dcc_fg", "factors", "py.warnings")


def error_text(exc: BaseException) -> str:
    """One line for the table: an unhealthy result names its failed checks; the errors dcc-fg raises for
    bad input (ValueError, FileNotFoundError, EstimatorError) their message; anything else (e.g. a
    UnicodeDecodeError of a garbage bag) its type and message."""
    if isinstance(exc, UnhealthyResultError):
        checks = "; ".join(f"{c.name}: {c.message}" for c in exc.report.failures)
        return f"unhealthy {exc.report.subject}: {checks}"
    text = " ".join(str(exc).split()) or type(exc).__name__
    if type(exc) in (ValueError, FileNotFoundError) or isinstance(exc, ConfigError | EstimatorError):
        return text
    return f"{type(exc).__name__}: {text}"


class RunLog:
    """Send the dcc_fg log to ``path`` (INFO and above) for the duration of a ``with`` block, instead of
    the worker's stderr; the loggers' previous state is restored afterwards."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.handler: logging.FileHandler | None = None
        self.saved: list[tuple[logging.Logger, int, bool]] = []

    def __enter__(self) -> RunLog:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.handler = logging.FileHandler(self.path, mode="w", encoding="utf-8")
        self.handler.setFormatter(logging.Formatter(FORMAT, DATE_FORMAT))
        for name in LOGGERS:
            logger = logging.getLogger(name)
            self.saved.append((logger, logger.level, logger.propagate))
            logger.addHandler(self.handler)
            logger.setLevel(logging.INFO)
            logger.propagate = False
        logging.captureWarnings(True)
        return self

    def __exit__(self, *exc: object) -> None:
        for logger, level, propagate in self.saved:
            logger.removeHandler(self.handler)  # type: ignore[arg-type]
            logger.setLevel(level)
            logger.propagate = propagate
        if self.handler is not None:
            self.handler.close()


def flight_bag_name(spec: FlightSpec) -> str:
    return "flight.bag" if spec.format == "ros1" else "flight"


def dataset_complete(spec: FlightSpec, folder: Path) -> bool:
    """True when ``folder`` holds the flight of ``spec`` written completely by an earlier study."""
    marker = folder / DATASET_NAME
    try:
        return bool(json.loads(marker.read_text()).get("spec") == spec.key())
    except (OSError, ValueError):
        return False


def simulate_flight_task(spec: FlightSpec, folder: str, log_path: str) -> dict[str, Any]:
    """Render the flight ``spec`` into ``folder`` (or reuse a complete one): ``{"folder", "bag",
    "calibration", "seconds", "reused", "error"}`` with ``error`` None on success, else one line."""
    out = Path(folder)
    t0 = time.perf_counter()
    result: dict[str, Any] = {**where_and_when(), "folder": folder, "bag": str(out / flight_bag_name(spec)),
                              "calibration": str(out / "calibration.yaml"), "reused": False, "error": None}  # fmt: skip
    if dataset_complete(spec, out):
        return {**result, "reused": True, "seconds": 0.0}
    with RunLog(Path(log_path)):
        log = logging.getLogger("dcc_fg.batch")
        try:
            config = FlightConfig.short(spec.duration) if spec.pattern == "short" else FlightConfig(spec.duration)
            joints = locked_gimbal() if spec.gimbal == "locked" else None
            write_flight(out, spec.format, config, seed=spec.seed, scale=spec.scale, noise_sigma=spec.noise,  # type: ignore[arg-type]
                         joints=joints, force=True)  # fmt: skip
            write_json(out / DATASET_NAME, {"spec": spec.key()})
        except Exception as exc:  # the study goes on; the runs on this flight report it
            log.exception("simulating %s failed", folder)
            result["error"] = f"simulating the flight failed: {error_text(exc)}"
    return {**result, "seconds": time.perf_counter() - t0}


def run_finished(task: RunTask, folder: Path) -> dict[str, Any] | None:
    """The stored row of a finished run in ``folder`` (status ok, same spec hash, summary present), else None."""
    try:
        stored = json.loads((folder / RESULT_NAME).read_text())
    except (OSError, ValueError):
        return None
    row = stored.get("row") if isinstance(stored, dict) else None
    if not isinstance(row, dict) or row.get("status") != "ok" or stored.get("spec_hash") != task.spec_hash:
        return None
    if not (folder / SUMMARY_NAME).is_file():
        return None
    return row


def where_and_when() -> dict[str, Any]:
    """Which process ran a task (``host:pid``) and when it started (Unix time, s): the study's schedule."""
    return {"worker": f"{socket.gethostname()}:{os.getpid()}", "started_unix": time.time()}


def base_row(task: RunTask, folder: Path) -> dict[str, Any]:
    """The row fields known before the run."""
    return {"name": task.name, "mode": task.mode, "status": "failed", "error": None, "run_id": task.run_id,
            "spec_hash": task.spec_hash, "folder": str(folder), "reused": False}  # fmt: skip


def result_row(task: RunTask, folder: Path, wall_s: float) -> dict[str, Any]:
    """The row of a successful run, from its ``summary.json`` and ``evaluation.json``.

    Units: normalized translation RMSE in % of the distance travelled, APE RMSE in m (after SE(3)
    alignment, Sim(3) for mono), joint-angle RMSE per joint in rad (None for mono/scc), real-time
    factor = processing time / data duration, wall time of run + evaluation in s."""
    summary = json.loads((folder / SUMMARY_NAME).read_text())
    ev = json.loads((folder / EVALUATION_NAME).read_text())
    joints = ev.get("joint_rmse_rad") if task.mode == "dcc" else None
    return {
        **base_row(task, folder),
        "status": "ok",
        "normalized_translation_rmse_percent": ev.get("normalized_translation_rmse_percent"),
        "ape_rmse_m": ev.get("ape_rmse_m"),
        "joint_rmse_rad": joints,
        "real_time_factor": summary.get("real_time_factor"),
        "processing_time_s": summary.get("processing_time_s"),
        "data_duration_s": summary.get("data_duration_s"),
        "distance_m": ev.get("distance_m"),
        "segments": summary.get("segment_count"),
        "wall_s": wall_s,
    }


def inputs_of(task: RunTask, dataset: dict[str, Any] | None) -> tuple[VioInputs, str]:
    """The ``dcc-fg vio`` inputs and the ground truth (a simulated flight's bag carries it)."""
    if isinstance(task.data, BagSpec):
        d = task.data
        return VioInputs(d.bag, d.calibration, d.imu_yaml, d.camchain), d.ground_truth
    assert dataset is not None
    return VioInputs(dataset["bag"], dataset["calibration"]), dataset["bag"]


def vio_run_task(task: RunTask, folder: str, log_path: str, dataset: dict[str, Any] | None = None,
                 command_line: list[str] | None = None) -> dict[str, Any]:  # fmt: skip
    """Run, evaluate and record one VIO run (module docstring); returns its row (never raises for a
    failed run: the row says ``failed`` with :func:`error_text`). ``dataset`` is the result of
    :func:`simulate_flight_task` for a simulated flight."""
    out = Path(folder)
    row = {**base_row(task, out), **where_and_when()}
    t0 = time.perf_counter()
    if dataset is not None and dataset.get("error"):
        return {**row, "error": dataset["error"], "wall_s": 0.0}
    set_command_line(command_line)
    (out / RESULT_NAME).unlink(missing_ok=True)
    with RunLog(Path(log_path)):
        log = logging.getLogger("dcc_fg.batch")
        try:
            inputs, ground_truth = inputs_of(task, dataset)
            run_vio(inputs, out, task.config, quiet=True, config_source=f"study run {task.name} ({task.mode})")
            evaluate = OutputSet(out, "evaluate", {"--ground-truth": ground_truth}, option="OUT")
            with evaluate:
                write_json(evaluate.path / EVALUATION_NAME, evaluation(out, Path(ground_truth)))
            row = {**row, **result_row(task, out, time.perf_counter() - t0)}
            write_json(out / RESULT_NAME, {"spec_hash": task.spec_hash, "spec": task.spec(), "row": row})
            log.info("run %s finished: %s", task.run_id, yaml.safe_dump(row, sort_keys=False).strip())
        except Exception as exc:  # reported in the table; the other runs go on
            log.exception("run %s failed", task.run_id)
            row = {**row, "error": error_text(exc), "wall_s": time.perf_counter() - t0}
    return row


def clear_folder(folder: Path) -> None:
    """Remove a run folder (``--force``) so the run starts from nothing."""
    if folder.is_dir():
        shutil.rmtree(folder)
