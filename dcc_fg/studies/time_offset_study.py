"""Tracks-level study of the VIO on unsynchronized cameras with time offsets (no rendering).

One simulated flight (:mod:`dcc_fg.sim.trajectory`, a 16 m x 8 m loop) is observed with the camera
timing of :class:`~dcc_fg.sim.timing.CameraTiming` (:func:`~dcc_fg.sim.timed_tracks.simulate_timed_tracks`:
every image projected at its true exposure time, stamped ``exposure - t_offset``) and run through the
``dcc`` smoother from the true state at the first frame (joint angles perturbed by 0.03 rad), with the
offsets estimated from 0 or held at 0. :func:`timing_family` draws the randomized family of timings
(rates, phase, offsets, stamp jitter) that ``benchmarks/bench_time_offsets.py`` and the tests sample.

Metrics: SE(3)-aligned normalized translation RMSE (%), per-joint RMSE (rad), the offsets' estimates and
1-sigma (s) against the truth. Times in ns / s, angles in rad.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from dcc_fg.data.vio import ImuConfig
from dcc_fg.sim.timed_tracks import simulate_timed_tracks
from dcc_fg.sim.timing import CameraTiming
from dcc_fg.sim.trajectory import (
    FlightConfig,
    FlightTruth,
    World,
    default_static_mount,
    flight_calibration,
    simulate_flight,
    truth_at,
)
from dcc_fg.vio.backend import InitialState, VioOptions, run_vio
from dcc_fg.vio.evaluate import GroundTruth, evaluate_trajectory, joint_rmse

#: The issue's rig: static camera 20 Hz, gimbal camera 30 Hz, t_s = 5 ms, t_d = 15 ms.
ISSUE_TIMING = CameraTiming(rates=(20.0, 30.0), phase=0.0123, time_offsets=(0.005, 0.015))
#: Rates (Hz) the family draws from (common machine-vision and USB camera rates).
FAMILY_RATES = (15.0, 20.0, 25.0, 30.0)


@dataclass(frozen=True)
class Flight:
    """A simulated flight, its landmarks, IMU configuration and ground truth."""

    truth: FlightTruth
    landmarks_W: np.ndarray
    imu: ImuConfig
    gt: GroundTruth


def make_flight(duration: float = 14.0, seed: int = 0, density: float = 0.5) -> Flight:
    """One short loop of ``duration`` s (IMU noise and landmarks from ``seed``)."""
    imu = ImuConfig(T_sI=default_static_mount())
    truth = simulate_flight(FlightConfig.short(duration), imu, seed=seed)
    pts = World.around(truth.config).sample_points(density, np.random.default_rng(seed + 100))
    return Flight(truth, pts, imu, GroundTruth(truth.t_ns, truth.T_WI, truth.t_ns, truth.theta))


def timing_family(seed: int) -> CameraTiming:
    """A random unsynchronized rig: each camera's rate from :data:`FAMILY_RATES`, a uniform phase,
    offsets uniform in +-0.4 of the camera's frame period (at most +-25 ms), stamp jitter 0-0.5 ms."""
    rng = np.random.default_rng([seed, 15])
    rates = (float(rng.choice(FAMILY_RATES)), float(rng.choice(FAMILY_RATES)))
    offsets = tuple(float(rng.uniform(-1, 1) * min(0.4 / r, 0.025)) for r in rates)
    return CameraTiming(rates, float(rng.uniform(0.0, 1.0 / rates[1])), (offsets[0], offsets[1]),
                        float(rng.uniform(0.0, 5e-4)))  # fmt: skip


def run_timing(
    flight: Flight,
    timing: CameraTiming,
    estimate: bool = True,
    pixel_sigma: float = 0.5,
    seed: int = 1,
    options: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Simulate the tracks of ``timing``, run dcc (offsets estimated from 0, or held at 0) and score it;
    ``options`` overrides :class:`~dcc_fg.vio.backend.VioOptions` fields."""
    cal = flight_calibration()
    frames = simulate_timed_tracks(flight.truth, flight.landmarks_W, cal, flight.imu.T_sI, timing, pixel_sigma, seed)
    tr = flight.truth
    t0 = frames[0].timestamp_ns
    T0, theta0 = truth_at(tr, np.array([t0]))
    i0 = min(int(np.searchsorted(tr.t_ns, t0)), tr.t_ns.size - 1)
    initial = InitialState(t0, T0[0], tr.v_W[i0], tr.acc_bias[i0], tr.gyro_bias[i0], theta0[0] + 0.03)
    focal = float(cal.static_camera.intrinsics[0]) if cal.static_camera is not None else 460.0
    opts = VioOptions(mode="dcc", sigma=pixel_sigma / focal, estimate_time_offsets=estimate, **(options or {}))
    res = run_vio(frames, tr.imu, flight.imu, cal, opts, initial)
    ev = evaluate_trajectory(res.timestamps_ns, res.T_WI, flight.gt, "se3")
    to = res.stats["time_offsets"]
    truth_offsets = timing.time_offsets
    out: dict[str, Any] = {
        "timing": timing.to_dict(),
        "estimate_offsets": estimate,
        "normalized_translation_rmse_percent": ev["normalized_translation_rmse_percent"],
        "ape_rmse_m": ev["ape_rmse_m"],
        "joint_rmse_rad": joint_rmse(res.timestamps_ns, res.theta, flight.gt),
        "failed_updates": res.stats["failed_updates"],
        "segments": res.stats["segment_count"],
        "frames_with_gimbal": sum(f.dynamic_timestamp_ns is not None for f in frames),
        "frames": len(frames),
        "held_from_ns": to["held_from_ns"],
    }
    for name, c in (("static", 0), ("dynamic", 1)):
        est, sigma = to[f"{name}_s"], to[f"{name}_sigma_s"]
        out[f"{name}_offset_s"] = est
        out[f"{name}_sigma_s"] = sigma
        out[f"{name}_error_s"] = est - truth_offsets[c]
    return out
