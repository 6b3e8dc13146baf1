"""Health checks of a VIO result (see :mod:`dcc_fg.util.health`).

:func:`vio_health` judges a finished run from its keyframe states and the recovery record the
smoother keeps in ``result.stats`` (:class:`~dcc_fg.vio.backend.smoother.VioSmoother`). Checks and
their thresholds (``options``: :class:`~dcc_fg.vio.backend.options.VioOptions`; ``imu``:
:class:`~dcc_fg.data.vio.ImuConfig`):

* ``keyframes``: at least ``min_track_keyframes`` keyframes (fewer cannot triangulate a landmark);
* ``finite``: every pose, velocity, bias and joint angle (further gimbal chains' too) finite;
* ``cameras.<name>`` (warning, N-camera runs): each further camera contributed landmark observations;
* ``observations.<name>`` (N-camera runs): the fraction of each camera's tracks that became landmark
  observations at least :data:`MIN_USED_RATIO` times cam0's, and cam0's own at least
  :data:`MIN_USED_FRACTION` (a camera that does not fit can wreck every camera's landmarks);
* ``residuals.<name>`` (N-camera runs): each camera's median reprojection residual (px,
  :mod:`dcc_fg.vio.backend.residuals`) at most :data:`MAX_RESIDUAL_RATIO` times cam0's: all cameras go
  through the same front end, so one that fits far worse than cam0 has a wrong ``T_cs`` / ``tau_d`` or
  intrinsics (1 deg of extrinsic rotation on the simulated stereo partner wrecks the run: its residual 10.8x
  cam0's on one flight, the gimbal camera's 3.7x on another, where the partner's observations were gated);
* ``speed``: every keyframe speed within ``max_speed`` (m/s);
* ``position_jumps``: within each trajectory segment, the distance between consecutive keyframes
  within what the previous speed and the IMU's acceleration range allow in the elapsed time
  (:func:`~dcc_fg.vio.backend.divergence.max_jump`);
* ``divergences``: every divergence / failed update detected during the run was followed by a
  segment that lasted at least one smoother window (``lag``) without diverging again;
* ``velocity_covariance``: the final keyframe's velocity 1-sigma within ``max_velocity_sigma``;
* ``vision``: the longest stretch of keyframes without any visual factor (landmark observation or
  zero-velocity update) no longer than two smoother windows (``2 lag``; one window can pass at a
  start from standstill before the motion gives the parallax to triangulate): beyond it the
  trajectory is IMU dead reckoning (an IMU clock offset or rate problem, a camera facing nothing);
* ``time_offsets.range`` (offsets estimated): every offset estimate within
  ``TIME_OFFSET_PRIOR_SIGMAS`` prior sigmas (``time_offset_prior_sigma``) of its start value; farther
  means the prior was wrong by far more than it claimed, or the estimate ran away;
* ``time_offsets.determined`` (warning): every offset's 1-sigma below half its prior sigma, i.e. the
  data determined it (too little rotation or motion leaves it at the start value);
* ``segments`` (always passes, informative): how many trajectory segments the run has.

Frames and units: ``T_WI`` body/IMU -> world, m, m/s, s.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np

from dcc_fg.data.vio import ImuConfig
from dcc_fg.util.health import HealthCheck, HealthReport
from dcc_fg.vio.backend.divergence import DivergenceLimits, max_jump, state_is_finite
from dcc_fg.vio.backend.options import NS, VioOptions, VioResult
from dcc_fg.vio.backend.state import KeyframeState


def _state(result: VioResult, i: int) -> KeyframeState:
    return KeyframeState(
        int(result.timestamps_ns[i]),
        result.T_WI[i],
        result.v_W[i],
        result.acc_bias[i],
        result.gyro_bias[i],
        result.theta[i],
    )


def _segment_of(result: VioResult) -> np.ndarray:
    """Segment index of every keyframe (from ``stats['segments']`` start stamps; 0 without them)."""
    starts = sorted(int(s["start_ns"]) for s in result.stats.get("segments", []))
    if not starts:
        return np.zeros(result.timestamps_ns.size, dtype=int)
    return np.searchsorted(np.asarray(starts, dtype=np.int64), result.timestamps_ns, side="right") - 1


def _jump_check(result: VioResult, limits: DivergenceLimits) -> HealthCheck:
    seg = _segment_of(result)
    worst_ratio, where = 0.0, ""
    for i in range(1, result.timestamps_ns.size):
        if seg[i] != seg[i - 1]:
            continue
        prev, cur = _state(result, i - 1), _state(result, i)
        if not (state_is_finite(prev) and state_is_finite(cur)):
            continue
        dt = (cur.t_ns - prev.t_ns) / NS
        jump = float(np.linalg.norm(cur.T_WI[:3, 3] - prev.T_WI[:3, 3]))
        bound = max_jump(prev, dt, limits)
        ratio = jump / bound if bound > 0 else np.inf
        if ratio > worst_ratio:
            worst_ratio, where = (
                ratio,
                f"{jump:.3g} m in {dt:.3f} s at t_ns {cur.t_ns}, bound {bound:.3g} m",
            )
    return HealthCheck(
        "position_jumps",
        worst_ratio <= 1.0,
        f"largest keyframe-to-keyframe move relative to the physical bound: {worst_ratio:.3g} ({where or 'none'})",
        "" if worst_ratio <= 1.0 else "the estimate jumped: check the IMU data (spikes, units, rate) and --pixel-sigma",
        worst_ratio,
        1.0,
    )


#: ``time_offsets.range``: largest move of an offset estimate from its start value, in prior sigmas.
TIME_OFFSET_PRIOR_SIGMAS = 4.0


def _time_offset_checks(offsets: dict[str, Any], options: VioOptions) -> list[HealthCheck]:
    """``time_offsets.range`` and ``time_offsets.determined`` (module docstring)."""
    prior = options.time_offset_prior_sigma
    cams = [c for c in ("static", "dynamic") if f"{c}_s" in offsets]
    moved = {c: abs(float(offsets[f"{c}_s"]) - float(offsets["start_s"][c])) for c in cams}
    worst = max(moved, key=lambda c: moved[c])
    limit = TIME_OFFSET_PRIOR_SIGMAS * prior
    ok = moved[worst] <= limit
    text = ", ".join(f"t_{c[0]} {1e3 * float(offsets[f'{c}_s']):.2f} ms" for c in cams)
    checks = [
        HealthCheck(
            "time_offsets.range",
            ok,
            f"offset estimates {text}; largest move from the start value {1e3 * moved[worst]:.1f} ms ({worst} camera; "
            f"limit {TIME_OFFSET_PRIOR_SIGMAS:g} prior sigmas = {1e3 * limit:.0f} ms)",
            ""
            if ok
            else "the offset left its prior: start closer to the true delay (--time-offsets T_S,T_D), raise "
            "smoother.time_offset_prior_sigma if the start really is that uncertain, or check the stamps",
            moved[worst],
            limit,
        )
    ]
    sigmas = {c: offsets.get(f"{c}_sigma_s") for c in cams}
    loose = [c for c in cams if sigmas[c] is None or sigmas[c] > 0.5 * prior]
    checks.append(
        HealthCheck(
            "time_offsets.determined",
            not loose,
            "offset 1-sigma "
            + ", ".join(f"t_{c[0]} {'unknown' if sigmas[c] is None else f'{1e3 * sigmas[c]:.3f} ms'}" for c in cams)
            + f" (prior {1e3 * prior:g} ms)",
            ""
            if not loose
            else f"the data hardly determined the {' and '.join(loose)} camera's offset (too little rotation or "
            "motion): it stays near its start value; give a known value with --time-offsets and --fix-time-offsets",
            max((s or np.inf) for s in sigmas.values()),
            0.5 * prior,
            severity="warning",
        )
    )
    return checks


#: Largest ratio of a camera's median reprojection residual to cam0's (``residuals.<name>``). Measured with
#: correct extrinsics: 0.98-1.06 (tracks-level simulation), 0.96-1.30 (rendered cluster flights), 0.84
#: (EuRoC's stereo pair); with 1 deg of rotation error on the simulated stereo partner: 10.8 (the partner)
#: or 3.7 (the gimbal camera), depending on the flight.
MAX_RESIDUAL_RATIO = 3.0


def _against_cam0(values: dict[str, Any]) -> Iterator[tuple[str, float, float, float]]:
    """``(camera, value, cam0's value, ratio)`` of every camera but cam0 with a value, when cam0 has one."""
    ref = values.get("cam0")
    if not ref:
        return
    for name, value in values.items():
        if name != "cam0" and value is not None:
            yield name, float(value), float(ref), float(value) / float(ref)


def _residual_checks(stats: dict[str, Any]) -> list[HealthCheck]:
    """``residuals.<name>``: each camera's median residual (px) against cam0's (module docstring)."""
    out = []
    for name, med, ref, ratio in _against_cam0(stats.get("residual_median_px") or {}):
        ok = ratio <= MAX_RESIDUAL_RATIO
        out.append(
            HealthCheck(
                f"residuals.{name}",
                ok,
                f"median reprojection residual of {name} {med:.2f} px, {ratio:.2f}x cam0's "
                f"({ref:.2f} px; limit {MAX_RESIDUAL_RATIO:g}x)",
                ""
                if ok
                else f"{name} does not fit the other cameras: check its extrinsics (T_cs of a static camera, tau_d "
                "on a chain), its intrinsics and that it is triggered with cam0; or leave it out with --cameras",
                ratio,
                MAX_RESIDUAL_RATIO,
            )
        )
    return out


#: Smallest ratio of a camera's used-observation fraction to cam0's (``observations.<name>``). Measured with
#: correct extrinsics: 0.97-1.07 (rendered cluster flights, fractions 0.79-0.88), 1.01 (EuRoC's stereo pair);
#: the simulated stereo partner 1 deg off: 0 to 0.34 (the run is refused by one check or the other).
MIN_USED_RATIO = 0.2
#: Smallest fraction of cam0's tracks that became observations in an N-camera run (``observations.cam0``):
#: 0.79-0.88 with correct extrinsics (above); 0.007 on a 10 s simulated stereo+gimbal flight whose stereo
#: partner is 1 deg off, where no camera's landmarks survive (every ratio to cam0 then looks normal).
MIN_USED_FRACTION = 0.2

_USED_HINT = (
    "their stereo tracks fail triangulation or their observations are gated): check its extrinsics (T_cs / tau_d), "
    "intrinsics and triggering; or leave it out with --cameras"
)


def _used_checks(stats: dict[str, Any]) -> list[HealthCheck]:
    """``observations.<name>``: the fraction of each camera's tracks that became observations, against
    cam0's, and cam0's own (:meth:`~dcc_fg.vio.backend.residuals.CameraResiduals.used_fractions`)."""
    out = []
    fractions = stats.get("observations_used_fraction") or {}
    ref = fractions.get("cam0")
    if ref is not None and len(fractions) > 1:
        ok = float(ref) >= MIN_USED_FRACTION
        out.append(
            HealthCheck(
                "observations.cam0",
                ok,
                f"{100 * float(ref):.1f} % of cam0's tracks became landmark observations (limit "
                f"{100 * MIN_USED_FRACTION:g} %)",
                ""
                if ok
                else "the cameras' features do not fit each other (a further camera's extrinsics can wreck every "
                "camera's landmarks: " + _USED_HINT,
                float(ref),
                MIN_USED_FRACTION,
            )
        )
    for name, frac, ref, ratio in _against_cam0(fractions):
        ok = ratio >= MIN_USED_RATIO
        out.append(
            HealthCheck(
                f"observations.{name}",
                ok,
                f"{100 * frac:.1f} % of {name}'s tracks became landmark observations, {ratio:.2f}x cam0's "
                f"{100 * ref:.1f} % (limit {MIN_USED_RATIO:g}x)",
                "" if ok else f"{name}'s features do not fit the other cameras' (" + _USED_HINT,
                ratio,
                MIN_USED_RATIO,
            )
        )
    return out


def _further_camera_checks(stats: dict[str, Any]) -> list[HealthCheck]:
    """``cameras.<name>`` (warning): each further camera of an N-camera run contributed observations of
    landmarks; none means its images, topic or extrinsics do not fit the others' (the run is the run of
    the other cameras)."""
    out = []
    for name, count in (stats.get("extra_obs") or {}).items():
        ok = int(count) > 0
        out.append(
            HealthCheck(
                f"cameras.{name}",
                ok,
                f"{int(count)} observations of camera {name} used",
                ""
                if ok
                else f"none of {name}'s tracks became an observation: check its topic, intrinsics and T_cs / tau_d "
                "(a mirrored or wrong extrinsic leaves every point outside the gate), or leave it out with --cameras",
                int(count),
                1,
                severity="warning",
            )
        )
    return out


def vio_health(result: VioResult, imu: ImuConfig, options: VioOptions) -> HealthReport:
    """Every health check of the trajectory ``result`` (module docstring)."""
    report = HealthReport("trajectory")
    stats: dict[str, Any] = result.stats
    # the window the run used (VioOptions.resolved), else the options' own
    lag = float(stats.get("window", {}).get("lag_s") or options.resolved(False).window_s)
    limits = DivergenceLimits.from_options(options, imu)
    n = int(result.timestamps_ns.size)
    need = options.min_track_keyframes
    report.add(
        HealthCheck(
            "keyframes",
            n >= need,
            f"{n} keyframes (at least {need} are needed to triangulate a landmark)",
            "" if n >= need else "the bag is too short or almost no frame lies within the IMU's time span",
            n,
            need,
        )
    )
    if n == 0:
        return report
    finite = all(state_is_finite(_state(result, i)) for i in range(n))
    finite = finite and all(bool(np.all(np.isfinite(th))) for th in result.chain_theta.values())
    report.add(
        HealthCheck(
            "finite",
            finite,
            "every keyframe state is finite" if finite else "NaN/inf in the estimated poses, velocities or biases",
            "" if finite else "check the IMU samples and noise densities",
        )
    )
    speeds = np.linalg.norm(result.v_W, axis=1)
    vmax = float(np.nanmax(speeds)) if np.any(np.isfinite(speeds)) else float("inf")
    ok = vmax <= options.max_speed
    report.add(
        HealthCheck(
            "speed",
            ok,
            f"largest speed {vmax:.3g} m/s (physical limit max_speed {options.max_speed:g} m/s)",
            ""
            if ok
            else "the estimate diverged: check IMU units (m/s^2, rad/s), T_sI and the IMU noise; raise "
            "smoother.max_speed only if the platform really is that fast",
            vmax,
            options.max_speed,
        )
    )
    report.add(_jump_check(result, limits))
    for check in _further_camera_checks(stats) + _residual_checks(stats) + _used_checks(stats):
        report.add(check)
    events = stats.get("divergences", [])
    bad = [e for e in events if not e.get("recovered", False)]
    report.add(
        HealthCheck(
            "divergences",
            not bad,
            f"{len(events)} divergence/failed-update events during the run, {len(bad)} not recovered within one "
            f"window ({lag:g} s)" + (f"; first: {bad[0]['reason']} at t_ns {bad[0]['t_ns']}" if bad else ""),
            ""
            if not bad
            else "the estimate kept diverging after restarts: check the IMU noise densities, T_sI and the camera "
            "calibration",
            len(bad),
            0,
        )
    )
    sigma = stats.get("final_velocity_sigma_mps")
    if sigma is not None:
        ok = bool(sigma <= options.max_velocity_sigma)
        report.add(
            HealthCheck(
                "velocity_covariance",
                ok,
                f"final velocity 1-sigma {sigma:.3g} m/s (limit max_velocity_sigma {options.max_velocity_sigma:g} m/s)",
                "" if ok else "nothing constrains the velocity at the end (vision lost?): check the images and IMU",
                sigma,
                options.max_velocity_sigma,
            )
        )
    blind = stats.get("longest_without_vision_s")
    if blind is not None:
        limit = 2.0 * lag
        ok = bool(blind <= limit)
        report.add(
            HealthCheck(
                "vision",
                ok,
                f"longest stretch of keyframes without any visual factor: {blind:.2f} s (limit: two smoother windows, "
                f"2 x lag = {limit:g} s)",
                ""
                if ok
                else "vision contributed nothing for that long (IMU dead reckoning): check the IMU clock offset and "
                "rate against the images, the camera topics and calibration (T_sI), and --pixel-sigma",
                blind,
                limit,
            )
        )
    offsets = stats.get("time_offsets")
    if offsets is not None and offsets.get("estimated"):
        for check in _time_offset_checks(offsets, options):
            report.add(check)
    segments = stats.get("segments", [])
    report.add(
        HealthCheck(
            "segments",
            True,
            f"{max(len(segments), 1)} trajectory segment(s)"
            + (
                ": restarts at " + ", ".join(f"t_ns {s['start_ns']} ({s['reason']})" for s in segments[1:])
                if len(segments) > 1
                else ""
            ),
            value=max(len(segments), 1),
        )
    )
    return report
