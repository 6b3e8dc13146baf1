"""Figure of the predicted ``T_ds`` accuracy over the operating range (:mod:`dcc_fg.planning.predict`).

* L = 1: 1-sigma (rotation mrad, translation mm) against theta_1 for the three predictions;
* L = 2: heat maps over (theta_1, theta_2), rotation and translation, one row per prediction mode;
* L = 3: heat maps over (theta_1, theta_2) at three slices of theta_3 (its lower limit, middle and
  upper limit), rotation and translation, for one prediction mode.

Angles in degrees (the calibration's joint-angle convention). The calibration's snapshots (white
dots) and planned snapshots (red crosses) are drawn where given; grey cells have no view of the
target both cameras share (the snapshot prediction is undefined there).
"""

from __future__ import annotations

import matplotlib
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from numpy.typing import NDArray

from dcc_fg.planning.predict import RangeAccuracy
from dcc_fg.plots.common import new_figure

FloatArray = NDArray[np.float64]
MODE_TITLES = {
    "snapshot": "snapshot there (theta from its images)",
    "calibration": "calibration's share at a snapshot",
    "kinematics": "kinematics alone (theta known)",
}
QUANTITIES = (("rotation", "mrad"), ("translation", "mm"))


def _values(acc: RangeAccuracy, mode: str) -> tuple[FloatArray, FloatArray]:
    rot, tra = acc.prediction.sigmas(mode)
    return rot * 1e3, tra * 1e3


def _heat(
    fig: Figure,
    ax: Axes,
    x: FloatArray,
    y: FloatArray,
    z: FloatArray,
    title: str,
    unit: str,
    labels: tuple[str, str],
    vmax: float | None = None,
) -> None:
    """One heat map of z (len(x), len(y)) over degrees x, y: cells without a prediction (no shared view)
    grey; outside the operating range (where data snapshots may still be drawn) the axes stay white."""
    masked = np.ma.masked_invalid(z.T)
    top = vmax if vmax is not None and np.isfinite(vmax) else None
    cmap = matplotlib.colormaps["magma_r"].with_extremes(bad="0.75")
    mesh = ax.pcolormesh(np.degrees(x), np.degrees(y), masked, shading="nearest", cmap=cmap, vmin=0.0, vmax=top)
    fig.colorbar(mesh, ax=ax, label=f"1-sigma ({unit})")
    ax.set_xlabel(labels[0])
    ax.set_ylabel(labels[1])
    ax.set_title(title, fontsize=9)


def _overlay(ax: Axes, pts: FloatArray | None, i: int, j: int, style: str) -> None:
    if pts is None or len(pts) == 0:
        return
    p = np.degrees(np.asarray(pts, float))
    if style == "data":
        ax.scatter(p[:, i], p[:, j], s=12, c="white", edgecolors="k", linewidths=0.4, label="snapshots")
    else:
        ax.scatter(p[:, i], p[:, j], s=40, c="tab:red", marker="x", linewidths=1.5, label="planned")


def accuracy_figure(
    acc: RangeAccuracy,
    data_angles: FloatArray | None = None,
    planned: FloatArray | None = None,
    mode: str = "snapshot",
) -> Figure:
    """The predicted accuracy figure (module docstring); ``mode`` selects the prediction of the L = 3
    slices (L = 1 and 2 show the snapshot and kinematics predictions; L = 1 also the calibration's share)."""
    pred = acc.prediction
    L = pred.thetas.shape[1]
    if L == 1:
        fig = new_figure(8.0, 5.5)
        axes = fig.subplots(2, 1, sharex=True)
        x = np.degrees(pred.thetas[:, 0])
        for m, style in (("snapshot", "-"), ("calibration", "--"), ("kinematics", ":")):
            vals = _values(acc, m)
            for ax, v in zip(axes, vals, strict=True):
                ax.plot(x, v, style, label=MODE_TITLES[m])
        for ax, (q, unit) in zip(axes, QUANTITIES, strict=True):
            ax.set_ylabel(f"{q} 1-sigma ({unit})")
            ax.grid(alpha=0.3)
            ax.set_ylim(bottom=0.0)
            if data_angles is not None:
                for t in np.degrees(np.asarray(data_angles, float)[:, 0]):
                    ax.axvline(t, color="0.6", lw=0.5, alpha=0.5)
            if planned is not None:
                for t in np.degrees(np.asarray(planned, float)[:, 0]):
                    ax.axvline(t, color="tab:red", lw=1.2)
        axes[0].legend(fontsize=8)
        axes[1].set_xlabel("θ_1 (deg)")
        fig.suptitle("Predicted T_ds accuracy over the operating range (grey lines: snapshots; red: planned)")
        return fig
    if L == 2:
        modes = ("snapshot", "kinematics")
        fig = new_figure(10.0, 8.0)
        axes = fig.subplots(2, 2, squeeze=False)
        n0, n1 = len(acc.axes[0]), len(acc.axes[1])
        for r, m in enumerate(modes):
            for c, ((q, unit), v) in enumerate(zip(QUANTITIES, _values(acc, m), strict=True)):
                ax = axes[r, c]
                _heat(fig, ax, acc.axes[0], acc.axes[1], v.reshape(n0, n1), f"{q}: {MODE_TITLES[m]}", unit,
                      ("θ_1 (deg)", "θ_2 (deg)"))  # fmt: skip
                _overlay(ax, data_angles, 0, 1, "data")
                _overlay(ax, planned, 0, 1, "planned")
        fig.suptitle("Predicted T_ds 1-sigma over the operating range (grey: no shared view)")
        return fig
    # L >= 3: slices over the last joint, maps over the first two (other joints at their middle)
    n = [len(a) for a in acc.axes]
    fig = new_figure(13.0, 7.5)
    axes = fig.subplots(2, 3, squeeze=False)
    rot, tra = _values(acc, mode)
    cubes = [v.reshape(n) for v in (rot, tra)]
    last = L - 1
    picks = [0, n[last] // 2, n[last] - 1]
    for r, ((q, unit), cube) in enumerate(zip(QUANTITIES, cubes, strict=True)):
        vmax = float(np.nanmax(cube)) if np.isfinite(cube).any() else None
        for c, k in enumerate(picks):
            index: list[int | slice] = [slice(None), slice(None)] + [n[j] // 2 for j in range(2, L)]
            index[last] = k
            z = cube[tuple(index)]
            at = np.degrees(acc.axes[last][k])
            _heat(fig, axes[r, c], acc.axes[0], acc.axes[1], z, f"{q}, θ_{L} = {at:.1f} deg", unit,
                  ("θ_1 (deg)", "θ_2 (deg)"), vmax)  # fmt: skip
            if r == 0 and c == 0:
                _overlay(axes[r, c], data_angles, 0, 1, "data")
                _overlay(axes[r, c], planned, 0, 1, "planned")
    fig.suptitle(f"Predicted T_ds 1-sigma, {MODE_TITLES[mode]} (grey: no shared view; snapshots of all θ_{L} "
                 "shown in the first panel)")  # fmt: skip
    return fig
