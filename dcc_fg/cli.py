"""Command-line interface: ``dcc-fg demo | calibrate | validate | intrinsics | simulate | vio | evaluate | config``.

This module only assembles the subcommands of :mod:`dcc_fg.commands`, sets up logging
(``-v`` / ``-q``) and turns failures into one-line messages with exit code 2:

* bad input (``ValueError``, ``FileNotFoundError``, malformed YAML, an invalid ``--config``);
* an estimator that failed numerically (:class:`~dcc_fg.util.errors.EstimatorError`, or a gtsam
  ``RuntimeError`` / numpy ``LinAlgError`` that no stage wrapped): the stage and a hint are named.

Anything else is a bug and ends in a traceback, so it is never mistaken for a problem with the input.
"""

from __future__ import annotations

import argparse
import logging
import sys

import numpy as np
import yaml

from dcc_fg.commands import calibrate, common, config, demo, evaluate, intrinsics, simulate, vio
from dcc_fg.util.errors import NUMERICAL_ERRORS, EstimatorError
from dcc_fg.util.logs import configure_logging
from dcc_fg.util.provenance import package_version, set_command_line

log = logging.getLogger("dcc_fg.cli")

GENERIC_HINT = (
    "check that the data cover the joints' range and that the initial values are plausible; rerun with -v for details"
)


def build_parser() -> argparse.ArgumentParser:
    """The ``dcc-fg`` parser with every subcommand."""
    p = argparse.ArgumentParser(
        prog="dcc-fg",
        description="Encoderless calibration of dynamic camera clusters (a static camera plus a camera on a "
        "gimbal without encoders) and gimbal-aware VIO, on GTSAM factor graphs.",
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
    return p


def report_failure(command: str, exc: BaseException) -> int:
    """One line on stderr for an expected failure; the exit code (2)."""
    if isinstance(exc, EstimatorError):
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
    return 2


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    set_command_line(None if argv is None else ["dcc-fg", *argv])
    configure_logging(getattr(args, "verbose", 0), getattr(args, "quiet", False))
    try:
        return int(args.func(args))
    except (ValueError, FileNotFoundError, yaml.YAMLError, EstimatorError, *NUMERICAL_ERRORS) as exc:
        return report_failure(args.command, exc)


if __name__ == "__main__":
    sys.exit(main())
