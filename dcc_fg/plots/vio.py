"""VIO figures on plain numpy arrays: top-view trajectories, joint angles over time, error over distance.

Positions are (N, 3) (or (N, 2)) in metres in the ground truth's world frame W; the caller aligns
the estimates (e.g. with evo's Umeyama alignment) and associates them in time. Joint angles (and
their optional per-keyframe 1-sigma, drawn as a shaded band) are in radians and drawn in degrees;
times in seconds.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from matplotlib.figure import Figure
from numpy.typing import NDArray

from dcc_fg.plots.common import new_figure
from dcc_fg.plots.joint_band import band_mask, draw_sigma_band

FloatArray = NDArray[np.float64]
MIN_HALF_SPAN_DEG = 1.0  # joint-angle panels span at least +-1 deg around a (near-)constant series


def _positions(p: FloatArray, what: str) -> FloatArray:
    p = np.asarray(p, dtype=float)
    if p.ndim != 2 or p.shape[1] not in (2, 3) or p.shape[0] < 1:
        raise ValueError(f"{what}: positions must be (N, 2) or (N, 3) with N >= 1, got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{what}: positions contain NaN or inf")
    return p


def distance_travelled(p: FloatArray) -> FloatArray:
    """(N,) cumulative path length along the positions (m), starting at 0."""
    p = _positions(p, "distance_travelled")
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])


def trajectory_topview_figure(
    ground_truth: FloatArray | None, estimates: Mapping[str, FloatArray], title: str = "Trajectory (top view)"
) -> Figure:
    """x-y view of the ground truth (black) and each estimate, with start (circle) and end (square) markers."""
    fig = new_figure(7.0, 6.5)
    ax = fig.add_subplot()
    curves = ({"ground truth": ground_truth} if ground_truth is not None else {}) | dict(estimates)
    if not curves:
        raise ValueError("trajectory_topview_figure: nothing to draw (no ground truth and no estimates)")
    for name, p in curves.items():
        p = _positions(p, name)
        style = {"color": "k", "lw": 2.0} if name == "ground truth" else {"lw": 1.3}
        (line,) = ax.plot(p[:, 0], p[:, 1], label=name, **style)
        ax.plot(p[-1, 0], p[-1, 1], "s", color=line.get_color(), ms=7, mfc="none")
    p0 = _positions(next(iter(curves.values())), "start")[0]
    # white with a black edge, so the start never takes the colour of an estimate's line
    ax.plot(p0[0], p0[1], "o", mfc="white", mec="k", mew=1.5, ms=9, zorder=5, label="start")
    ax.plot([], [], "s", color="k", mfc="none", label="end")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    ax.set_title(title)
    return fig


def joint_angles_figure(
    t: FloatArray,
    ground_truth: FloatArray | None,
    estimates: Mapping[str, FloatArray | tuple[FloatArray, FloatArray]],
    sigmas: Mapping[str, FloatArray] | None = None,
) -> Figure:
    """One panel per joint: angle (deg) over time (s), ground truth in black and each estimate.

    ``ground_truth`` is (N, L) sampled at ``t``; each estimate is either (N, L) at ``t`` or a pair
    ``(t_est, theta_est)``. ``sigmas`` maps estimate names to their (N, L) 1-sigma (rad, NaN where not
    reported): a shaded band ``theta ± sigma`` in the estimate's colour, drawn only where a sigma exists
    (:func:`dcc_fg.plots.joint_band.draw_sigma_band`).
    """
    t = np.asarray(t, dtype=float)
    series: dict[str, tuple[FloatArray, FloatArray]] = {}
    if ground_truth is not None:
        series["ground truth"] = (t, np.asarray(ground_truth, float))
    for name, e in estimates.items():
        series[name] = (
            (np.asarray(e[0], float), np.asarray(e[1], float)) if isinstance(e, tuple) else (t, np.asarray(e, float))
        )
    if not series:
        raise ValueError("joint_angles_figure: nothing to draw")
    Ls = {th.shape[1] if th.ndim == 2 else -1 for _, th in series.values()}
    for name, (ts, th) in series.items():
        if th.ndim != 2 or th.shape[0] != ts.shape[0]:
            raise ValueError(
                f"joint_angles_figure: {name} must be (N, L) with N = len(t), got {th.shape} vs {ts.shape}"
            )
    if len(Ls) != 1 or Ls == {0}:
        raise ValueError(f"joint_angles_figure: all series need the same number of joints L >= 1, got {sorted(Ls)}")
    L = Ls.pop()
    bands = _band_sigmas(series, sigmas or {})
    fig = new_figure(9.0, 2.3 * L + 0.8)
    axes = np.atleast_1d(fig.subplots(L, 1, sharex=True, squeeze=False)).ravel()
    for j, ax in enumerate(axes):
        band_deg = []
        for name, (ts, th) in series.items():
            style = {"color": "k", "lw": 2.0} if name == "ground truth" else {"lw": 1.2}
            (line,) = ax.plot(ts, np.degrees(th[:, j]), label=name, **style)
            if name in bands:
                sig = bands[name][:, j]
                if draw_sigma_band(ax, ts, th[:, j], sig, color=line.get_color(), label=f"{name} ±1σ") is not None:
                    ok = band_mask(th[:, j], sig)
                    band_deg += [np.degrees(th[ok, j] - sig[ok]), np.degrees(th[ok, j] + sig[ok])]
        # a locked joint (scc) is constant: show it on a readable span instead of an offset axis of 1e-10 deg
        deg = np.concatenate([np.degrees(th[:, j]) for _, th in series.values()] + band_deg)
        lo, hi = float(deg.min()), float(deg.max())
        if hi - lo < 2.0 * MIN_HALF_SPAN_DEG:
            mid = 0.5 * (lo + hi)
            ax.set_ylim(mid - MIN_HALF_SPAN_DEG, mid + MIN_HALF_SPAN_DEG)
        ax.ticklabel_format(axis="y", useOffset=False)
        ax.set_ylabel(f"θ_{j + 1} (deg)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, loc="best", ncol=len(series))
    axes[-1].set_xlabel("time (s)")
    fig.suptitle("Joint angles over time")
    return fig


def _band_sigmas(
    series: Mapping[str, tuple[FloatArray, FloatArray]], sigmas: Mapping[str, FloatArray]
) -> dict[str, FloatArray]:
    """The sigmas (rad) of :func:`joint_angles_figure` checked against their estimates' shapes."""
    out = {}
    for name, sig in sigmas.items():
        if name not in series or name == "ground truth":
            raise ValueError(f"joint_angles_figure: sigmas for '{name}', which is not one of the estimates")
        sig = np.asarray(sig, float)
        if sig.shape != series[name][1].shape:
            raise ValueError(
                f"joint_angles_figure: sigmas of {name} have shape {sig.shape}, its angles {series[name][1].shape}"
            )
        out[name] = sig
    return out


def error_over_distance_figure(ground_truth: FloatArray, estimates: Mapping[str, FloatArray]) -> Figure:
    """Translation error |p_est - p_gt| (m) against the distance travelled along the ground truth (m)."""
    gt = _positions(ground_truth, "ground truth")
    if not estimates:
        raise ValueError("error_over_distance_figure: no estimates")
    dist = distance_travelled(gt)
    fig = new_figure(8.0, 4.5)
    ax = fig.add_subplot()
    for name, p in estimates.items():
        p = _positions(p, name)
        if p.shape != gt.shape:
            raise ValueError(f"error_over_distance_figure: {name} has shape {p.shape}, ground truth {gt.shape}")
        e = np.linalg.norm(p - gt, axis=1)
        pct = 100 * e[-1] / max(dist[-1], 1e-9)
        ax.plot(dist, e, lw=1.3, label=f"{name} (final error {e[-1]:.3g} m = {pct:.2g}% of {dist[-1]:.3g} m)")
    ax.set_xlabel("distance travelled (m)")
    ax.set_ylabel("translation error (m)")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title("Translation error over distance travelled")
    return fig
