"""What every ``dcc-fg`` command shares: verbosity flags, ``--config``, flags that override it.

Flags that set an option are declared with ``dest="section.key"`` and ``default=SUPPRESS``, so the
parsed namespace holds exactly the flags the user typed; :func:`effective_config` lays them over the
``--config`` file (or the defaults). Library code never sees an ``argparse.Namespace``: commands
turn it into options dataclasses here and pass those on.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any, TypeVar

from dcc_fg.util.config import apply_overrides, load_yaml_config

T = TypeVar("T")

SUPPRESS = argparse.SUPPRESS


def stderr_is_terminal() -> bool:
    """True when stderr is a terminal (progress bars go there only then)."""
    return sys.stderr.isatty()


def verbosity_parent() -> argparse.ArgumentParser:
    """``-v/--verbose`` and ``-q/--quiet``, added to every subcommand."""
    p = argparse.ArgumentParser(add_help=False)
    g = p.add_argument_group("output verbosity")
    g.add_argument(
        "-v", "--verbose", action="count", default=0, help="more log messages (debug level); repeatable"
    )
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
