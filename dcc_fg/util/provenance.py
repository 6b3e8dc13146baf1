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
        "command_line": list(sys.argv if argv is None else argv),
        "inputs": {k: str(Path(v).resolve()) for k, v in inputs.items() if v is not None},
        "options": to_plain(options),
        "environment": {
            "python": platform.python_version(),
            "gtsam": package_version("gtsam"),
            "numpy": package_version("numpy"),
            "opencv": package_version("opencv-python-headless"),
        },
    }
