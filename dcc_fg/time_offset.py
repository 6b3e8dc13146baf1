"""Calibration from unsynchronized or continuously moving recordings, with the inter-camera time offset.

The snapshots are built by :func:`dcc_fg.sync.pair_streams` for an inter-camera offset
``delta = t_d - t_s`` (s; ``t_imu = t_stamp + t_offset`` per camera, Kalibr / OpenVINS convention):
each gimbal frame with the static camera's corners interpolated to its exposure time. When the offset
is not given it is estimated: with the wrong ``delta`` the static view belongs to another instant
than the gimbal view, and while the rig moves no joint angles reconcile the two, so the
reprojection error grows with ``|delta - delta_true|``. The mean squared pixel residual of the
calibration is minimized over ``delta`` by golden-section search on ``delta0 +- half`` (default:
half the longer frame period), each evaluation a single-start calibration from the kinematics found
at ``delta0``; a parabola through the last bracket gives the estimate and, from its curvature in
chi-square units, the 1-sigma. The final calibration at the estimate uses the global strategy
(:func:`dcc_fg.global_fit.calibrate_global`).

A recording without motion between the cameras' frames carries no information about ``delta``:
the cost is flat, the 1-sigma is reported as unbounded and the offset is not trusted (``estimated``
stays True but ``determined`` is False).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dcc_fg.calibrate import CalibrationOptions, CalibrationResult, calibrate
from dcc_fg.data import CalibrationDataset, Snapshot
from dcc_fg.global_fit import calibrate_global
from dcc_fg.model import GimbalCalibration
from dcc_fg.sync import CameraStream, SyncOptions, SyncReport, pair_streams
from dcc_fg.util.errors import EstimatorError
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]
log = logging.getLogger("dcc_fg.time_offset")

GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0
SEARCH_ITERATIONS = 14  # golden-section steps: the bracket shrinks to 0.618^14 ~ 1e-3 of its width
CURVATURE_STEP_FRACTION = 8.0  # the 1-sigma comes from the parabola through best and best +- half / 8
MAX_SNAPSHOTS = 150  # gimbal frames used (evenly spaced) when a recording has more


@dataclass
class OffsetEstimate:
    """The inter-camera offset used and how it was found.

    Attributes:
        delta_s: ``t_d - t_s``, s. std_s: its 1-sigma (s; inf when the data do not determine it,
            NaN when it was given). estimated: searched (True) or given (False). determined: the
            cost has a clear minimum inside the searched interval. interval_s: the interval searched.
        evaluations: ``[(delta_s, mean squared pixel residual px^2, number of residual values)]``.
    """

    delta_s: float
    std_s: float = float("nan")
    estimated: bool = False
    determined: bool = True
    interval_s: tuple[float, float] | None = None
    evaluations: list[tuple[float, float, int]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {
            "delta_s": self.delta_s,
            "std_s": self.std_s,
            "estimated": self.estimated,
            "determined": self.determined,
            "interval_s": list(self.interval_s) if self.interval_s else None,
            "evaluations": [list(e) for e in self.evaluations],
        }


@dataclass
class StreamCalibration:
    """The calibration, the data it used, the pairing report and the offset."""

    result: CalibrationResult
    data: CalibrationDataset
    sync: SyncReport
    offset: OffsetEstimate


def subsample(stream: CameraStream, max_frames: int) -> CameraStream:
    """At most ``max_frames`` frames that see the target, evenly spaced in time (all when fewer)."""
    seen = [k for k, o in enumerate(stream.observations) if len(o) > 0]
    if len(seen) <= max_frames:
        keep = seen
    else:
        keep = sorted({seen[int(round(x))] for x in np.linspace(0, len(seen) - 1, max_frames)})
    return CameraStream(stream.stamps_ns[keep], [stream.observations[k] for k in keep], stream.source)


def dataset_at(
    static: CameraStream,
    dynamic: CameraStream,
    cameras: tuple[CameraModel, CameraModel],
    target_points: FloatArray,
    delta_s: float,
    sync: SyncOptions,
    source: str,
) -> tuple[CalibrationDataset, SyncReport]:
    """The snapshots for the offset ``delta_s`` (:func:`dcc_fg.sync.pair_streams`) as a dataset."""
    snapshots, report = pair_streams(static, dynamic, int(round(delta_s * 1e9)), sync)
    if not snapshots:
        reasons = ", ".join(f"{k}: {v}" for k, v in report.rejected.items()) or "no gimbal frames"
        raise ValueError(
            f"{source}: no gimbal frame could be paired with the static camera at an offset of "
            f"{delta_s * 1e3:.3g} ms ({reasons}); check --time-offsets and that both cameras see the target"
        )
    data = CalibrationDataset(cameras[0], cameras[1], target_points, snapshots, source=source)
    return data, report


def _with_guesses(
    data: CalibrationDataset, previous: CalibrationResult, previous_data: CalibrationDataset
) -> CalibrationDataset:
    """``data`` with each snapshot's joint guess from the previous solution's snapshot nearest in time."""
    t_prev = np.array([s.timestamp_ns for s in previous_data.snapshots], dtype=np.int64)
    out: list[Snapshot] = []
    for s in data.snapshots:
        k = int(np.argmin(np.abs(t_prev - s.timestamp_ns)))
        out.append(replace(s, joints=previous.joint_angles[k].copy()))
    return replace(data, snapshots=out)


def mean_squared_residual(result: CalibrationResult) -> tuple[float, int]:
    """Mean squared pixel residual (px^2, both cameras, u and v) and the number of values."""
    ss = sum(float(np.sum(r * r)) for r in result.residuals_static + result.residuals_dynamic)
    n = sum(int(r.size) for r in result.residuals_static + result.residuals_dynamic)
    return ss / max(n, 1), n


def calibrate_streams(
    static: CameraStream,
    dynamic: CameraStream,
    cameras: tuple[CameraModel, CameraModel],
    target_points: FloatArray,
    n_joints: int,
    options: CalibrationOptions | None = None,
    initial: GimbalCalibration | None = None,
    delta_s: float | None = None,
    estimate: bool = True,
    half_width_s: float | None = None,
    sync: SyncOptions | None = None,
    max_snapshots: int = MAX_SNAPSHOTS,
    source: str = "",
) -> StreamCalibration:
    """Calibrate from two unsynchronized streams (module docstring).

    Args:
        static, dynamic: every frame of each camera, detected (:func:`dcc_fg.sources.dataset.load_streams`).
        cameras: (static, dynamic) intrinsics; target_points: (N, 3) target points, m.
        n_joints: L. options: the solver's options. initial: ``--gimbal`` kinematics (a start of the
            global strategy), or None.
        delta_s: ``t_d - t_s`` (s): the offset to use (``estimate=False``) or the centre of the search.
        half_width_s: half width of the search interval, s (default: half the longer frame period).
        max_snapshots: gimbal frames used at most (evenly spaced).

    Raises:
        ValueError: no gimbal frame pairs at the offset, bad arguments.
    """
    opt = options or CalibrationOptions()
    sync = sync or SyncOptions()
    if max_snapshots < 1:
        raise ValueError(f"max_snapshots must be >= 1, got {max_snapshots}")
    delta0 = 0.0 if delta_s is None else float(delta_s)
    periods = [s.period_ns() * 1e-9 for s in (static, dynamic)]
    longest = max((p for p in periods if math.isfinite(p)), default=float("nan"))
    if math.isfinite(longest) and abs(delta0) > 0.5 * longest:
        log.warning(
            "the given inter-camera offset %.1f ms is more than half a frame period (%.1f ms): the gimbal frames "
            "are paired with the static frames around tau_d + delta, as given",
            delta0 * 1e3, 0.5 * longest * 1e3,
        )  # fmt: skip
    dyn = subsample(dynamic, max_snapshots)
    data0, report0 = dataset_at(static, dyn, cameras, target_points, delta0, sync, source)
    first = calibrate_global(data0, n_joints, opt, initial=initial)
    if not estimate:
        return StreamCalibration(first, data0, report0, OffsetEstimate(delta0))

    half = half_width_s if half_width_s is not None else 0.5 * longest
    if not (math.isfinite(half) and half > 0):
        raise ValueError(f"the offset search needs a positive half width, got {half} s (frame periods {periods})")
    evaluations: list[tuple[float, float, int]] = []
    cache: dict[float, float] = {}

    def cost(delta: float) -> float:
        if delta in cache:
            return cache[delta]
        try:
            data, _ = dataset_at(static, dyn, cameras, target_points, delta, sync, source)
            res = calibrate(_with_guesses(data, first, data0), first.calibration, opt)
            value, n = mean_squared_residual(res)
        except (EstimatorError, ValueError) as exc:
            log.info("offset %.3f ms: %s", delta * 1e3, exc)
            value, n = float("inf"), 0
        cache[delta] = value
        evaluations.append((delta, value, n))
        return value

    lo, hi = delta0 - half, delta0 + half
    a, b = hi - GOLDEN * (hi - lo), lo + GOLDEN * (hi - lo)
    fa, fb = cost(a), cost(b)
    for _ in range(SEARCH_ITERATIONS):
        if fa <= fb:
            hi, b, fb = b, a, fa
            a = hi - GOLDEN * (hi - lo)
            fa = cost(a)
        else:
            lo, a, fa = a, b, fb
            b = lo + GOLDEN * (hi - lo)
            fb = cost(b)
    best = a if fa <= fb else b
    step = max(half / CURVATURE_STEP_FRACTION, 1e-4)
    around = [(d, cost(d)) for d in (best - step, best, best + step)]
    estimate_info = _parabola([e for e in evaluations if any(e[0] == d for d, _ in around)], best)
    estimate_info.interval_s = (delta0 - half, delta0 + half)
    estimate_info.evaluations = sorted(evaluations)
    data, report = dataset_at(static, dyn, cameras, target_points, estimate_info.delta_s, sync, source)
    result = calibrate_global(
        _with_guesses(data, first, data0), n_joints, opt, initial=first.calibration, initial_name="offset search"
    )
    if not estimate_info.determined:
        log.warning(
            "the inter-camera time offset is not determined by the data (the cost is flat: little motion between "
            "the cameras' frames); the offset %.2f ms is used as given", delta0 * 1e3,
        )  # fmt: skip
    return StreamCalibration(result, data, report, estimate_info)


def _parabola(evaluations: list[tuple[float, float, int]], best: float) -> OffsetEstimate:
    """Estimate and 1-sigma from the parabola through the evaluations at ``best`` and ``best +- step``.

    The profile cost in chi-square units is ``chi2(delta) = n * msr(delta) / sigma^2`` (``n`` residual
    values, ``sigma^2`` the mean squared residual at the minimum: the a-posteriori variance), so with
    ``msr ~ c2 (delta - d*)^2 + ...`` the 1-sigma is ``sqrt(2 / chi2'') = sqrt(sigma^2 / (n c2))``."""
    pts = sorted((e for e in evaluations if math.isfinite(e[1])), key=lambda e: abs(e[0] - best))[:5]
    if len(pts) < 3:
        return OffsetEstimate(best, float("inf"), True, False)
    x = np.array([p[0] for p in pts]) - best
    y = np.array([p[1] for p in pts])
    c2, c1, _ = np.polyfit(x, y, 2)
    if not c2 > 0:
        return OffsetEstimate(best, float("inf"), True, False)
    vertex = best - c1 / (2.0 * c2)
    if abs(vertex - best) > float(np.ptp(x)):
        vertex = best
    sigma2 = max(float(np.min(y)), 1e-300)
    n = float(np.median([p[2] for p in pts]))
    std = math.sqrt(sigma2 / (n * c2))
    return OffsetEstimate(float(vertex), std, True, True)
