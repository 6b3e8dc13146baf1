"""Command-line interface: ``dcc-fg demo | calibrate | validate | intrinsics | simulate | vio | evaluate | config |
export | batch``.

This module only assembles the subcommands of :mod:`dcc_fg.commands`, sets up logging
(``-v`` / ``-q``) and turns failures into messages without traceback. Exit codes:

* 0: success;
* 2: bad input (``ValueError``, ``FileNotFoundError``, malformed YAML, an invalid ``--config``, an
  unusable ``--out``), an estimator that failed numerically (:class:`~dcc_fg.util.errors.EstimatorError`,
  or a gtsam ``RuntimeError`` / numpy ``LinAlgError`` that no stage wrapped: the stage and a hint are
  named) or a file system error (``OSError``: permission denied, disk full...); one line on stderr;
* 3 (:data:`~dcc_fg.util.health.EXIT_UNHEALTHY`): the run finished but its result failed a health
  check (:class:`~dcc_fg.util.health.UnhealthyResultError`); every failed check on its own line with
  what to try; nothing written (``--accept-unhealthy`` writes it, marked ``healthy: false``);
* 130: interrupted (Ctrl-C); one line, nothing half-written (the outputs are written as one set).

Anything else is a bug and ends in a traceback, so it is never mistaken for a problem with the input.
"""

from __future__ import annotations

import argparse
import logging
import sys

import numpy as np
import yaml

from dcc_fg.commands import batch, calibrate, common, config, demo, evaluate, export, intrinsics, plan, simulate, vio
from dcc_fg.util.errors import NUMERICAL_ERRORS, EstimatorError
from dcc_fg.util.health import EXIT_UNHEALTHY, UnhealthyResultError
from dcc_fg.util.logs import configure_logging
from dcc_fg.util.provenance import package_version, set_command_line

log = logging.getLogger("dcc_fg.cli")

#: Exit codes (also in ``dcc-fg --help``).
EXIT_OK = 0
EXIT_FAILED = 2
EXIT_INTERRUPTED = 130

EPILOG = (
    "exit codes: 0 success; 2 bad input, unusable --out, file system error or a failed estimator (one line on "
    f"stderr); {EXIT_UNHEALTHY} the result failed its health checks (each named on stderr with what to try; nothing "
    f"written; --accept-unhealthy writes it marked healthy: false); {EXIT_INTERRUPTED} interrupted (Ctrl-C; nothing "
    "half-written). Every command writes its --out folder as one set: checked before any work, staged in a hidden "
    "folder and moved into place only on success; the previous run's outputs of the same command there are replaced, "
    "other files left alone."
)

GENERIC_HINT = (
    "check that the data cover the joints' range and that the initial values are plausible; rerun with -v for details"
)


def build_parser() -> argparse.ArgumentParser:
    """The ``dcc-fg`` parser with every subcommand."""
    p = argparse.ArgumentParser(
        prog="dcc-fg",
        description="Encoderless calibration of dynamic camera clusters (a static camera plus a camera on a "
        "gimbal without encoders) and gimbal-aware VIO, on GTSAM factor graphs.",
        epilog=EPILOG,
    )
    p.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")
    sub = p.add_subparsers(dest="command", required=True)
    parent = common.verbosity_parent()
    demo.add_parser(sub, parent)
    calibrate.add_parsers(sub, parent)
    intrinsics.add_parser(sub, parent)
    simulate.add_parser(sub, parent)
    vio.add_parser(sub, parent)
    evaluate.add_parser(sub, parent)
    config.add_parser(sub, parent)
    export.add_parser(sub, parent)
    batch.add_parser(sub, parent)
    plan.add_parser(sub, parent)
    return p


def command_name(args: argparse.Namespace) -> str:
    """``calibrate``, or ``simulate flight`` for a nested subcommand."""
    what = getattr(args, "what", None)
    return f"{args.command} {what}" if what else str(args.command)


def os_error_text(exc: OSError) -> str:
    """An OSError as one line naming the file: ``PATH: Permission denied``."""
    if exc.strerror and exc.filename:
        return f"{exc.filename}: {exc.strerror}" + (f" -> {exc.filename2}" if exc.filename2 else "")
    return " ".join(str(exc).split()) or type(exc).__name__


def report_failure(command: str, exc: BaseException) -> int:
    """One line on stderr for an expected failure (an unhealthy result: one line per failed check);
    the exit code (2, or EXIT_UNHEALTHY)."""
    if isinstance(exc, UnhealthyResultError):
        print(f"dcc-fg {command}: error: {exc.detail}", file=sys.stderr)
        return EXIT_UNHEALTHY
    if isinstance(exc, OSError) and not isinstance(exc, FileNotFoundError):
        text = os_error_text(exc)
    elif isinstance(exc, EstimatorError):
        text = str(exc)
    elif isinstance(exc, yaml.YAMLError):
        text = f"malformed YAML: {' '.join(str(exc).split())}"
    elif isinstance(exc, np.linalg.LinAlgError) or (isinstance(exc, RuntimeError) and not isinstance(exc, OSError)):
        detail = " ".join(str(exc).split()) or type(exc).__name__
        text = f"{command} failed in the estimator: {detail} (hint: {GENERIC_HINT})"
    else:
        text = str(exc)
    print(f"dcc-fg {command}: error: {text}", file=sys.stderr)
    log.debug("failure detail", exc_info=exc)
    return EXIT_FAILED


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    set_command_line(None if argv is None else ["dcc-fg", *argv])
    configure_logging(getattr(args, "verbose", 0), getattr(args, "quiet", False))
    try:
        return int(args.func(args))
    except (ValueError, OSError, yaml.YAMLError, EstimatorError, *NUMERICAL_ERRORS) as exc:
        return report_failure(command_name(args), exc)
    except KeyboardInterrupt:
        print(f"dcc-fg {command_name(args)}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
