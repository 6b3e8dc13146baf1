"""The options of ``dcc-fg calibrate --incremental`` (:mod:`dcc_fg.commands.calibrate_incremental`), a section
of :class:`~dcc_fg.commands.calibrate.CalibrateConfig`."""

from __future__ import annotations

import math
from dataclasses import dataclass

from dcc_fg.planning.range_spec import parse_tolerance


@dataclass(frozen=True)
class IncrementalSettings:
    """The ``--incremental`` options (``incremental:`` section of the ``--config`` YAML): ``poll_seconds``
    between polls of a folder (s, > 0), ``idle_timeout`` without a new snapshot before the run stops
    (s, >= 0), ``tolerance`` of the worst-case ``T_ds`` 1-sigma (``ROT,TRANS`` text as ``dcc-fg plan
    --tolerance``), ``range`` the operating range (``LO:HI,...`` degrees per joint; None: the data's
    range plus a margin), ``background``: the global solves run in a background process while the updates
    go on (``--blocking-solves``: inside the updates; :mod:`dcc_fg.incremental`)."""

    poll_seconds: float = 1.0
    idle_timeout: float = 30.0
    tolerance: str = "1mrad,1mm"
    range: str | None = None
    background: bool = True

    def __post_init__(self) -> None:
        if not (math.isfinite(self.poll_seconds) and self.poll_seconds > 0):
            raise ValueError(f"--poll-seconds must be a positive number of seconds, got {self.poll_seconds}")
        if not (math.isfinite(self.idle_timeout) and self.idle_timeout >= 0):
            raise ValueError(f"--idle-timeout must be a number of seconds >= 0, got {self.idle_timeout}")
        parse_tolerance(self.tolerance)  # ValueError naming the problem
        if not isinstance(self.background, bool):
            raise ValueError(f"incremental.background must be true or false, got {self.background!r}")
