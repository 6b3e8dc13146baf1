"""What a run records about itself so it can be reproduced: version, command line, inputs, options."""

from __future__ import annotations

import platform
import sys
from collections.abc import Mapping, Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

from dcc_fg.util.config import to_plain

PACKAGE = "dcc-fg"

#: The command line of the running ``dcc-fg`` command (set by :func:`dcc_fg.cli.main`, which may be
#: called with an explicit argv from Python); None means ``sys.argv``.
_command_line: list[str] | None = None


def set_command_line(argv: Sequence[str] | None) -> None:
    """Record the command line that :func:`run_record` reports (None: ``sys.argv``)."""
    global _command_line
    _command_line = None if argv is None else list(argv)


def package_version(name: str = PACKAGE) -> str:
    """Installed version of a distribution (``unknown`` when it is not installed)."""
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "unknown"


def run_record(
    command: str,
    inputs: Mapping[str, str | Path | None],
    options: Any,
    argv: Sequence[str] | None = None,
) -> dict[str, Any]:
    """The provenance block of a ``summary.json``.

    ``inputs`` maps roles (``data``, ``camchain``, ...) to paths (stored absolute; absent ones
    dropped); ``options`` is the effective configuration dataclass; ``argv`` the command line
    (default ``sys.argv``).
    """
    return {
        "dcc_fg_version": package_version(),
        "command": command,
        "command_line": list(argv if argv is not None else _command_line if _command_line is not None else sys.argv),
        "inputs": {k: str(Path(v).resolve()) for k, v in inputs.items() if v is not None},
        "options": to_plain(options),
        "environment": {
            "python": platform.python_version(),
            "gtsam": package_version("gtsam"),
            "numpy": package_version("numpy"),
            "opencv": package_version("opencv-python-headless"),
        },
    }
