"""Calibration figures: reprojection residuals, per-snapshot errors, joint-space coverage, parameters.

Inputs are a :class:`dcc_fg.calibrate.CalibrationResult` (pixel residuals ``h(x) - z`` per snapshot
and camera; joint angles in radians; ``T_ds`` covariances in gtsam Pose3 tangent order
``[omega (rad), v (m)]``) and optionally the simulator's ground truth. Angles are drawn in degrees
(values) or milliradians (errors), lengths in millimetres.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Circle
from numpy.typing import NDArray

from dcc_fg.calibrate import CalibrationResult
from dcc_fg.data import CalibrationDataset
from dcc_fg.model import GimbalCalibration
from dcc_fg.plots.chain3d import chain_figure
from dcc_fg.plots.common import CAMERA_COLORS, new_figure
from dcc_fg.plots.residual_map import residual_grids, residual_map_figure
from dcc_fg.studies.calibration_accuracy import T_ds_errors, offset_free_joint_errors
from factors import chain

FloatArray = NDArray[np.float64]
CAMERAS = ("static", "dynamic")


def _residuals(result: CalibrationResult, camera: str) -> list[FloatArray]:
    return result.residuals_static if camera == "static" else result.residuals_dynamic


def noise_sigma(result: CalibrationResult, pixel_sigma: float | None = None) -> tuple[float, str]:
    """Pixel noise (1 sigma per axis) for the figures: given, the solver's, or estimated from the residuals.

    The estimate is the robust ``1.4826 * median(|r|)`` over both axes and cameras (the residuals have zero
    median at a least-squares solution), so a few outlier corners on real data do not inflate the circles.
    """
    if pixel_sigma is not None:
        return float(pixel_sigma), "given"
    if result.options.pixel_sigma is not None:
        return float(result.options.pixel_sigma), "solver setting"
    allr = np.concatenate(result.residuals_static + result.residuals_dynamic)
    return float(1.4826 * np.median(np.abs(allr))), "estimated: 1.4826 MAD"


def snapshot_rms(result: CalibrationResult, camera: str) -> FloatArray:
    """(K,) RMS per axis of the residuals of each snapshot in ``camera`` (pixels, NaN without corners)."""
    return np.array([np.sqrt(np.mean(r**2)) if len(r) else np.nan for r in _residuals(result, camera)])


def snapshot_rms_both(result: CalibrationResult) -> FloatArray:
    """(K,) RMS per axis of each snapshot over both cameras (pixels)."""
    out = []
    for rs, rd in zip(result.residuals_static, result.residuals_dynamic, strict=True):
        r = np.concatenate([rs, rd])
        out.append(np.sqrt(np.mean(r**2)) if len(r) else np.nan)
    return np.array(out)


def residual_figure(result: CalibrationResult, pixel_sigma: float | None = None) -> Figure:
    """Per camera: scatter of the pixel residuals (du, dv) with the 1/2/3-sigma circles, and their histogram.

    Top row: one scatter per camera (one point per corner) and three circles of radius k*sigma; the
    legend gives the fraction of corners inside each circle against a 2D Gaussian's 1 - exp(-k^2/2).
    Bottom row: histograms of du and dv with the N(0, sigma^2) density.
    """
    sigma, source = noise_sigma(result, pixel_sigma)
    fig = new_figure(10.0, 8.0)
    axes = fig.subplots(2, 2)
    for c, cam in enumerate(CAMERAS):
        res = _residuals(result, cam)
        r = np.concatenate(res) if res else np.zeros((0, 2))
        ax_s, ax_h = axes[0, c], axes[1, c]
        if r.shape[0] == 0:
            for ax in (ax_s, ax_h):
                ax.text(0.5, 0.5, f"no {cam} residuals", ha="center", va="center", transform=ax.transAxes)
            continue
        ax_s.scatter(
            r[:, 0], r[:, 1], s=3, alpha=0.35, color=CAMERA_COLORS[cam], linewidths=0, label="corners", rasterized=True
        )
        norms = np.linalg.norm(r, axis=1)
        for k, ls in zip((1, 2, 3), ("-", "--", ":"), strict=True):
            inside = float(np.mean(norms <= k * sigma))
            expected = 1.0 - np.exp(-0.5 * k * k)
            ax_s.add_patch(
                Circle(
                    (0.0, 0.0),
                    k * sigma,
                    fill=False,
                    color="k",
                    ls=ls,
                    lw=1.2,
                    label=f"{k}σ: {100 * inside:.1f}% inside (Gaussian {100 * expected:.1f}%)",
                )
            )
        lim = max(3.5 * sigma, float(np.percentile(np.abs(r), 99.5)))
        outside = int(np.sum(np.abs(r).max(axis=1) > lim))
        ax_s.set_xlim(-lim, lim)
        ax_s.set_ylim(-lim, lim)
        ax_s.set_aspect("equal")
        ax_s.set_xlabel("du (px)")
        ax_s.set_ylabel("dv (px)")
        title = f"{cam} camera: {r.shape[0]} corners, RMS/axis {np.sqrt(np.mean(r**2)):.3f} px"
        if outside:
            title += f"\n({outside} beyond the axes, largest |e| {norms.max():.2f} px)"
        ax_s.set_title(title)
        ax_s.legend(loc="upper right", fontsize=7, framealpha=0.85)
        bins = np.linspace(-lim, lim, 41)
        ax_h.hist(r[:, 0], bins=bins, density=True, histtype="step", lw=1.5, label="du")
        ax_h.hist(r[:, 1], bins=bins, density=True, histtype="step", lw=1.5, label="dv")
        x = np.linspace(-lim, lim, 200)
        ax_h.plot(x, np.exp(-0.5 * (x / sigma) ** 2) / (sigma * np.sqrt(2 * np.pi)), "k--", label=f"N(0, {sigma:.2f}²)")
        ax_h.set_xlim(-lim, lim)
        ax_h.set_xlabel("residual (px)")
        ax_h.set_ylabel("density")
        ax_h.set_title(f"{cam} camera: residual histogram")
        ax_h.legend(fontsize=8)
    fig.suptitle(f"Reprojection residuals h(x) - z (pixel noise σ = {sigma:.3f} px, {source})")
    return fig


def _tds_sigma(result: CalibrationResult) -> tuple[FloatArray, FloatArray] | None:
    cov = result.T_ds_covariances
    if cov is None:
        return None
    rot = np.sqrt(np.trace(cov[:, :3, :3], axis1=1, axis2=2))
    tra = np.sqrt(np.trace(cov[:, 3:, 3:], axis1=1, axis2=2))
    return rot, tra


def draw_snapshot_rms_panel(ax: Axes, result: CalibrationResult) -> None:
    """RMS per axis of each snapshot's residuals in each camera (pixels) and the pixel noise sigma."""
    idx = np.arange(len(result.joint_angles))
    for cam in CAMERAS:
        ax.plot(idx, snapshot_rms(result, cam), "o", ms=4, color=CAMERA_COLORS[cam], label=f"{cam} camera")
    sigma, source = noise_sigma(result)
    ax.axhline(sigma, color="k", ls="--", lw=1, label=f"σ = {sigma:.3f} px ({source})")
    ax.set_ylabel("RMS/axis (px)")
    ax.set_title("Reprojection residual per snapshot")
    ax.legend(fontsize=8, ncol=3, loc="upper right")
    ax.set_ylim(0, 1.35 * np.nanmax([*snapshot_rms(result, "static"), *snapshot_rms(result, "dynamic"), sigma]))


