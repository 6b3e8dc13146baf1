"""One logging set-up for every command: ``-v`` / ``-q`` and a readable format on stderr.

Levels: default INFO (pairing summaries, joint-angle fits, what was written), ``-v`` DEBUG,
``-q`` WARNING (warnings are always shown). ``warnings.warn`` messages go through the same handler.
"""

from __future__ import annotations

import logging
import sys

FORMAT = "%(asctime)s %(levelname)-7s %(name)s: %(message)s"
DATE_FORMAT = "%H:%M:%S"
_HANDLER_NAME = "dcc-fg"


def level_for(verbose: int = 0, quiet: bool = False) -> int:
    """The logging level of ``-v`` (repeatable) and ``-q``."""
    if quiet:
        return logging.WARNING
    return logging.DEBUG if verbose > 0 else logging.INFO


def configure_logging(verbose: int = 0, quiet: bool = False) -> int:
    """Install (or re-level) the stderr handler of the ``dcc_fg`` and ``factors`` loggers.

    Idempotent: calling it again (tests run many commands in one process) replaces the level and
    keeps a single handler. Returns the level set.
    """
    level = level_for(verbose, quiet)
    for name in ("dcc_fg", "factors", "py.warnings"):
        logger = logging.getLogger(name)
        handler = next((h for h in logger.handlers if h.get_name() == _HANDLER_NAME), None)
        if handler is None:
            handler = logging.StreamHandler(sys.stderr)
            handler.set_name(_HANDLER_NAME)
            handler.setFormatter(logging.Formatter(FORMAT, DATE_FORMAT))
            logger.addHandler(handler)
        handler.stream = sys.stderr  # follow a replaced stderr (pytest's capsys)
        handler.setLevel(level)
        logger.setLevel(level)
        logger.propagate = False
    logging.captureWarnings(True)
    return level
