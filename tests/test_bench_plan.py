"""The small fixed subset of benchmarks/bench_plan.py that CI runs: one random-family member (seed 19,
L = 2, rendered images), the three strategies up to 10 added snapshots, and benchmarks/bench_plan_cost.py
on one L = 1 member. The full study (20 members) is ``python benchmarks/bench_plan.py --n 20 --workers 2``."""

from __future__ import annotations

import argparse
import math

import pytest
from conftest import load_benchmark
from scipy.stats import chi2


@pytest.mark.slow
def test_plan_member_19_needs_fewer_snapshots_and_predicts_its_error() -> None:
    """Member 19 (in the full study: plan 2, random 8, grid 9 snapshots): the plan reaches the reference
    tolerance with at most half the snapshots of random angles and of the grid, and its final
    calibration's error at a held-out angle is consistent with the prediction (NEES inside the 99.9 %
    interval of chi2(6 - L))."""
    bench = load_benchmark("bench_plan")
    args = argparse.Namespace(step=2, max_added=10, relative=1.0, tolerance=None)
    r = bench.run_member(19, args)
    assert not r.failure and r.joints == 2
    assert r.needed["plan"] < math.inf
    for other in ("random", "grid"):
        assert 2 * r.needed["plan"] <= r.needed[other], r.needed
    lo, hi = chi2.ppf([0.0005, 0.9995], r.nees_dof)
    assert lo <= r.nees <= hi
    assert 0.2 < r.true_over_predicted < 3.0


@pytest.mark.slow
def test_plan_cost_benchmark_runs(capsys: pytest.CaptureFixture[str]) -> None:
    load_benchmark("bench_plan")  # bench_plan_cost imports it by name
    bench = load_benchmark("bench_plan_cost")
    assert bench.main(["--seeds", "8", "--k", "2"]) == 0
    out = capsys.readouterr().out
    assert "member 8 L=1: K=2 plan" in out and "ratio" in out
