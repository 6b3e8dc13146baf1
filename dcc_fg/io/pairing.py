"""Timestamp pairing shared by every reader (image folders, bags, detection folders).

All timestamps are integers in nanoseconds.  The static camera (``cam0``) is the reference: a
pair is reported at the static frame's timestamp.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

log = logging.getLogger(__name__)

#: Default pairing tolerance: 5 ms (well below the frame period of a 30 Hz camera pair).
DEFAULT_TOLERANCE_NS = 5_000_000


@dataclass
class Pairing:
    """Result of :func:`pair_timestamps`.

    Attributes:
        pairs: ``(i, j)`` indices into the static and dynamic timestamp lists, sorted by the
            static timestamp; each index appears at most once.
        unpaired_static: static timestamps (ns) without a dynamic frame within the tolerance.
        unpaired_dynamic: dynamic timestamps (ns) without a static frame within the tolerance.
        tolerance_ns: the tolerance used.
        static_ns, dynamic_ns: the two timestamp lists that were paired (the indices of ``pairs``
            refer to them), ns.
    """

    pairs: list[tuple[int, int]] = field(default_factory=list)
    unpaired_static: list[int] = field(default_factory=list)
    unpaired_dynamic: list[int] = field(default_factory=list)
    tolerance_ns: int = DEFAULT_TOLERANCE_NS
    static_ns: list[int] = field(default_factory=list, repr=False)
    dynamic_ns: list[int] = field(default_factory=list, repr=False)

    def statistics(self) -> dict[str, float | int | None]:
        """Numbers for a pairing health check (milliseconds; None where undefined).

        Returns:
            ``pairs``; ``gap_median_ms`` / ``gap_max_ms``: median and largest
            ``|t_dynamic - t_static|`` over the pairs; ``gap_median_signed_ms``: median of
            ``t_dynamic - t_static``; ``period_static_ms`` / ``period_dynamic_ms``: median frame
            period of each camera (median difference of its sorted distinct stamps);
            ``unpaired_static`` / ``unpaired_dynamic``: frames without a partner;
            ``tolerance_ms``: the pairing tolerance.
        """
        s = np.asarray(self.static_ns, dtype=np.int64)
        d = np.asarray(self.dynamic_ns, dtype=np.int64)
        out: dict[str, float | int | None] = {
            "pairs": len(self.pairs),
            "gap_median_ms": None,
            "gap_max_ms": None,
            "gap_median_signed_ms": None,
            "period_static_ms": median_period_ms(s),
            "period_dynamic_ms": median_period_ms(d),
            "unpaired_static": len(self.unpaired_static),
            "unpaired_dynamic": len(self.unpaired_dynamic),
            "tolerance_ms": self.tolerance_ns / 1e6,
        }
        if self.pairs and s.size and d.size:
            idx = np.asarray(self.pairs, dtype=np.int64)
            gap = (d[idx[:, 1]] - s[idx[:, 0]]).astype(float) / 1e6
            out["gap_median_ms"] = float(np.median(np.abs(gap)))
            out["gap_max_ms"] = float(np.max(np.abs(gap)))
            out["gap_median_signed_ms"] = float(np.median(gap))
        return out

    def summary(self, static_name: str = "cam0", dynamic_name: str = "cam1") -> str:
        """One line: counts of pairs and unpaired frames per stream."""
        return (
            f"{len(self.pairs)} pairs within {self.tolerance_ns / 1e6:g} ms; unpaired frames: "
            f"{len(self.unpaired_static)} of {static_name}, {len(self.unpaired_dynamic)} of {dynamic_name}"
        )


def pair_timestamps(
    static_ns: Sequence[int] | NDArray[np.int64],
    dynamic_ns: Sequence[int] | NDArray[np.int64],
    tolerance_ns: int = DEFAULT_TOLERANCE_NS,
) -> Pairing:
    """Pair two timestamp lists one-to-one, closest pairs first.

    Every candidate pair with ``|t_static - t_dynamic| <= tolerance_ns`` is considered in order
    of increasing time difference and accepted if neither frame is paired yet (a greedy minimum
    matching: exact for the usual case of one candidate per frame, and never pairs a frame twice).

    Args:
        static_ns: static-camera timestamps, ns (any order; duplicates allowed).
        dynamic_ns: dynamic-camera timestamps, ns.
        tolerance_ns: largest accepted time difference, ns (>= 0).

    Returns:
        The pairs and the unpaired timestamps of each stream (both sorted ascending).
    """
    if tolerance_ns < 0:
        raise ValueError(f"tolerance_ns must be >= 0, got {tolerance_ns}")
    s = np.asarray(static_ns, dtype=np.int64).reshape(-1)
    d = np.asarray(dynamic_ns, dtype=np.int64).reshape(-1)
    d_order = np.argsort(d, kind="stable")
    d_sorted = d[d_order]
    lo = np.searchsorted(d_sorted, s - tolerance_ns, side="left")
    hi = np.searchsorted(d_sorted, s + tolerance_ns, side="right")
    candidates: list[tuple[int, int, int]] = []
    for i in range(s.size):
        for k in range(int(lo[i]), int(hi[i])):
            j = int(d_order[k])
            candidates.append((abs(int(s[i]) - int(d[j])), i, j))
    candidates.sort()
    used_s = np.zeros(s.size, dtype=bool)
    used_d = np.zeros(d.size, dtype=bool)
    pairs = []
    for _, i, j in candidates:
        if not used_s[i] and not used_d[j]:
            used_s[i] = used_d[j] = True
            pairs.append((i, j))
    pairs.sort(key=lambda p: (int(s[p[0]]), p[0]))
    return Pairing(
        pairs=pairs,
        unpaired_static=sorted(int(x) for x in s[~used_s]),
        unpaired_dynamic=sorted(int(x) for x in d[~used_d]),
        tolerance_ns=int(tolerance_ns),
        static_ns=[int(x) for x in s],
        dynamic_ns=[int(x) for x in d],
    )


def median_period_ms(stamps_ns: Sequence[int] | NDArray[np.int64]) -> float | None:
    """Median difference of the sorted distinct stamps, ms (None for fewer than 2 stamps)."""
    t = np.unique(np.asarray(stamps_ns, dtype=np.int64))
    return float(np.median(np.diff(t))) / 1e6 if t.size >= 2 else None


def stamp_jitter_s(stamps_ns: Sequence[int] | NDArray[np.int64]) -> float:
    """1-sigma (s) of a camera's header stamps around a regular grid ``t0 + n P``: the grid index ``n``
    of each stamp from the 10th percentile of the intervals (so a stream with dropped or skipped
    frames, e.g. only the gimbal images paired with a slower static camera, still finds its period),
    ``t0`` and ``P`` by least squares (absorbs a clock-rate difference), then ``1.4826 MAD`` of the
    residuals; 0 for fewer than 4 distinct stamps."""
    t = np.unique(np.asarray(stamps_ns, dtype=np.int64))
    if t.size < 4:
        return 0.0
    rel = (t - t[0]).astype(float)
    d = np.diff(rel)
    period = float(np.percentile(d, 10))
    if period <= 0:
        return 0.0
    n = np.r_[0.0, np.cumsum(np.maximum(np.round(d / period), 1.0))]  # interval by interval: no drift of n
    A = np.column_stack([np.ones_like(n), n])
    coef, *_ = np.linalg.lstsq(A, rel, rcond=None)
    r = rel - A @ coef
    return float(1.4826 * np.median(np.abs(r - np.median(r)))) / 1e9


def nearest_within(
    query_ns: Sequence[int] | NDArray[np.int64],
    reference_ns: Sequence[int] | NDArray[np.int64],
    tolerance_ns: int,
) -> NDArray[np.int64]:
    """Index of the nearest reference timestamp for each query, or -1 if none is within tolerance.

    Not one-to-one (several snapshots may take the same joint-state sample).
    """
    q = np.asarray(query_ns, dtype=np.int64).reshape(-1)
    r = np.asarray(reference_ns, dtype=np.int64).reshape(-1)
    out = np.full(q.size, -1, dtype=np.int64)
    if r.size == 0:
        return out
    order = np.argsort(r, kind="stable")
    rs = r[order]
    pos = np.searchsorted(rs, q)
    for n, (t, p) in enumerate(zip(q, pos, strict=True)):
        best, best_dt = -1, tolerance_ns + 1
        for k in (p - 1, p):
            if 0 <= k < rs.size and abs(int(rs[k]) - int(t)) < best_dt:
                best, best_dt = int(order[k]), abs(int(rs[k]) - int(t))
        out[n] = best
    return out


def check_pairing(pairing: Pairing, n_static: int, n_dynamic: int, static_name: str, dynamic_name: str) -> None:
    """Log the pairing summary; raise a ValueError naming both streams if nothing paired.

    Args:
        pairing: the result of :func:`pair_timestamps`.
        n_static, n_dynamic: frame counts of the two streams.
        static_name, dynamic_name: how to name the streams in messages (folder, bag topic).
    """
    if n_static == 0 or n_dynamic == 0:
        empty = static_name if n_static == 0 else dynamic_name
        raise ValueError(f"{empty}: no frames")
    if not pairing.pairs:
        s0, s1 = pairing.unpaired_static[0], pairing.unpaired_static[-1]
        d0, d1 = pairing.unpaired_dynamic[0], pairing.unpaired_dynamic[-1]
        raise ValueError(
            f"timestamps never pair within {pairing.tolerance_ns} ns: {static_name} has {n_static} frames "
            f"in [{s0}, {s1}] ns, {dynamic_name} has {n_dynamic} frames in [{d0}, {d1}] ns "
            "(are the cameras hardware-synchronized? increase the pairing tolerance)"
        )
    if pairing.unpaired_static or pairing.unpaired_dynamic:
        log.warning("%s", pairing.summary(static_name, dynamic_name))
    else:
        log.info("%s", pairing.summary(static_name, dynamic_name))
