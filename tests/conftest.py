"""Shared fixtures: the simulated demo problem and the location of the real data."""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path
from types import ModuleType

# One BLAS thread per pytest-xdist worker: CI runs one worker per core (-n auto), and OpenBLAS's own
# threads on top of those compete for the same cores. Set before numpy is first imported (below).
if "PYTEST_XDIST_WORKER" in os.environ:
    for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

import pytest  # noqa: E402

from dcc_fg.calibrate import CalibrationOptions, CalibrationResult, calibrate
from dcc_fg.sim.calibration_scene import SimulatedCalibration, simulate_calibration

SHARED_DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def load_benchmark(name: str) -> ModuleType:
    """The script ``benchmarks/<name>.py`` as a module (loaded once per process), so that a test runs
    a fixed subset of the study the script runs in full."""
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses resolve annotations through sys.modules
    spec.loader.exec_module(module)
    return module


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
