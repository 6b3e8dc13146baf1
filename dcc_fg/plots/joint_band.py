"""Joint-angle 1-sigma bands of a VIO run: the band itself, its file, and the error-against-band figure.

Joint angles ``theta`` and their 1-sigma ``sigma`` are (N, L) in radians per keyframe (sigma NaN where
the run reported none); they are drawn in degrees over time in seconds. A band is drawn only where a
finite, non-negative sigma exists, so a run that reports sigmas for some keyframes only (or none) gets a
band exactly there.

File (read here, written by a VIO run that reports the marginals): ``OUT/joint_angles_sigma.csv`` with
the header ``timestamp_ns,sigma_theta_1,...,sigma_theta_L`` (integer nanoseconds, the keyframe stamps
of ``joint_angles.csv``; radians; ``nan`` for a keyframe without a sigma). ``joint_angles.csv`` itself
keeps its ``timestamp_ns,theta_1..theta_L`` columns, which other readers (``dcc-fg export``) check.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure
from numpy.typing import NDArray

from dcc_fg.plots.common import new_figure

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
SIGMA_FILE = "joint_angles_sigma.csv"
SIGMA_PREFIX = "sigma_theta_"
BAND_ALPHA = 0.25


def band_mask(theta: FloatArray, sigma: FloatArray) -> NDArray[np.bool_]:
    """True where a band can be drawn: finite angle and finite, non-negative sigma (same shapes)."""
    return np.isfinite(theta) & np.isfinite(sigma) & (np.nan_to_num(sigma, nan=-1.0, posinf=-1.0) >= 0.0)


def draw_sigma_band(
    ax: Axes,
    t: FloatArray,
    theta: FloatArray,
    sigma: FloatArray,
    color: str | tuple[float, ...] | None = None,
    label: str | None = None,
    center: FloatArray | None = None,
) -> PolyCollection | None:
    """Shade ``[theta - sigma, theta + sigma]`` (radians in, degrees drawn) over ``t`` (seconds) where
    :func:`band_mask` holds; one polygon per run of keyframes with a sigma. ``center`` (radians,
    default ``theta``) moves the band, e.g. to zero for an error plot. Returns the collection, or None
    when no keyframe has a sigma (nothing drawn)."""
    t = np.asarray(t, float)
    theta = np.asarray(theta, float)
    sigma = np.asarray(sigma, float)
    if not (t.shape == theta.shape == sigma.shape) or t.ndim != 1:
        raise ValueError(
            f"draw_sigma_band: t, theta and sigma must be (N,) alike, got {t.shape}, {theta.shape}, {sigma.shape}"
        )
    c = theta if center is None else np.asarray(center, float)
    ok = band_mask(c, sigma)
    if not ok.any():
        return None
    s = np.where(ok, sigma, 0.0)
    mid = np.where(ok, c, 0.0)
    return ax.fill_between(
        t,
        np.degrees(mid - s),
        np.degrees(mid + s),
        where=ok,
        interpolate=False,
        color=color,
        alpha=BAND_ALPHA,
        linewidth=0.0,
        label=label,
    )


def read_joint_sigmas_csv(path: str | Path) -> tuple[IntArray, FloatArray]:
    """``(timestamps_ns (N,), sigma (N, L) rad)`` from a ``joint_angles_sigma.csv`` (module docstring);
    ``nan`` entries stay NaN. Raises ValueError naming the file and line for a bad header, a value that
    is not a number or a negative sigma."""
    path = Path(path)
    lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
    if not lines:
        raise ValueError(f"{path}: empty; expected a header 'timestamp_ns,{SIGMA_PREFIX}1,...'")
    header = [h.strip() for h in lines[0].split(",")]
    want = ["timestamp_ns"] + [f"{SIGMA_PREFIX}{j + 1}" for j in range(len(header) - 1)]
    if header != want or len(header) < 2:
        raise ValueError(f"{path}:1: columns {','.join(header)}; expected {','.join(want[:2])},... (radians)")
    stamps: list[int] = []
    rows: list[list[float]] = []
    for k, ln in enumerate(lines[1:], start=2):
        first, *rest = ln.split(",")
        try:
            stamps.append(int(first))
            row = [float(x) for x in rest]
        except ValueError:
            raise ValueError(f"{path}:{k}: not a number in '{ln}'") from None
        if len(row) != len(header) - 1:
            raise ValueError(f"{path}:{k}: {len(row)} sigmas, the header names {len(header) - 1}")
        if any(x < 0 or np.isinf(x) for x in row):
            raise ValueError(f"{path}:{k}: a sigma must be a finite non-negative number of radians or nan, got '{ln}'")
        rows.append(row)
    return np.array(stamps, dtype=np.int64), np.array(rows, dtype=float).reshape(len(rows), len(header) - 1)


def sigmas_at(stamps_ns: IntArray, sigma_stamps_ns: IntArray, sigma: FloatArray, n_joints: int) -> FloatArray:
    """(N, n_joints) sigma (rad) of each keyframe stamp in ``stamps_ns``: the row with the same stamp
    (exact integer match), NaN for keyframes without one. Raises ValueError on a joint-count mismatch."""
    sigma = np.asarray(sigma, float).reshape(len(sigma_stamps_ns), -1)
    if sigma.shape[1] != n_joints:
        raise ValueError(f"joint sigmas have {sigma.shape[1]} joints, the joint angles {n_joints}")
    out = np.full((len(stamps_ns), n_joints), np.nan)
    order = np.argsort(sigma_stamps_ns, kind="stable")
    sorted_stamps = np.asarray(sigma_stamps_ns, np.int64)[order]
    pos = np.clip(np.searchsorted(sorted_stamps, stamps_ns), 0, max(len(sorted_stamps) - 1, 0))
    if len(sorted_stamps):
        hit = sorted_stamps[pos] == stamps_ns
        out[hit] = sigma[order[pos[hit]]]
    return out


def joint_error_band_figure(t: FloatArray, error: FloatArray, sigma: FloatArray, name: str = "estimate") -> Figure:
    """One panel per joint: ``estimate - ground truth`` (deg) over time (s) and the ±1-sigma band around
    zero; the legend gives the fraction of keyframes (with a sigma) whose error lies inside the band
    against a Gaussian's 68.3%. ``error`` and ``sigma`` are (N, L) radians at the times ``t`` (N,)."""
    t = np.asarray(t, float)
    error = np.asarray(error, float)
    sigma = np.asarray(sigma, float)
    if error.ndim != 2 or error.shape != sigma.shape or error.shape[0] != t.shape[0] or error.shape[1] < 1:
        raise ValueError(
            f"joint_error_band_figure: error and sigma must be (N, L >= 1) with N = len(t), got {error.shape}, "
            f"{sigma.shape}, {t.shape}"
        )
    L = error.shape[1]
    fig = new_figure(9.0, 2.3 * L + 0.8)
    axes = np.atleast_1d(fig.subplots(L, 1, sharex=True, squeeze=False)).ravel()
    for j, ax in enumerate(axes):
        ok = band_mask(error[:, j], sigma[:, j])
        inside = float(np.mean(np.abs(error[ok, j]) <= sigma[ok, j])) if ok.any() else float("nan")
        label = f"±1σ ({100 * inside:.0f}% of {int(ok.sum())} keyframes inside; Gaussian 68%)" if ok.any() else None
        draw_sigma_band(ax, t, error[:, j], sigma[:, j], color="tab:blue", label=label, center=np.zeros_like(t))
        ax.plot(t, np.degrees(error[:, j]), color="tab:blue", lw=1.0, label=f"{name} - ground truth")
        ax.axhline(0.0, color="k", lw=0.8)
        if not ok.any():
            ax.text(0.5, 0.9, "no 1σ reported", ha="center", va="top", transform=ax.transAxes, fontsize=8)
        ax.ticklabel_format(axis="y", useOffset=False)
        ax.set_ylabel(f"θ_{j + 1} error (deg)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper right")
    axes[-1].set_xlabel("time (s)")
    fig.suptitle("Joint-angle error against the ground truth, with the reported ±1σ")
    return fig
