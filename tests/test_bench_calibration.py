"""Smoke test of benchmarks/bench_calibration.py on a small problem (12 snapshots)."""

from __future__ import annotations

import pytest
from conftest import load_benchmark


@pytest.mark.slow
def test_bench_calibration_small_problem_same_cost() -> None:
    bench = load_benchmark("bench_calibration")
    out = bench.run(seed=0, snapshots=12, verbose=False)
    # both solvers start from the values calibrate() hands to GTSAM
    assert out["initial_cost_shared"] == pytest.approx(out["calibrate_initial_cost"], rel=1e-9)
    assert out["gtsam_initial_cost"] == pytest.approx(out["calibrate_initial_cost"], rel=1e-12)
    # the reproduced GTSAM solve is calibrate()'s solve
    assert out["gtsam_final_cost"] == pytest.approx(out["calibrate_final_cost"], rel=1e-9)
    assert out["gtsam_final_cost_graph"] == pytest.approx(out["gtsam_final_cost"], rel=1e-9)
    # both solvers reach the same minimum of the shared cost
    assert out["scipy_final_cost"] == pytest.approx(out["gtsam_final_cost"], rel=1e-6)
    # the criterion: dcc-fg ends at the same or a lower cost (1e-12: summation round-off)
    assert out["gtsam_final_cost"] <= out["scipy_final_cost"] * (1 + 1e-12)
    assert out["gtsam_final_cost"] < out["initial_cost_shared"]
    assert out["gtsam_time_s"] > 0 and out["scipy_time_s"] > 0
