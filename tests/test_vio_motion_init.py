"""Starting the VIO in motion (:mod:`dcc_fg.vio.backend.motion_init`): the rest test, the visual-inertial
alignment against the simulator's truth over a family of flights and start times, and a run started in
flight against the same run started from the true state."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from dcc_fg.data.vio import ImuConfig, TrackFrame
from dcc_fg.sim.trajectory import (
    FlightConfig,
    FlightTruth,
    World,
    default_static_mount,
    flight_calibration,
    simulate_flight,
    simulate_tracks,
)
from dcc_fg.vio.backend import InitialState, VioOptions, run_vio
from dcc_fg.vio.backend.motion_init import StartSelector, align_in_motion, at_rest
from dcc_fg.vio.evaluate import GroundTruth, evaluate_trajectory

NS = 1_000_000_000
SIGMA = 0.5 / 460.0  # the tracks' pixel noise, normalized


def _flight(seed: int) -> tuple[FlightTruth, list[TrackFrame], ImuConfig]:
    imu_cfg = ImuConfig(T_sI=default_static_mount())
    truth = simulate_flight(FlightConfig.short(14.0), imu_cfg, seed=seed)
    pts = World.around(truth.config).sample_points(0.5, np.random.default_rng(100 + seed))
    frames = simulate_tracks(truth, pts, flight_calibration(), imu_cfg.T_sI, 0.5, seed=seed + 1)
    return truth, frames, imu_cfg


@pytest.fixture(scope="module")
def flights() -> dict[int, tuple[FlightTruth, list[TrackFrame], ImuConfig]]:
    return {seed: _flight(seed) for seed in (0, 1, 2)}


def _index(truth: FlightTruth, t_ns: int) -> int:
    return int(np.atleast_1d(truth.index_of(np.array([t_ns])))[0])


def test_alignment_against_the_truth_over_flights_and_start_times(flights: dict) -> None:
    """3 flights x 8 start times in flight (1 s windows): gravity direction and velocity of the first
    keyframe against the truth, in units of the alignment's own 1-sigma. Accepted alignments must be
    within 3 sigma (plus the accelerometer-bias floor of the IMU model: 0.1 m/s^2 / g = 0.6 deg) and at
    least 80 % of the windows must be accepted."""
    accepted, total, worst = 0, 0, []
    for truth, frames, imu_cfg in flights.values():
        for start in np.arange(2.5, 11.0, 1.1):
            t0 = int(truth.t_ns[0]) + int(start * NS)
            window = [f for f in frames if t0 <= f.timestamp_ns <= t0 + NS]
            total += 1
            al, why = align_in_motion(window, truth.imu, imu_cfg, SIGMA)
            if al is None:
                continue
            accepted += 1
            i = _index(truth, window[0].timestamp_ns)
            R0 = truth.T_WI[i][:3, :3]
            g_true = R0.T @ np.array([0.0, 0.0, -imu_cfg.gravity])
            cosang = al.gravity_b0 @ g_true / (np.linalg.norm(al.gravity_b0) * imu_cfg.gravity)
            g_err = float(np.arccos(np.clip(cosang, -1.0, 1.0)))
            v_err = float(np.linalg.norm(al.v0_b0 - R0.T @ truth.v_W[i]))
            worst.append((g_err / (3 * al.gravity_sigma + np.radians(0.6)), v_err / (3 * al.velocity_sigma + 0.06)))
            assert al.residual_sigmas < 2.0  # |error| RMS of a 2D Gaussian is sqrt(2) sigma
    g_ratio, v_ratio = np.max(worst, axis=0)
    print(
        f"\nmotion alignment: {accepted}/{total} accepted; worst error / bound: gravity {g_ratio:.2f}, "
        f"velocity {v_ratio:.2f}"
    )
    assert accepted >= 0.8 * total
    assert g_ratio <= 1.0 and v_ratio <= 1.0


def test_rest_test_needs_the_imu_and_the_tracks_at_rest(flights: dict) -> None:
    truth, frames, imu_cfg = flights[0]
    t0 = int(truth.t_ns[0])
    hover = [f for f in frames if f.timestamp_ns <= t0 + NS // 2]  # the flight hovers for 1 s
    rest, why = at_rest(hover, truth.imu, imu_cfg, 0.5)
    assert rest, why
    moving = [f for f in frames if t0 + 5 * NS <= f.timestamp_ns <= t0 + 5 * NS + NS // 2]
    rest, why = at_rest(moving, truth.imu, imu_cfg, 0.5)
    assert not rest and "IMU" in why
    # an IMU at rest but tracks that move (a body at constant velocity looks like this): not at rest
    shifted = [dataclasses.replace(f, timestamp_ns=h.timestamp_ns) for f, h in zip(moving, hover, strict=False)]
    rest, why = at_rest(shifted, truth.imu, imu_cfg, 0.5)
    assert not rest and "static tracks move" in why


def test_start_selector_refuses_clearly_when_nothing_aligns(flights: dict) -> None:
    truth, frames, imu_cfg = flights[0]
    t0 = int(truth.t_ns[0]) + 5 * NS
    blind = [dataclasses.replace(f, static_ids=f.static_ids[:5], static_xy=f.static_xy[:5]) for f in frames
             if f.timestamp_ns >= t0]  # fmt: skip
    sel = StartSelector(truth.imu, imu_cfg, VioOptions(mode="mono", sigma=SIGMA, motion_init_max_window=1.5))
    with pytest.raises(ValueError, match=r"could not start the VIO: not at rest .* alignment over the first"):
        for f in blind:
            sel.push(f)


@pytest.mark.slow  # two 10 s tracks-level runs
def test_a_run_started_in_flight_tracks_the_run_started_from_the_truth(flights: dict) -> None:
    truth, frames, imu_cfg = flights[1]
    t0 = int(truth.t_ns[0]) + 4 * NS
    late = [f for f in frames if f.timestamp_ns >= t0]
    i = _index(truth, late[0].timestamp_ns)
    cal = flight_calibration()
    opts = VioOptions(mode="dcc", sigma=SIGMA, theta_initial=tuple(truth.theta[i] + 0.03))
    true_start = InitialState(
        late[0].timestamp_ns, truth.T_WI[i], truth.v_W[i], truth.acc_bias[i], truth.gyro_bias[i], truth.theta[i] + 0.03
    )
    res = run_vio(late, truth.imu, imu_cfg, cal, opts)
    ref = run_vio(late, truth.imu, imu_cfg, cal, opts, true_start)
    assert res.stats["start"]["how"] == "motion" and "aligned" in res.stats["start"]["detail"]
    gt = GroundTruth(truth.t_ns, truth.T_WI, truth.t_ns, truth.theta)
    ape = evaluate_trajectory(res.timestamps_ns, res.T_WI, gt, "se3")["ape_rmse_m"]
    ape_ref = evaluate_trajectory(ref.timestamps_ns, ref.T_WI, gt, "se3")["ape_rmse_m"]
    print(f"\nstarted in flight: APE {ape:.4f} m vs {ape_ref:.4f} m from the true state ({ape / ape_ref:.2f}x)")
    assert ape <= 2.0 * ape_ref
    # the standstill start is unchanged: the hover at the beginning is detected
    whole = run_vio(frames, truth.imu, imu_cfg, cal, dataclasses.replace(opts, theta_initial=tuple(truth.theta[0])))
    assert whole.stats["start"]["how"] == "standstill"