def draw_T_ds_error_panels(
    ax_rotation: Axes,
    ax_translation: Axes,
    T_ds_error: FloatArray | None,
    T_ds_sigma: tuple[FloatArray, FloatArray] | None,
) -> None:
    """Rotation (mrad) and translation (mm) error norms of ``T_ds(theta_i)`` per snapshot, and the reported 1 sigma.

    ``T_ds_error``: (K, 6) Pose3 tangent errors ``[omega, v]`` against the truth, or None;
    ``T_ds_sigma``: per snapshot ``sqrt(trace)`` of the rotation and translation covariance blocks, or None.
    """
    panels = (("rotation", slice(0, 3), 1e3, "mrad"), ("translation", slice(3, 6), 1e3, "mm"))
    for r, (ax, (name, sl, scale, unit)) in enumerate(zip((ax_rotation, ax_translation), panels, strict=True)):
        if T_ds_error is not None:
            e = np.linalg.norm(T_ds_error[:, sl], axis=1) * scale
            ax.plot(
                np.arange(len(e)),
                e,
                "o",
                ms=4,
                color="tab:green",
                label=f"|error| (RMS {np.sqrt(np.mean(e**2)):.3g} {unit})",
            )
        if T_ds_sigma is not None:
            s = T_ds_sigma[r] * scale
            ax.step(
                np.arange(len(s)),
                s,
                where="mid",
                color="k",
                lw=1,
                label=f"reported 1σ √tr Σ (RMS {np.sqrt(np.mean(s**2)):.3g})",
            )
        if T_ds_error is None and T_ds_sigma is None:
            ax.text(0.5, 0.5, "no ground truth and no covariance", ha="center", va="center", transform=ax.transAxes)
        ax.set_ylabel(f"{name} ({unit})")
        top = [np.max(e)] if T_ds_error is not None else []
        top += [np.max(T_ds_sigma[r] * scale)] if T_ds_sigma is not None else []
        ax.set_ylim(0, 1.35 * max(top) if top else 1.0)
        title = "error against ground truth" if T_ds_error is not None else "uncertainty"
        ax.set_title(f"T_ds(θ_i) {name} " + title)
        if T_ds_error is not None or T_ds_sigma is not None:
            ax.legend(fontsize=8, loc="upper right")


