"""``dcc-fg batch STUDY.yaml [--out OUT] [--workers N | --scheduler ADDRESS] [--force]``.

Validates the study file (:mod:`dcc_fg.batch`, schema in its docstring), runs every run and mode not
finished before on Dask, and prints the Markdown table and the wall time against the serial sum of
the runs' times. Exit code 0 when the table was written, even if some runs failed (they are rows
with their error; ``--strict`` makes a failed run exit 1); 2 for an invalid study file or ``--out``.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from dcc_fg.batch import BatchOptions, load_study, run_study
from dcc_fg.batch.table import markdown_by_mode, markdown_runs
from dcc_fg.commands import common
from dcc_fg.util.provenance import run_record

#: Exit code of ``--strict`` when a run failed.
EXIT_RUN_FAILED = 1

BATCH_SUMMARY = "run a study (bags or simulated flights x modes x options) on Dask and tabulate the results"
BATCH_DESCRIPTION = (
    "Every run and mode of STUDY.yaml is one task on a Dask cluster (a local one of --workers single-threaded "
    "processes, or --scheduler), is evaluated against its ground truth (normalized translation RMSE, APE, joint RMSE, "
    "real-time factor) and becomes a row of OUT/results.csv, OUT/results.md and OUT/results_rmse.png. A failed run "
    "is a row with its error and does not stop the others; runs finished in an earlier invocation are reused "
    "(OUT/runs/NAME-MODE-HASH/result.json; --force redoes them). The study file is validated before any run "
    "starts. Schema: see the docstring of dcc_fg.batch or the README."
)


def batch_command(args: argparse.Namespace) -> int:
    """The ``dcc-fg batch`` subcommand."""
    study = load_study(args.study)
    out = Path(args.out) if args.out else study.out
    if out is None:
        raise ValueError(f"{args.study}: no output folder: give --out or 'out:' in the study file")
    command_line = tuple(run_record("batch", {}, None)["command_line"])
    options = BatchOptions(out, args.workers, args.scheduler, args.force, command_line)
    result = run_study(study, options)
    if not args.quiet:
        print(markdown_runs(result.rows))
        print()
        print(markdown_by_mode(result.rows))
        print()
        print(result.timing_text())
        print("wrote " + ", ".join(str(p) for p in result.files.values()))
    failed = sum(r["status"] != "ok" for r in result.rows)
    return EXIT_RUN_FAILED if args.strict and failed else 0


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def add_parser(sub: Any, parent: argparse.ArgumentParser) -> None:
    """Register ``dcc-fg batch``."""
    b = common.add_command(sub, "batch", parent, BATCH_SUMMARY, BATCH_DESCRIPTION, batch_command)
    b.add_argument("study", help="study YAML: out, defaults, runs (name, simulate | bag + calibration + ground_truth, "
                   "modes, options, vio)")  # fmt: skip
    b.add_argument("--out", help="output folder (default: the study file's 'out'); checked before any run")
    where = b.add_mutually_exclusive_group()
    where.add_argument("--workers", type=positive_int, help="local Dask worker processes (default: every usable core)")
    where.add_argument("--scheduler", metavar="ADDRESS", help="an existing Dask scheduler, e.g. tcp://host:8786; its "
                       "workers need dcc-fg installed and the study's paths on a shared file system")  # fmt: skip
    b.add_argument("--force", action="store_true", help="redo the runs finished in an earlier invocation")
    b.add_argument("--strict", action="store_true", help=f"exit {EXIT_RUN_FAILED} when any run failed")
