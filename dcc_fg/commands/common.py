"""What every ``dcc-fg`` command shares: verbosity flags, ``--config``, flags that override it.

Flags that set an option are declared with ``dest="section.key"`` and ``default=SUPPRESS``, so the
parsed namespace holds exactly the flags the user typed; :func:`effective_config` lays them over the
``--config`` file (or the defaults). Library code never sees an ``argparse.Namespace``: commands
turn it into options dataclasses here and pass those on.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path
from typing import Any, TypeVar

from dcc_fg.util.config import apply_overrides, load_yaml_config
from dcc_fg.util.health import HealthReport, UnhealthyResultError
from dcc_fg.viz.rerun_log import RerunOptions, require_rerun

T = TypeVar("T")

SUPPRESS = argparse.SUPPRESS

log = logging.getLogger("dcc_fg.commands")

#: How every result folder is written (the end of each ``--out`` help text).
OUT_FOLDER_HELP = (
    "Checked before any work: not a file, not an input or inside an input folder, not holding an input, not the "
    "result folder of another command. The outputs are written into a hidden staging folder and moved into place "
    "together only when the run succeeds (a failure or Ctrl-C leaves the folder as it was); the previous run's "
    "outputs of this command in that folder (listed in its .dcc_fg_manifest.json) are removed, other files are "
    "left alone"
)


def stderr_is_terminal() -> bool:
    """True when stderr is a terminal (progress bars go there only then)."""
    return sys.stderr.isatty()


def verbosity_parent() -> argparse.ArgumentParser:
    """``-v/--verbose`` and ``-q/--quiet``, added to every subcommand."""
    p = argparse.ArgumentParser(add_help=False)
    g = p.add_argument_group("output verbosity")
    g.add_argument("-v", "--verbose", action="count", default=0, help="more log messages (debug level); repeatable")
    g.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        help="only warnings and errors: no progress bar, no info messages, no summary table",
    )
    return p


def add_command(
    sub: Any, name: str, parent: argparse.ArgumentParser | None, summary: str, description: str, func: Any
) -> argparse.ArgumentParser:
    """A subcommand ``name`` with the verbosity flags of ``parent`` that runs ``func(args)``."""
    p = sub.add_parser(name, parents=[parent] if parent else [], help=summary, description=description)
    p.set_defaults(func=func)
    return p


def add_option(p: argparse.ArgumentParser, flag: str, dest: str, help: str, **kwargs: Any) -> None:
    """A flag that sets the configuration option ``dest`` (``section.key``) only when given."""
    p.add_argument(flag, dest=dest, default=SUPPRESS, help=help, **kwargs)


def add_config_flag(p: argparse.ArgumentParser, command: str) -> None:
    """``--config FILE``: options from a YAML file (``dcc-fg config --print COMMAND`` writes one)."""
    p.add_argument(
        "--config",
        metavar="FILE",
        help=f"options from a YAML file (write the defaults with 'dcc-fg config --print {command}'; a summary.json "
        "of an earlier run also works); flags given on the command line override it",
    )


def option_flags(args: argparse.Namespace) -> dict[str, Any]:
    """The ``section.key`` options the user gave on the command line."""
    return {k: v for k, v in vars(args).items() if "." in k}


def effective_config(args: argparse.Namespace, cls: type[T], command: str) -> T:
    """Defaults, then the ``--config`` file, then the command-line flags."""
    path = getattr(args, "config", None)
    config = load_yaml_config(path, cls, command) if path else cls()
    return apply_overrides(config, option_flags(args))


def progress_wanted(args: argparse.Namespace) -> bool:
    """A progress bar only on a terminal and without ``--quiet``."""
    return not getattr(args, "quiet", False) and stderr_is_terminal()


def judge_health(report: HealthReport, accept: bool) -> dict[str, Any]:
    """The ``health`` block of ``summary.json`` for ``report``.

    An unhealthy report raises :class:`~dcc_fg.util.health.UnhealthyResultError` (nothing is written;
    exit code 3) unless ``accept`` (``--accept-unhealthy``); then every failed check is logged as a
    warning and the block says ``healthy: false`` with the reasons.
    """
    for check in report.warnings:
        hint = f" (try: {check.hint})" if check.hint else ""
        log.warning("%s health warning: %s: %s%s", report.subject, check.name, check.message, hint)
    if not report.healthy:
        if not accept:
            raise UnhealthyResultError(report)
        for check in report.failures:
            hint = f" (try: {check.hint})" if check.hint else ""
            log.warning("unhealthy %s accepted (--accept-unhealthy): %s: %s%s", report.subject, check.name,
                        check.message, hint)  # fmt: skip
    return report.to_dict()


def float_pair(text: str) -> tuple[float, float]:
    """argparse ``type`` for ``A,B``: two finite numbers (the checks of the option itself follow)."""
    parts = text.split(",")
    try:
        pair = tuple(float(x) for x in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expects two numbers A,B, got {text!r}") from None
    if len(pair) != 2 or not all(math.isfinite(x) for x in pair):
        raise argparse.ArgumentTypeError(f"expects two finite numbers A,B, got {text!r}")
    return pair[0], pair[1]


def add_rerun_flags(p: argparse.ArgumentParser, what: str) -> None:
    """``--rerun FILE.rrd`` and ``--rerun-spawn``: an interactive Rerun recording of the run (``what`` it
    shows); needs the optional extra dcc-fg[viz]. Not options of the run: they are not recorded in
    summary.json and do not change the results."""
    g = p.add_argument_group("interactive visualization (needs pip install dcc-fg[viz])")
    g.add_argument("--rerun", metavar="FILE.rrd", help=f"write a Rerun recording of the run: {what}. Open it with "
                   "'rerun FILE.rrd'. Written when the estimate exists, also when its health checks fail (exit 3), "
                   "so a bad result can be inspected")  # fmt: skip
    g.add_argument("--rerun-spawn", action="store_true", help="start the Rerun viewer and stream the recording to it")


def rerun_options(args: argparse.Namespace) -> RerunOptions:
    """The ``--rerun`` / ``--rerun-spawn`` request, checked before any work (rerun-sdk installed, a ``.rrd``
    file name): :class:`~dcc_fg.viz.rerun_log.RerunUnavailableError` names what to install."""
    path = getattr(args, "rerun", None)
    options = RerunOptions(Path(path) if path else None, bool(getattr(args, "rerun_spawn", False)))
    require_rerun(options)
    return options
