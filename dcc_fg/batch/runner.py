"""Run a validated study on Dask: skip finished runs, simulate the flights, run the rest, write the table.

Every run (and every simulated flight) is one task of a ``dask.distributed`` cluster: by default a
:class:`~distributed.LocalCluster` of ``workers`` *processes* with one thread each (GTSAM, the front
end and the smoother hold the GIL, so threads would not run in parallel); with ``scheduler`` an
existing cluster (``tcp://HOST:8786``), whose workers must have dcc-fg installed and see the same
paths (a shared file system: the tasks carry absolute paths); start them without Dask's default
``MALLOC_TRIM_THRESHOLD_`` (see :data:`WORKER_ENVIRON`). A run on a simulated flight depends on
that flight's task, so a flight is rendered once for all its modes and before them; tasks are handed
out one per worker thread, most important first (:class:`Dispatcher`).

The study's timing: ``serial_s`` is the sum of the tasks' own wall times (what running them one after
the other would take), ``wall_s`` the time from the first submission to the last result (the
cluster's start-up, ``startup_s``, is reported apart), ``speedup = serial_s / wall_s``.
"""

from __future__ import annotations

import heapq
import logging
import secrets
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import dask
from distributed import Client, LocalCluster, as_completed

from dcc_fg.batch.study import FlightSpec, RunTask, Study
from dcc_fg.batch.table import CSV_NAME, FIGURE_NAME, MARKDOWN_NAME, csv_text, markdown_text, write_figure
from dcc_fg.batch.tasks import (
    base_row,
    clear_folder,
    dataset_complete,
    error_text,
    flight_bag_name,
    run_finished,
    simulate_flight_task,
    vio_run_task,
)
from dcc_fg.io.output_set import OutputSet
from dcc_fg.io.outputs import write_text_atomic
from dcc_fg.util.parallel import usable_cores

log = logging.getLogger("dcc_fg.batch")

#: Seconds to wait for an existing scheduler (``--scheduler``).
CONNECT_TIMEOUT_S = 30
#: Dask priorities: the flight simulations first (their runs wait for them), then the runs longest first
#: (dcc estimates the joints, scc holds them, mono reads one camera), so the last task is a short one.
SIMULATION_PRIORITY = 10
MODE_PRIORITY = {"dcc": 3, "scc": 2, "mono": 1}
#: Environment of the local cluster's workers: Dask's defaults (one BLAS/OpenMP thread per worker process)
#: without its ``MALLOC_TRIM_THRESHOLD_=65536``, which turns off glibc's dynamic mmap threshold so that
#: every image-sized buffer is a fresh ``mmap``: measured on a 12 s 640x480 flight, rendering 2.5x and
#: the dcc VIO 1.25x slower than outside Dask (``sys`` time 22 s instead of 2.5 s).
WORKER_ENVIRON = {"OMP_NUM_THREADS": 1, "MKL_NUM_THREADS": 1, "OPENBLAS_NUM_THREADS": 1}


@dataclass(frozen=True)
class BatchOptions:
    """``out``: the study's output folder; ``workers``: local Dask worker processes (None: every usable
    core); ``scheduler``: address of an existing Dask scheduler instead of a local cluster; ``force``:
    redo finished runs (simulated flights that are complete are still reused: they are fixed by their
    seed); ``command_line``: recorded in each run's ``summary.json``."""

    out: Path
    workers: int | None = None
    scheduler: str | None = None
    force: bool = False
    command_line: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.workers is not None and self.workers < 1:
            raise ValueError(f"--workers must be >= 1, got {self.workers}")
        if self.workers is not None and self.scheduler:
            raise ValueError("--workers and --scheduler exclude each other (the scheduler's cluster has its workers)")


@dataclass
class BatchResult:
    """What a study invocation did. ``rows``: the table rows in study order; counts of runs ``executed``
    now (``failed`` of them), ``reused`` from earlier invocations, flights ``simulated`` now; times in s
    (module docstring); ``files``: the table files by kind (``csv``, ``markdown``, ``figure``); ``schedule``:
    every task run now (``kind`` flight | run, ``label``, ``worker`` host:pid, ``started_unix`` s, ``seconds``)."""

    rows: list[dict[str, Any]]
    executed: int = 0
    reused: int = 0
    failed: int = 0
    simulated: int = 0
    workers: int = 0
    startup_s: float = 0.0
    wall_s: float = 0.0
    serial_s: float = 0.0
    files: dict[str, Path] = field(default_factory=dict)
    schedule: list[dict[str, Any]] = field(default_factory=list)

    @property
    def speedup(self) -> float | None:
        """Serial sum of the task times over the study's wall time (None when nothing ran)."""
        return self.serial_s / self.wall_s if self.wall_s > 0 and self.executed else None

    def timing_text(self) -> str:
        """``wall time vs serial sum`` (one line)."""
        if not self.executed and not self.simulated:
            return f"nothing to run: all {self.reused} runs reused from earlier invocations (--force redoes them)"
        ratio = self.speedup
        return (
            f"wall time {self.wall_s:.1f} s vs serial sum {self.serial_s:.1f} s of {self.executed} runs and "
            f"{self.simulated} simulated flights: {ratio:.2f}x on {self.workers} Dask workers "
            f"(+ {self.startup_s:.1f} s cluster start-up); {self.reused} runs reused, {self.failed} failed"
        )


