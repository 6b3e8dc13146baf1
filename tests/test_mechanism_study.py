"""The issue-14 study of random mechanisms (dcc_fg.studies.mechanism_study): aggregation on synthetic
records (fast) and one small rendered member per L end to end (slow)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from conftest import load_benchmark
from scipy.stats import chi2

import dcc_fg.studies.mechanism_study as ms
from dcc_fg.global_fit import FURTHER_STEPS
from dcc_fg.projection import MAX_STEPS
from dcc_fg.studies.mechanism_study import (
    MechanismRecord,
    RunOutcome,
    nees_interval,
    pooled_ratio,
    study_member,
    summarize,
    truth_start,
)


def _record(seed: int, L: int, *, success: bool = True, nees: float = 6.0, ratio: float = 1.0) -> MechanismRecord:
    r = MechanismRecord(seed, L, 40, n_snapshots=40)
    r.auto = RunOutcome(final_error=10.0, time_s=1.0, healthy=True)
    r.truth_start = RunOutcome(final_error=10.0, time_s=1.0)
    r.success, r.observable = success, True
    r.rotation_rms, r.crb_rotation_rms = ratio * 1e-4, 1e-4
    r.translation_rms, r.crb_translation_rms = ratio * 2e-4, 2e-4
    r.nees_mean = nees
    r.render_time_s = r.detect_time_s = 1.0
    if not success:
        r.failure = "local minimum"
    return r


def test_nees_interval_is_the_chi_square_interval_of_a_mean() -> None:
    lo, hi = nees_interval(50)
    assert lo == pytest.approx(chi2.ppf(0.025, 300) / 50)
    assert hi == pytest.approx(chi2.ppf(0.975, 300) / 50)
    assert lo < 6.0 < hi
    # Monte Carlo: the mean of 50 chi2(6) draws lands inside about 95 % of the time
    rng = np.random.default_rng(0)
    means = rng.chisquare(6, size=(4000, 50)).mean(axis=1)
    coverage = np.mean((means >= lo) & (means <= hi))
    assert abs(coverage - 0.95) < 4 * math.sqrt(0.95 * 0.05 / 4000)
    assert all(math.isnan(x) for x in nees_interval(0))


def test_pooled_ratio_ignores_missing_bounds() -> None:
    assert pooled_ratio([3.0, 4.0, 1.0], [3.0, 4.0, math.nan]) == pytest.approx(1.0)
    assert pooled_ratio([2.0], [1.0]) == pytest.approx(2.0)
    assert math.isnan(pooled_ratio([1.0], [0.0]))


def test_summary_counts_successes_and_judges_each_criterion() -> None:
    recs = [_record(s, 2) for s in range(49)] + [_record(49, 2, success=False), _record(0, 1)]
    s = summarize(recs, 2)
    assert (s.n, s.successes, s.n_observable) == (50, 49, 49)
    assert s.success_ok and s.crb_ok and s.nees_ok and s.passed
    assert s.failures == ["seed 49 (L=2): local minimum"]
    assert s.nees_interval == nees_interval(49)

    two_fail = summarize(recs[:48] + [_record(48, 2, success=False), recs[49]], 2)
    assert two_fail.successes == 48 and not two_fail.success_ok and not two_fail.passed

    inaccurate = summarize([_record(s, 2, ratio=1.6) for s in range(10)], 2)
    assert inaccurate.rotation_ratio_pooled == pytest.approx(1.6) and not inaccurate.crb_ok

    overconfident = summarize([_record(s, 2, nees=9.0) for s in range(50)], 2)
    assert overconfident.nees_mean == pytest.approx(9.0) and not overconfident.nees_ok
    # with 5 members the interval is wide: a mean NEES of 9 is still consistent
    assert summarize([_record(s, 2, nees=9.0) for s in range(5)], 2).nees_ok


def test_record_round_trips_through_json_dict() -> None:
    r = _record(3, 3)
    r.held_by_prior = ["alpha_2"]
    d = r.to_dict()
    assert d["rotation_ratio"] == pytest.approx(1.0) and d["sigma_detector_px"] is None
    back = MechanismRecord.from_dict(d)
    assert back.auto == r.auto and back.held_by_prior == ["alpha_2"] and math.isnan(back.sigma_detector_px)


@pytest.mark.slow
@pytest.mark.parametrize("n_joints", [1, 2])
def test_small_member_end_to_end(n_joints: int, tmp_path: Path) -> None:
    """Render, detect and calibrate a 12-snapshot member; the record is complete and the automatic
    start reaches the truth start's minimum."""
    rec = study_member(1, n_joints, 12, tmp_path / "data")
    assert rec.failure == "", rec.failure
    assert rec.success and rec.reference == "best of both"
    assert 8 <= rec.n_snapshots <= 12
    assert rec.auto.healthy is True and rec.auto.error == "" and rec.truth_start.error == ""
    assert rec.auto.final_error <= rec.truth_start.final_error * (1 + 1e-6) + 1e-9
    for name in (
        "render_time_s",
        "detect_time_s",
        "rotation_rms",
        "translation_rms",
        "sigma_detector_px",
        "sigma_posterior_px",
        "crb_rotation_rms",
        "crb_translation_rms",
        "nees_mean",
    ):
        value = getattr(rec, name)
        assert np.isfinite(value) and value > 0, name
    # detected corners of rendered images: well below a pixel, above nothing
    assert 1e-3 < rec.sigma_detector_px < 0.5
    # one realization of a ~6-dof quantity: its RMS over the bound stays within a loose factor
    assert 0.1 < rec.rotation_ratio < 4.0 and 0.1 < rec.translation_ratio < 4.0
    assert rec.nees_mean < chi2.ppf(0.999, 6)
    d = rec.to_dict()
    assert d["seed"] == 1 and d["n_joints"] == n_joints and d["description"]