def draw_joint_error_panel(ax: Axes, result: CalibrationResult, thetas_true: FloatArray | None) -> None:
    """Offset-free joint-angle errors (mrad) with +-1 sigma error bars, or without ``thetas_true`` the 1 sigma."""
    L = result.calibration.n_joints
    idx = np.arange(len(result.joint_angles))
    std = result.joint_angle_std
    if thetas_true is not None:
        je = offset_free_joint_errors(thetas_true, result.joint_angles) * 1e3
        for j in range(L):
            ax.errorbar(
                idx + (j - (L - 1) / 2) * 0.15,
                je[:, j],
                yerr=std[:, j] * 1e3,
                fmt="o",
                ms=3,
                capsize=2,
                lw=0.8,
                label=f"θ_{j + 1} (RMS {np.sqrt(np.mean(je[:, j] ** 2)):.3g} mrad)",
            )
        ax.axhline(0.0, color="k", lw=0.8)
        span = float(np.nanmax(np.abs(je) + np.nan_to_num(std) * 1e3))
        ax.set_ylim(-1.1 * span, 1.5 * span)
        ax.set_title("Joint-angle error (constant offset per joint removed) ± reported 1σ")
    else:
        for j in range(L):
            ax.plot(idx, std[:, j] * 1e3, "o", ms=3, label=f"θ_{j + 1}")
        ax.set_title("Joint-angle reported 1σ")
        ax.set_ylim(bottom=0)
    ax.set_ylabel("mrad")
    ax.legend(fontsize=8, ncol=min(L, 3), loc="upper right")


def snapshot_error_figure(
    result: CalibrationResult,
    truth: GimbalCalibration | None = None,
    thetas_true: FloatArray | None = None,
) -> Figure:
    """Per snapshot: RMS residual per camera, T_ds rotation/translation error and joint-angle error.

    Rows: (1) RMS per axis of each snapshot's residuals in each camera (pixels); (2) rotation and
    (3) translation error of ``T_ds(theta_i)`` against the truth (norm of the Pose3 tangent error,
    mrad / mm), with the tool's reported 1-sigma ``sqrt(trace(Sigma))`` as a line (for a consistent
    estimator ``E|e|^2 = trace(Sigma)``); without truth only the reported 1-sigma is drawn;
    (4) offset-free joint-angle errors with +-1 sigma error bars (or, without truth, the 1-sigma).
    """
    have_truth = truth is not None and thetas_true is not None
    L = result.calibration.n_joints
    rows = 3 + (1 if L > 0 else 0)
    fig = new_figure(10.0, 2.4 * rows + 0.6)
    axes = fig.subplots(rows, 1, sharex=True)
    draw_snapshot_rms_panel(axes[0], result)
    err = T_ds_errors(truth, thetas_true, result.calibration, result.joint_angles) if have_truth else None
    draw_T_ds_error_panels(axes[1], axes[2], err, _tds_sigma(result))
    if L > 0:
        draw_joint_error_panel(axes[3], result, thetas_true if have_truth else None)
    axes[-1].set_xlabel("snapshot")
    return fig


