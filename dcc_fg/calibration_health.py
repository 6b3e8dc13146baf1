"""Health checks of a calibration / validation result (see :mod:`dcc_fg.util.health`).

Placeholder: filled in by the calibration-health work of issue 13.
"""

from __future__ import annotations

from dcc_fg.calibrate import CalibrationResult
from dcc_fg.data import CalibrationDataset
from dcc_fg.util.health import HealthReport


def calibration_health(result: CalibrationResult, data: CalibrationDataset) -> HealthReport:
    """Every health check of ``result`` (estimated from ``data``)."""
    return HealthReport("calibration")
