"""Shared fixtures: the simulated demo problem and the location of the real data."""

from __future__ import annotations

from pathlib import Path

import pytest

from dcc_fg.calibrate import CalibrationOptions, CalibrationResult, calibrate
from dcc_fg.sim.calibration_scene import SimulatedCalibration, simulate_calibration

SHARED_DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def shared_data(sub: str) -> Path:
    """Path inside ../shared/data, or skip the test with the reason."""
    path = SHARED_DATA / sub
    if not path.exists():
        pytest.skip(f"real data {path} is not available (../shared/data is absent on a fresh clone)")
    return path


@pytest.fixture(scope="session")
def demo_sim() -> SimulatedCalibration:
    return simulate_calibration(0)


@pytest.fixture(scope="session")
def demo_result(demo_sim: SimulatedCalibration) -> CalibrationResult:
    return calibrate(demo_sim.calibration_set, demo_sim.initial, CalibrationOptions())