@dataclass(frozen=True)
class Layout:
    """Where a study writes (all under ``out``): ``runs/RUN_ID``, ``data/FLIGHT``, ``logs/NAME.log``."""

    out: Path

    def run(self, task: RunTask) -> Path:
        return self.out / "runs" / task.run_id

    def run_log(self, task: RunTask) -> Path:
        return self.out / "logs" / f"{task.run_id}.log"

    def flight(self, spec: FlightSpec) -> Path:
        return self.out / "data" / spec.folder_name

    def flight_log(self, spec: FlightSpec) -> Path:
        return self.out / "logs" / f"simulate-{spec.folder_name}.log"


@contextmanager
def dask_client(workers: int, scheduler: str | None) -> Iterator[Client]:
    """A client of the scheduler at ``scheduler``, or of a new local cluster of ``workers`` single-threaded
    worker processes with :data:`WORKER_ENVIRON` (a run may still start the VIO's front-end process: it is
    a subprocess, not a multiprocessing child of the daemonic worker)."""
    if scheduler:
        with Client(scheduler, timeout=CONNECT_TIMEOUT_S) as client:
            yield client
        return
    with dask.config.set({"distributed.nanny.pre-spawn-environ": WORKER_ENVIRON}):
        cluster = LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=logging.ERROR
        )
    with cluster, Client(cluster) as client:
        yield client


def finished_rows(study: Study, layout: Layout, force: bool) -> dict[str, dict[str, Any]]:
    """The rows of the runs finished in earlier invocations, by run id (none with ``force``)."""
    if force:
        return {}
    done = {}
    for task in study.tasks:
        row = run_finished(task, layout.run(task))
        if row is not None:
            done[task.run_id] = {**row, "reused": True}
    return done


def flight_input(spec: FlightSpec, layout: Layout) -> dict[str, Any]:
    """A complete flight's description (as :func:`simulate_flight_task` returns it, time 0)."""
    folder = layout.flight(spec)
    return {"folder": str(folder), "bag": str(folder / flight_bag_name(spec)),
            "calibration": str(folder / "calibration.yaml"), "reused": True, "error": None, "seconds": 0.0}  # fmt: skip


