"""Snapshots from unsynchronized or continuously moving recordings: each gimbal frame gets the static
camera's view of the target at the same instant, interpolated from the static frames around it.

Clocks. Every camera stamps its images on its own clock; with the convention of Kalibr and OpenVINS
(``t_imu = t_stamp + t_offset``) an image stamped ``tau`` was exposed at ``tau + t_offset`` on a
common clock. A gimbal image stamped ``tau_d`` was therefore exposed when the static camera's clock
read ``tau_d + delta`` with the inter-camera offset ``delta = t_d - t_s`` (seconds; stored here in
ns). For a hardware-synchronized pair ``delta = 0`` and the stamps coincide.

Compensation. The static camera's corners of one target point trace a smooth curve in time while
the rig moves; the corners at ``q = tau_d + delta`` are interpolated per corner id from the three
static frames nearest to ``q`` (quadratic Lagrange interpolation; linear when only two bracket it),
using the ids all of them saw. A snapshot is

* *exact* when a static frame lies within ``exact_tolerance_ns`` of ``q`` (its corners are used as
  detected: a recording held still, or synchronized cameras, give today's snapshots unchanged);
* *compensated* when the corners were interpolated;
* *rejected* when ``q`` is not bracketed by static frames within ``max_gap_ns`` of each other (the
  static camera lost the target, a stream stopped, or ``q`` lies outside the static recording), or
  when the motion is too fast for the interpolation: the quadratic and the linear interpolant
  disagree by more than ``max_curvature_px`` (then the unknown higher-order motion is not small).

Snapshot timestamps are ``q`` (the static camera's clock, ns), as for synchronized pairs.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dcc_fg.data import Observation, Snapshot

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class CameraStream:
    """Every frame of one camera, detected on its own.

    Attributes:
        stamps_ns: (N,) header stamps on the camera's own clock, ns, strictly increasing.
        observations: the target corners of each frame (empty where the target was not found).
        source: the folder or ``bag: topic`` the frames came from (for messages).
    """

    stamps_ns: IntArray
    observations: list[Observation]
    source: str

    def __post_init__(self) -> None:
        stamps = np.asarray(self.stamps_ns, dtype=np.int64).reshape(-1)
        object.__setattr__(self, "stamps_ns", stamps)
        if stamps.size != len(self.observations):
            raise ValueError(f"{self.source}: {stamps.size} stamps but {len(self.observations)} observations")
        if stamps.size > 1 and np.any(np.diff(stamps) <= 0):
            k = int(np.flatnonzero(np.diff(stamps) <= 0)[0])
            raise ValueError(
                f"{self.source}: stamps go backwards or repeat at frame {k + 1} ({stamps[k]} -> {stamps[k + 1]} ns); "
                "sort the frames by exposure time or fix the camera driver's stamps"
            )

    def period_ns(self) -> float:
        """Median frame period, ns (NaN for fewer than two frames)."""
        return float(np.median(np.diff(self.stamps_ns))) if self.stamps_ns.size > 1 else float("nan")


@dataclass(frozen=True)
class SyncOptions:
    """Pairing by interpolation (module docstring).

    Attributes:
        exact_tolerance_ns: a static frame this close to the query time is used as detected, ns.
        max_gap_factor: the static frames around the query may be at most this many static frame
            periods apart (a longer gap: lost target or stopped stream, the snapshot is rejected).
        max_curvature_px: largest disagreement of the quadratic and the linear interpolant, px.
        min_common_points: a snapshot needs at least this many target points seen by both cameras.
    """

    exact_tolerance_ns: int = 500_000
    max_gap_factor: float = 2.5
    max_curvature_px: float = 2.0
    min_common_points: int = 8

    def __post_init__(self) -> None:
        if self.exact_tolerance_ns < 0:
            raise ValueError(f"exact_tolerance_ns must be >= 0, got {self.exact_tolerance_ns}")
        if not (np.isfinite(self.max_gap_factor) and self.max_gap_factor >= 1.0):
            raise ValueError(f"max_gap_factor must be >= 1, got {self.max_gap_factor}")
        if not (np.isfinite(self.max_curvature_px) and self.max_curvature_px > 0):
            raise ValueError(f"max_curvature_px must be > 0, got {self.max_curvature_px}")


@dataclass
class SyncReport:
    """What the pairing did with the gimbal frames (counts) at the offset ``delta_ns``."""

    delta_ns: int
    dynamic_frames: int = 0
    exact: int = 0
    compensated: int = 0
    rejected: Counter[str] = field(default_factory=Counter)
    compensation_px: list[float] = field(default_factory=list)  # RMS corner shift of each compensated snapshot

    @property
    def used(self) -> int:
        return self.exact + self.compensated

    def to_dict(self) -> dict[str, Any]:
        shift = np.asarray(self.compensation_px, dtype=float)
        return {
            "delta_s": self.delta_ns * 1e-9,
            "dynamic_frames": self.dynamic_frames,
            "used": self.used,
            "exact": self.exact,
            "compensated": self.compensated,
            "rejected": dict(self.rejected),
            "compensation_px": {
                "median": float(np.median(shift)) if shift.size else None,
                "max": float(shift.max()) if shift.size else None,
            },
        }


def _common_ids(observations: list[Observation]) -> IntArray:
    ids = observations[0].ids
    for obs in observations[1:]:
        ids = np.intersect1d(ids, obs.ids)
    return ids


def _pixels_of(obs: Observation, ids: IntArray) -> FloatArray:
    order = {int(i): k for k, i in enumerate(obs.ids)}
    return obs.pixels[[order[int(i)] for i in ids]]


def lagrange_weights(times: FloatArray, q: float) -> FloatArray:
    """Weights ``w`` with ``f(q) ~= sum_k w_k f(t_k)`` (Lagrange polynomial through the ``times``)."""
    w = np.ones(times.size)
    for k in range(times.size):
        for m in range(times.size):
            if m != k:
                w[k] *= (q - times[m]) / (times[k] - times[m])
    return w


def interpolate_observation(
    stream: CameraStream, q_ns: float, max_gap_ns: float, max_curvature_px: float
) -> tuple[Observation | None, str, float]:
    """The stream's corners at time ``q_ns`` (its own clock), interpolated (module docstring).

    Returns ``(observation or None, reason, RMS shift from the nearest frame's corners px)``;
    ``reason`` is ``"exact"`` / ``"compensated"`` or why it was rejected.
    """
    t = stream.stamps_ns
    seen = np.array([len(o) > 0 for o in stream.observations])
    k = int(np.searchsorted(t, q_ns))  # t[k-1] < q <= t[k]
    if k == 0 or k >= t.size:
        return None, "outside the static recording", float("nan")
    a, b = k - 1, k
    if t[b] - t[a] > max_gap_ns:
        return None, "static frames too far apart", float("nan")
    if not (seen[a] and seen[b]):
        return None, "target not seen by the static camera around it", float("nan")
    idx = [a, b]
    third = [c for c in (a - 1, b + 1) if 0 <= c < t.size and seen[c] and abs(t[c] - q_ns) <= max_gap_ns]
    if third:
        idx.append(min(third, key=lambda c: abs(t[c] - q_ns)))
    obs = [stream.observations[i] for i in idx]
    ids = _common_ids(obs)
    if ids.size == 0:
        return None, "no corner common to the static frames around it", float("nan")
    P = np.stack([_pixels_of(o, ids) for o in obs])  # (n, N, 2)
    times = (t[idx] - q_ns).astype(float)
    linear = np.tensordot(lagrange_weights(times[:2], 0.0), P[:2], axes=1)
    value = np.tensordot(lagrange_weights(times, 0.0), P, axes=1) if len(idx) == 3 else linear
    if float(np.max(np.linalg.norm(value - linear, axis=1))) > max_curvature_px:
        return None, "motion too fast to interpolate", float("nan")
    nearest = P[int(np.argmin(np.abs(times)))]
    shift = float(np.sqrt(np.mean(np.sum((value - nearest) ** 2, axis=1))))
    return Observation(ids, value), "compensated", shift


def pair_streams(
    static: CameraStream, dynamic: CameraStream, delta_ns: int, options: SyncOptions | None = None
) -> tuple[list[Snapshot], SyncReport]:
    """One snapshot per gimbal frame that sees the target: its corners as detected, and the static
    camera's corners at the same instant (``tau_d + delta_ns`` on the static clock), exact or
    interpolated; the report counts what happened to every gimbal frame."""
    opt = options or SyncOptions()
    report = SyncReport(int(delta_ns))
    period = static.period_ns()
    max_gap = opt.max_gap_factor * period if np.isfinite(period) else 0.0
    snapshots: list[Snapshot] = []
    for tau_d, obs_d in zip(dynamic.stamps_ns, dynamic.observations, strict=True):
        report.dynamic_frames += 1
        if len(obs_d) == 0:
            report.rejected["target not seen by the gimbal camera"] += 1
            continue
        q = int(tau_d) + int(delta_ns)
        k = int(np.argmin(np.abs(static.stamps_ns - q))) if static.stamps_ns.size else -1
        if k >= 0 and abs(int(static.stamps_ns[k]) - q) <= opt.exact_tolerance_ns:
            obs_s, reason, shift = static.observations[k], "exact", 0.0
            q = int(static.stamps_ns[k])  # the static frame's stamp, as for synchronized pairs
            if len(obs_s) == 0:
                obs_s, reason = None, "target not seen by the static camera around it"
        else:
            obs_s, reason, shift = interpolate_observation(static, q, max_gap, opt.max_curvature_px)
        if obs_s is None:
            report.rejected[reason] += 1
            continue
        if np.intersect1d(obs_s.ids, obs_d.ids).size < opt.min_common_points:
            report.rejected["fewer common corners than min_common_points"] += 1
            continue
        snapshots.append(Snapshot(q, obs_s, obs_d, None))
        if reason == "exact":
            report.exact += 1
        else:
            report.compensated += 1
            report.compensation_px.append(shift)
    return snapshots, report