def coverage_figure(result: CalibrationResult, joint_angles: FloatArray | None = None) -> Figure:
    """Which part of the joint space the snapshots cover, coloured by each snapshot's RMS residual.

    L = 1: histogram of theta_1 above the snapshots' RMS residual against theta_1; L = 2: theta_1 vs
    theta_2; L >= 3: one panel per pair of joints. Angles in degrees.
    """
    th = np.degrees(result.joint_angles if joint_angles is None else np.asarray(joint_angles, float))
    L = th.shape[1] if th.ndim == 2 else 0
    rms = snapshot_rms_both(result)
    if L == 0:
        fig = new_figure(5.0, 1.2)
        ax = fig.add_subplot()
        ax.text(0.5, 0.5, "L = 0: rigid pair, no joint space", ha="center", va="center", fontsize=12)
        ax.set_axis_off()
        return fig
    norm_kw = {"cmap": "viridis", "vmin": float(np.nanmin(rms)), "vmax": float(np.nanmax(rms))}
    if L == 1:
        fig = new_figure(7.5, 5.5)
        ax_h, ax_s = fig.subplots(2, 1, sharex=True, height_ratios=[2, 1.4])
        ax_h.hist(th[:, 0], bins=min(30, max(5, len(th) // 3)), color="0.8", edgecolor="0.4")
        ax_h.set_ylabel("snapshots")
        sc = ax_s.scatter(th[:, 0], rms, c=rms, s=25, edgecolors="k", linewidths=0.3, **norm_kw)
        ax_s.set_ylabel("RMS/axis (px)")
        ax_s.set_xlabel("θ_1 (deg)")
        ax_s.grid(alpha=0.3)
        fig.colorbar(sc, ax=[ax_h, ax_s], label="RMS/axis residual (px)")
        fig.suptitle(f"Joint-space coverage: {len(th)} snapshots")
        return fig
    pairs = [(i, j) for i in range(L) for j in range(i + 1, L)]
    ncol = min(3, len(pairs))
    nrow = int(np.ceil(len(pairs) / ncol))
    fig = new_figure(4.2 * ncol + 1.0, 4.0 * nrow)
    axes = np.atleast_1d(fig.subplots(nrow, ncol, squeeze=False)).ravel()
    sc = None
    for ax, (i, j) in zip(axes, pairs, strict=False):
        sc = ax.scatter(th[:, i], th[:, j], c=rms, s=25, edgecolors="k", linewidths=0.3, **norm_kw)
        ax.set_xlabel(f"θ_{i + 1} (deg)")
        ax.set_ylabel(f"θ_{j + 1} (deg)")
        ax.grid(alpha=0.3)
    for ax in axes[len(pairs) :]:
        fig.delaxes(ax)
    fig.colorbar(sc, ax=list(axes[: len(pairs)]), label="RMS/axis residual (px)")
    fig.suptitle(f"Joint-space coverage: {len(th)} snapshots")
    return fig


def _wrap(x: FloatArray) -> FloatArray:
    return np.arctan2(np.sin(x), np.cos(x))


def parameter_status(cal: GimbalCalibration) -> list[str]:
    """Per kinematic parameter: ``gauge-fixed``, ``observable`` or ``unobservable``."""
    n = len(cal.kin)
    gauge = cal.gauge_fixed if cal.gauge_fixed is not None else np.zeros(n, bool)
    obs = cal.observable if cal.observable is not None else np.ones(n, bool)
    return ["gauge-fixed" if g else ("observable" if o else "unobservable") for g, o in zip(gauge, obs, strict=True)]


STATUS_LABEL = {
    "observable": "observable",
    "gauge-fixed": "gauge-fixed (held)",
    "unobservable": "unobservable (gauge-dependent)",
}
STATUS_STYLE = {
    "observable": {"fmt": "o", "color": "tab:blue"},
    "gauge-fixed": {"fmt": "s", "color": "0.5"},
    "unobservable": {"fmt": "^", "color": "tab:red"},
}


@dataclass(frozen=True)
class ParameterGroup:
    """One row of :func:`parameter_figure`: the angles or the lengths among the kinematic parameters.

    ``to_display`` converts values (rad or m) to ``unit`` (deg or mm); errors are multiplied by
    ``error_scale`` to ``error_unit`` (mrad or mm).
    """

    name: str
    indices: NDArray[np.int64]
    to_display: Callable[[FloatArray], FloatArray]
    unit: str
    error_scale: float
    error_unit: str


def parameter_groups(cal: GimbalCalibration) -> list[ParameterGroup]:
    """The angle and the length parameters of ``cal`` (indices into ``cal.kin``)."""
    is_angle = chain.kin_is_angle(cal.n_joints)
    return [
        ParameterGroup("angles", np.flatnonzero(is_angle), np.degrees, "deg", 1e3, "mrad"),
        ParameterGroup("lengths", np.flatnonzero(~is_angle), lambda v: v * 1e3, "mm", 1e3, "mm"),
    ]


def draw_parameter_markers(
    ax_value: Axes,
    ax_error: Axes,
    cal: GimbalCalibration,
    truth: GimbalCalibration | None,
    group: ParameterGroup,
    status: list[str],
    std: FloatArray,
) -> None:
    """Per observability status: values +-1 sigma (left), estimate - truth +-1 sigma or the 1 sigma (right)."""
    sel = group.indices
    y = np.arange(len(sel))[::-1]
    for st, style in STATUS_STYLE.items():
        m = np.array([status[k] == st for k in sel], dtype=bool)
        if not m.any():
            continue
        k = sel[m]
        val = group.to_display(cal.kin[k])
        err = np.where(np.isfinite(std[k]), group.to_display(np.nan_to_num(std[k])), 0.0)
        ax_value.errorbar(
            val, y[m], xerr=err, fmt=style["fmt"], color=style["color"], ms=5, capsize=3, label=STATUS_LABEL[st]
        )
        if truth is not None:
            d = cal.kin[k] - truth.kin[k]
            d = _wrap(d) if group.unit == "deg" else d
            ax_error.errorbar(
                d * group.error_scale,
                y[m],
                xerr=np.nan_to_num(std[k]) * group.error_scale,
                fmt=style["fmt"],
                color=style["color"],
                ms=5,
                capsize=3,
                label=STATUS_LABEL[st],
            )
        else:
            s = np.where(np.isfinite(std[k]), std[k] * group.error_scale, 0.0)
            ax_error.errorbar(s, y[m], fmt=style["fmt"], color=style["color"], ms=5, label=STATUS_LABEL[st])


def annotate_parameter_errors(
    ax_error: Axes, truth: GimbalCalibration | None, group: ParameterGroup, status: list[str], std: FloatArray
) -> None:
    """Error axis: a note when no parameter has a 1 sigma; with the truth a symlog scale and the zero line."""
    sel = group.indices
    obs_std = np.array([std[k] for k in sel if status[k] == "observable" and np.isfinite(std[k])])
    if not np.isfinite(std[sel]).any():
        ax_error.text(
            0.5,
            0.5,
            "no 1σ reported: every parameter here is gauge-fixed or\nmixes with a gauge direction "
            "(see the T_ds uncertainty instead)",
            ha="center",
            va="center",
            fontsize=8,
            transform=ax_error.transAxes,
            bbox={"facecolor": "white", "alpha": 0.85, "edgecolor": "0.7"},
        )
    if truth is not None:
        # gauge-fixed / unobservable errors can be orders of magnitude larger than the observable ones:
        # linear inside +-4 sigma of the observable parameters, logarithmic outside
        lin = 4.0 * float(obs_std.max()) * group.error_scale if obs_std.size else 1.0
        ax_error.set_xscale("symlog", linthresh=lin, linscale=2.0)
        ax_error.axvspan(-lin, lin, color="0.93", zorder=0)
        ax_error.axvline(0.0, color="k", lw=0.8)
        ax_error.set_xlabel(f"estimate - truth ({group.error_unit}), ±1σ")
    else:
        ax_error.set_xlabel(f"reported 1σ ({group.error_unit}; 0 = not estimated)")


def parameter_figure(cal: GimbalCalibration, truth: GimbalCalibration | None = None) -> Figure:
    """Kinematic parameter estimates with their 1-sigma, by observability status, and the truth when known.

    Left column: values (angles in degrees, lengths in mm) with +-1 sigma error bars; the truth as
    black crosses. Right column: estimate - truth (mrad / mm) with +-1 sigma error bars when the truth
    is given, otherwise the reported 1 sigma. Marker: circle observable, square gauge-fixed (held at
    its initial value), triangle unobservable (no standard deviation).
    """
    status = parameter_status(cal)
    std = cal.kin_std if cal.kin_std is not None else np.full(len(cal.kin), np.nan)
    groups = parameter_groups(cal)
    n_max = max(len(g.indices) for g in groups)
    fig = new_figure(11.0, 0.28 * n_max * 2 + 2.0)
    axes = fig.subplots(2, 2, gridspec_kw={"height_ratios": [len(g.indices) for g in groups]})
    for r, group in enumerate(groups):
        ax_v, ax_d = axes[r, 0], axes[r, 1]
        y = np.arange(len(group.indices))[::-1]
        draw_parameter_markers(ax_v, ax_d, cal, truth, group, status, std)
        annotate_parameter_errors(ax_d, truth, group, status, std)
        if truth is not None:
            ax_v.plot(group.to_display(truth.kin[group.indices]), y, "x", color="k", ms=7, label="truth")
        for ax in (ax_v, ax_d):
            ax.set_yticks(y, [cal.names[k] for k in group.indices], fontsize=8)
            ax.grid(axis="x", alpha=0.3)
        ax_v.set_xlabel(f"value ({group.unit}), ±1σ")
        ax_v.set_title(f"{group.name}")
        ax_d.set_title(f"{group.name}: " + ("error against truth" if truth is not None else "standard deviation"))
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=len(labels), fontsize=8)
    fig.suptitle("Kinematic parameters (circle observable, square gauge-fixed, triangle unobservable)")
    return fig


def calibration_figures(
    result: CalibrationResult,
    truth: GimbalCalibration | None = None,
    thetas_true: FloatArray | None = None,
    theta: Sequence[float] | None = None,
    target_points: FloatArray | None = None,
    data: CalibrationDataset | None = None,
) -> dict[str, Figure]:
    """All calibration figures by file stem: residuals, (with ``data``) residual_map, snapshot_errors,
    coverage, parameters, chain.

    The chain sketch uses ``theta`` (default: the snapshot whose joint angles are nearest the middle
    of the estimated range) and draws the target of that snapshot when ``target_points`` (target frame,
    metres) are given. ``data`` is the dataset ``result`` was computed from: its detected corner
    positions place the residuals over each camera's image (:mod:`dcc_fg.plots.residual_map`).
    """
    L = result.calibration.n_joints
    i_snap = 0
    if theta is None and L > 0 and len(result.joint_angles):
        mid = np.median(result.joint_angles, axis=0)
        i_snap = int(np.argmin(np.linalg.norm(result.joint_angles - mid, axis=1)))
        theta = result.joint_angles[i_snap]
    elif theta is None:
        theta = np.zeros(L)
    T_st = result.T_st[i_snap] if (target_points is not None and len(result.T_st)) else None
    figures = {"residuals": residual_figure(result)}
    if data is not None:
        figures["residual_map"] = residual_map_figure(residual_grids(result, data))
    return figures | {
        "snapshot_errors": snapshot_error_figure(result, truth, thetas_true),
        "coverage": coverage_figure(result),
        "parameters": parameter_figure(result.calibration, truth),
        "chain": chain_figure(result.calibration, np.asarray(theta, float), T_st=T_st, target_points=target_points),
    }