class Dispatcher:
    """Feeds the cluster one task per worker thread, most important first, and collects the results.

    Dask assigns a task with dependencies to a worker as soon as they are done, which can queue several
    long runs on one worker while another idles; so tasks are submitted only when a thread is free
    (``capacity`` in flight), from a priority queue: flights first (their runs become ready when the
    flight is written), then the runs longest first (:data:`MODE_PRIORITY`). A task that died (e.g. a
    killed worker) is a failed run; the runs of a flight that failed report the flight's error.
    """

    def __init__(self, client: Client, layout: Layout, options: BatchOptions, result: BatchResult, total: int):
        self.client, self.layout, self.options, self.result, self.total = client, layout, options, result, total
        self.token = secrets.token_hex(4)
        self.ready: list[tuple[int, int, str, Any, Any]] = []  # (-priority, order, kind, item, dataset)
        self.waiting: dict[FlightSpec, list[RunTask]] = {}
        self.what: dict[str, tuple[str, Any]] = {}
        self.rows: dict[str, dict[str, Any]] = {}
        self.order = 0

    def push(self, priority: int, kind: str, item: Any, dataset: Any = None) -> None:
        heapq.heappush(self.ready, (-priority, self.order, kind, item, dataset))
        self.order += 1

    def plan(self, todo: list[RunTask]) -> None:
        """Queue the flights to simulate and the runs that are ready (a complete flight is reused)."""
        flights: dict[FlightSpec, dict[str, Any] | None] = {}
        for task in todo:
            if self.options.force:
                clear_folder(self.layout.run(task))
            if not isinstance(task.data, FlightSpec):
                self.push(MODE_PRIORITY[task.mode], "run", task)
                continue
            spec = task.data
            if spec not in flights:
                complete = dataset_complete(spec, self.layout.flight(spec))
                flights[spec] = flight_input(spec, self.layout) if complete else None
                if not complete:
                    self.push(SIMULATION_PRIORITY, "flight", spec)
            if flights[spec] is None:
                self.waiting.setdefault(spec, []).append(task)
            else:
                self.push(MODE_PRIORITY[task.mode], "run", task, flights[spec])

    def submit_next(self, done: as_completed) -> None:
        _, _, kind, item, dataset = heapq.heappop(self.ready)
        if kind == "flight":
            args: tuple[Any, ...] = (simulate_flight_task, item, str(self.layout.flight(item)),
                                     str(self.layout.flight_log(item)))  # fmt: skip
            key = f"simulate-{item.folder_name}-{self.token}"
        else:
            args = (vio_run_task, item, str(self.layout.run(item)), str(self.layout.run_log(item)), dataset,
                    list(self.options.command_line))  # fmt: skip
            key = f"run-{item.run_id}-{self.token}"
        fut = self.client.submit(*args, key=key)
        self.what[fut.key] = (kind, item)
        done.add(fut)

    def run(self, todo: list[RunTask]) -> dict[str, dict[str, Any]]:
        """Execute ``todo``; the new rows by run id."""
        self.plan(todo)
        capacity = max(1, sum(self.client.nthreads().values()))
        done = as_completed()
        while self.ready and done.count() < capacity:
            self.submit_next(done)
        for fut in done:
            kind, item = self.what[fut.key]
            exc = fut.exception() if fut.status == "error" else None
            if kind == "flight":
                self.flight_done(item, fut.result() if exc is None else {"error": error_text(exc), "seconds": 0.0})
            else:
                row = fut.result() if exc is None else {**base_row(item, self.layout.run(item)),
                                                        "error": error_text(exc), "wall_s": 0.0}  # fmt: skip
                self.run_done(item, row)
            while self.ready and done.count() < capacity:
                self.submit_next(done)
        return self.rows

    def flight_done(self, spec: FlightSpec, value: dict[str, Any]) -> None:
        result = self.result
        if value.get("error"):
            log.warning("flight %s: %s", spec.folder_name, value["error"])
        else:
            result.simulated += 1
            log.info("simulated flight %s in %.1f s", spec.folder_name, value["seconds"])
        result.serial_s += float(value.get("seconds") or 0.0)
        when = {k: value.get(k) for k in ("worker", "started_unix", "seconds")}
        result.schedule.append({"kind": "flight", "label": spec.folder_name, **when})
        for task in self.waiting.pop(spec, []):
            self.push(MODE_PRIORITY[task.mode], "run", task, value)

    def run_done(self, task: RunTask, row: dict[str, Any]) -> None:
        result = self.result
        self.rows[task.run_id] = row
        result.executed += 1
        result.failed += row["status"] != "ok"
        result.serial_s += float(row.get("wall_s") or 0.0)
        result.schedule.append({"kind": "run", "label": task.run_id, "worker": row.get("worker"),
                                "started_unix": row.get("started_unix"), "seconds": row.get("wall_s")})  # fmt: skip
        n = len(self.rows) + result.reused
        if row["status"] == "ok":
            rmse = row.get("normalized_translation_rmse_percent")
            log.info("[%d/%d] %s %s: ok, norm. transl. RMSE %s %%, %.1f s", n, self.total, task.name, task.mode,
                     "-" if rmse is None else f"{rmse:.4f}", row.get("wall_s") or 0.0)  # fmt: skip
        else:
            log.warning("[%d/%d] %s %s: failed: %s (log: %s)", n, self.total, task.name, task.mode, row["error"],
                        self.layout.run_log(task))  # fmt: skip


def write_table(outputs: OutputSet, result: BatchResult) -> dict[str, Path]:
    """``results.csv``, ``results.md`` and ``results_rmse.png`` into OUT as one output set."""
    with outputs:
        write_text_atomic(outputs.path / CSV_NAME, csv_text(result.rows))
        write_text_atomic(outputs.path / MARKDOWN_NAME, markdown_text(result.rows, result.timing_text()))
        write_figure(result.rows, outputs.path / FIGURE_NAME)
    return {"csv": outputs.out / CSV_NAME, "markdown": outputs.out / MARKDOWN_NAME, "figure": outputs.out / FIGURE_NAME}


def run_study(study: Study, options: BatchOptions) -> BatchResult:
    """Execute every run of ``study`` not finished before, gather every row and write the table (module
    docstring). A failed run is a row with its error; only a bad ``out`` or a cluster that cannot be
    reached raise."""
    layout = Layout(options.out.resolve())
    outputs = OutputSet(layout.out, "batch", study.inputs())  # checks OUT before any work
    done = finished_rows(study, layout, options.force)
    todo = [t for t in study.tasks if t.run_id not in done]
    workers = options.workers or usable_cores()
    result = BatchResult(rows=[], reused=len(done), workers=workers if not options.scheduler else 0)
    log.info("study %s: %d runs, %d reused from earlier invocations, %d to run", study.path, len(study.tasks),
             len(done), len(todo))  # fmt: skip
    new: dict[str, dict[str, Any]] = {}
    if todo:
        t0 = time.perf_counter()
        with dask_client(min(workers, len(todo)), options.scheduler) as client:
            result.workers = len(client.scheduler_info().get("workers", {})) or workers
            result.startup_s = time.perf_counter() - t0
            t1 = time.perf_counter()
            new = Dispatcher(client, layout, options, result, len(study.tasks)).run(todo)
            result.wall_s = time.perf_counter() - t1
    result.rows = [new.get(t.run_id) or done[t.run_id] for t in study.tasks]
    result.files = write_table(outputs, result)
    return result