def test_bench_table_marks_each_L() -> None:
    bench = load_benchmark("bench_random_mechanisms")
    ok = [_record(s, 1) for s in range(5)]
    failing = [_record(s, 2) for s in range(3)] + [_record(3, 2, success=False)]
    text = bench.table([summarize(ok, 1), summarize(failing, 2)])
    lines = text.splitlines()
    assert len(lines) == 3 and lines[1].rstrip().endswith("PASS") and lines[2].rstrip().endswith("FAIL")
    assert "3/4" in lines[2]
    assert "local minimum" in bench.member_line(failing[-1])


@pytest.mark.parametrize("held, continued", [(True, "lower"), (True, None), (False, "lower"), (True, "capped")])
def test_the_truth_start_is_continued_to_the_bottom_of_its_valley(monkeypatch, held, continued) -> None:  # noqa: ANN001
    """The reference solution is the truth start's calibration, continued with the projected solve when it
    holds directions (as the search does with its lowest solutions), and continued again by FURTHER_STEPS
    when that continuation stopped on its step cap (as the search does with its answer); kept as is when
    the continuation does not lower the cost (continue_projected returns None) or nothing is held."""

    class Res:
        def __init__(self, name: str, is_held: bool, capped: bool = False) -> None:
            self.name, self.extra = name, ({"held_by_prior": [{"parameters": ["dh1.alpha"]}]} if is_held else {})
            self.extra["held_projection"] = {"kept": True, "converged": not capped}

    calls = []

    def fake_continue(data, res, max_steps=MAX_STEPS):  # noqa: ANN001, ANN202
        calls.append((res.name, max_steps))
        if continued is None:
            return None
        if res.name == "joint solve":
            return Res("continued", held, capped=continued == "capped")
        return Res("continued on", held)

    monkeypatch.setattr(ms, "with_joints", lambda data, thetas: data)
    monkeypatch.setattr(ms, "calibrate", lambda data, initial, opt: Res("joint solve", held))
    monkeypatch.setattr(ms, "continue_projected", fake_continue)
    out = truth_start(object(), object(), np.zeros((1, 3)), ms.CalibrationOptions())
    expected = {"lower": [("joint solve", MAX_STEPS)], None: [("joint solve", MAX_STEPS)],
                "capped": [("joint solve", MAX_STEPS), ("continued", FURTHER_STEPS)]}[continued]  # fmt: skip
    assert calls == (expected if held else [])
    names = {"lower": "continued", None: "joint solve", "capped": "continued on"}
    assert out.name == (names[continued] if held else "joint solve")
