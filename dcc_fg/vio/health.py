"""Health checks of a VIO result (see :mod:`dcc_fg.util.health`).

Placeholder: filled in by the VIO-health work of issue 13.
"""

from __future__ import annotations

from dcc_fg.data.vio import ImuConfig
from dcc_fg.util.health import HealthReport
from dcc_fg.vio.backend.options import VioOptions, VioResult


def vio_health(result: VioResult, imu: ImuConfig, options: VioOptions) -> HealthReport:
    """Every health check of the trajectory ``result``."""
    return HealthReport("trajectory")
