"""Text summary tables, and the figures of :mod:`dcc_fg.plots` re-exported so callers find them with the tables."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from dcc_fg.model import GimbalCalibration
from dcc_fg.plots import (
    calibration_figures,
    chain_figure,
    coverage_figure,
    error_over_distance_figure,
    joint_angles_figure,
    joint_error_band_figure,
    parameter_figure,
    residual_figure,
    residual_grids,
    residual_map_figure,
    residual_map_summary,
    save_figure,
    snapshot_error_figure,
    trajectory_topview_figure,
    write_calibration_outputs,
    write_report_pdf,
)
from dcc_fg.plots.calibration import parameter_status


def _fmt(x: float | None) -> str:
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "-"
    return f"{x:.3e}" if abs(x) < 1e-2 or abs(x) >= 1e3 else f"{x:.4f}"


def _rows(title: str, header: list[str], rows: list[list[Any]]) -> str:
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
    lines = [
        title,
        "  "
        + "  ".join(
            str(h).rjust(w) if i else str(h).ljust(w) for i, (h, w) in enumerate(zip(header, widths, strict=True))
        ),
    ]
    for r in rows:
        lines.append(
            "  "
            + "  ".join(
                str(c).rjust(w) if i else str(c).ljust(w) for i, (c, w) in enumerate(zip(r, widths, strict=True))
            )
        )
    return "\n".join(lines)


def calibration_table(stats: dict[str, Any]) -> str:
    """Reprojection statistics of one calibration run (from ``GimbalCalibration.statistics``)."""
    rep = stats["reprojection_error_px"]
    rows = [
        [
            cam,
            rep[cam]["count"],
            _fmt(rep[cam]["mean"]),
            _fmt(rep[cam]["std"]),
            _fmt(rep[cam]["rms_per_axis"]),
            _fmt(rep[cam].get("max")),
        ]
        for cam in ("static", "dynamic", "all")
    ]
    head = (
        f"{stats['mode']} calibration ({stats['formulation']}), {stats['snapshots']} snapshots, "
        f"{stats['iterations']} iterations, {stats['solve_time_s']:.2f} s"
    )
    return _rows(head, ["camera", "corners", "mean |e| px", "std px", "RMS/axis px", "max px"], rows)


DEMO_COLUMNS = ["", "paper cal", "dcc-fg cal", "paper val", "dcc-fg val"]
SPREAD_REPORTED = 0.1  # mean Mahalanobis^2: a plausible second solution this far from the best one is mentioned


def demo_reprojection_table(s: dict[str, Any]) -> str:
    """Table I: mean, std and RMS per axis of the reprojection error (px), calibration and validation sets."""
    p = s["paper"]
    cal_rep = s["calibration"]["reprojection_error_px"]["all"]
    val_rep = s["validation"]["reprojection_error_px"]["all"]
    n_cal = s["scenario"]["calibration_snapshots"]
    n_val = s["scenario"]["validation_snapshots"]
    return _rows(
        "Table I - reprojection error (simulated 2-DOF gimbal, 0.4 px noise)",
        DEMO_COLUMNS,
        [
            ["images", n_cal, n_cal, n_val, n_val],
            [
                "mean |e| (px)",
                _fmt(p["reprojection_mean_px"]["calibration"]),
                _fmt(cal_rep["mean"]),
                _fmt(p["reprojection_mean_px"]["validation"]),
                _fmt(val_rep["mean"]),
            ],
            [
                "std |e| (px)",
                _fmt(p["reprojection_std_px"]["calibration"]),
                _fmt(cal_rep["std"]),
                _fmt(p["reprojection_std_px"]["validation"]),
                _fmt(val_rep["std"]),
            ],
            ["RMS per axis (px)", "-", _fmt(cal_rep["rms_per_axis"]), "-", _fmt(val_rep["rms_per_axis"])],
        ],
    )


def demo_joint_error_table(s: dict[str, Any]) -> str:
    """Table II: offset-free joint-angle errors (rad) of the bundle calibration, and their RMS beside the CRB."""
    p = s["paper"]
    gt = s["ground_truth_errors"]["bundle"]
    rows = []
    for j, (jc, jv) in enumerate(
        zip(gt["calibration"]["joint_offset_free_rad"], gt["validation"]["joint_offset_free_rad"], strict=True)
    ):
        pc = p["joint_mean_rad"]["calibration"][j] if j < 2 else None
        pv = p["joint_mean_rad"]["validation"][j] if j < 2 else None
        sc = p["joint_std_rad"]["calibration"][j] if j < 2 else None
        sv = p["joint_std_rad"]["validation"][j] if j < 2 else None
        rows.append([f"joint {j + 1} mean |err|", _fmt(pc), _fmt(jc["mean"]), _fmt(pv), _fmt(jv["mean"])])
        rows.append([f"joint {j + 1} std", _fmt(sc), _fmt(jc["std"]), _fmt(sv), _fmt(jv["std"])])
    for j, b in enumerate(s["cramer_rao_bound"]["joint_offset_free_rms_rad"]):
        rms = gt["calibration"]["joint_offset_free_rad"][j]["rms"]
        rows.append([f"joint {j + 1} RMS / CRB", "-", f"{_fmt(rms)} / {_fmt(b)}", "-", "-"])
    return _rows("Table II - joint-angle errors (rad, constant offset per joint removed)", DEMO_COLUMNS, rows)


def demo_kinematic_error_table(s: dict[str, Any]) -> str:
    """Table III: mean and std of the absolute errors of the observable translation (m) and rotation (rad)
    kinematic parameters of the bundle calibration."""
    p = s["paper"]
    kin = s["ground_truth_errors"]["bundle"]["calibration"]["kinematic_errors_observable"]
    trans = [abs(v) for k, v in kin.items() if k.split(".")[1] in ("tx", "ty", "tz", "d", "a")]
    rot = [abs(v) for k, v in kin.items() if k.split(".")[1] in ("rx", "ry", "rz", "alpha")]
    return _rows(
        "Table III - kinematic parameter errors (observable parameters only: " + ", ".join(kin) + ")",
        ["", "paper", "dcc-fg"],
        [
            [
                "translation mean |err| (m)",
                _fmt(p["translation_param_mean_m"]),
                _fmt(float(np.mean(trans)) if trans else None),
            ],
            [
                "translation std (m)",
                _fmt(p["translation_param_std_m"]),
                _fmt(float(np.std(trans)) if trans else None),
            ],
            [
                "rotation mean |err| (rad)",
                _fmt(p["rotation_param_mean_rad"]),
                _fmt(float(np.mean(rot)) if rot else None),
            ],
            ["rotation std (rad)", _fmt(p["rotation_param_std_rad"]), _fmt(float(np.std(rot)) if rot else None)],
        ],
    )


def demo_T_ds_error_table(s: dict[str, Any]) -> str:
    """RMS of the gauge-invariant T_ds(theta_i) errors (rad, m): bundle and two-way calibration, validation, CRB."""
    gt = s["ground_truth_errors"]["bundle"]
    tw = s["ground_truth_errors"]["two_way"]["calibration"]
    crb = s["cramer_rao_bound"]
    return _rows(
        "Gauge-invariant errors: T_ds(theta_i) per snapshot against ground truth",
        ["", "bundle cal", "two-way cal", "bundle val", "CRB (cal)"],
        [
            [
                "rotation RMS (rad)",
                _fmt(gt["calibration"]["T_ds_rotation_rad"]["rms"]),
                _fmt(tw["T_ds_rotation_rad"]["rms"]),
                _fmt(gt["validation"]["T_ds_rotation_rad"]["rms"]),
                _fmt(crb["T_ds_rotation_rms_rad"]),
            ],
            [
                "translation RMS (m)",
                _fmt(gt["calibration"]["T_ds_translation_m"]["rms"]),
                _fmt(tw["T_ds_translation_m"]["rms"]),
                _fmt(gt["validation"]["T_ds_translation_m"]["rms"]),
                _fmt(crb["T_ds_translation_rms_m"]),
            ],
        ],
    )


def demo_table(s: dict[str, Any]) -> str:
    """The demo's comparison with the paper's Tables I-III (``s``: the demo's ``summary.json`` dictionary)."""
    tables = (demo_reprojection_table, demo_joint_error_table, demo_kinematic_error_table, demo_T_ds_error_table)
    return "\n\n".join(table(s) for table in tables)


def sync_summary(inp: dict[str, Any], sync: dict[str, Any], offset: dict[str, Any]) -> str:
    """Lines of an unsynchronized (``--sync interpolate``) run: frames, what happened to the gimbal frames,
    the inter-camera offset (ms) with its 1-sigma."""
    rejected = ", ".join(f"{v} {k}" for k, v in sync["rejected"].items()) or "none"
    shift = sync["compensation_px"]["median"]
    std = offset["std_s"]
    how = "given" if not offset["estimated"] else (
        f"estimated, 1-sigma {std * 1e3:.3g} ms" if offset["determined"] and math.isfinite(std)
        else "NOT determined by the data (too little motion), used as given")  # fmt: skip
    return "\n".join([
        f"input ({inp['layout']}): {inp['frames_static']} cam0 and {inp['frames_dynamic']} cam1 frames; "
        f"{sync['dynamic_frames']} gimbal frames considered",
        f"snapshots: {sync['used']} used ({sync['exact']} with a static frame at the same instant, "
        f"{sync['compensated']} with the static corners interpolated, median shift "
        f"{'-' if shift is None else f'{shift:.2f}'} px); rejected: {rejected}",
        f"inter-camera time offset t_d - t_s: {offset['delta_s'] * 1e3:.3f} ms ({how})",
    ])  # fmt: skip


def run_summary_table(stats: dict[str, Any]) -> str:
    """End-of-run summary of ``dcc-fg calibrate`` / ``validate`` (from the run's ``statistics``).

    Input counts (``stats["input"]``, from :func:`dcc_fg.sources.dataset.load_dataset`'s report),
    snapshots used / rejected, the reprojection table per camera, the observability of the
    kinematic parameters (``stats["observability"]``) and the spread of the per-snapshot T_ds
    standard deviations (``stats["T_ds_std"]``, mrad and mm).
    """
    lines = []
    inp = stats.get("input")
    sync, offset = stats.get("sync"), stats.get("time_offset")
    if inp and sync and offset:
        lines.append(sync_summary(inp, sync, offset))
    elif inp:
        lines.append(
            f"input ({inp['layout']}): {inp['pairs']} image pairs; unpaired frames: {inp['unpaired_static']} cam0, "
            f"{inp['unpaired_dynamic']} cam1; target found in {inp['detected_static']} cam0 and "
            f"{inp['detected_dynamic']} cam1 images"
        )
        lines.append(
            f"snapshots: {inp['kept']} used, {inp['rejected']} rejected (fewer than {inp['min_common_points']} "
            "target points seen by both cameras)"
        )
    lines.append(calibration_table(stats))
    obs = stats.get("observability")
    if obs:
        fixed, dep = obs["gauge_fixed"], obs["gauge_dependent"]
        lines.append(
            f"observability (information matrix): {obs['n_observable']} of {obs['n_parameters']} kinematic "
            f"parameters observable ({', '.join(obs['observable']) or 'none'})"
            + (f"; held fixed to remove the gauge: {', '.join(fixed)}" if fixed else "")
            + (f"; estimated but gauge-dependent (no std): {', '.join(dep)}" if dep else "")
            + (
                f"; held at zero (exactly intersecting axes): {', '.join(obs['held_at_zero'])}"
                if obs.get("held_at_zero")
                else ""
            )
        )
    glob = stats.get("global")
    if glob:
        costs = [f"{st['start']}: {st['data_cost']:.6g}" for st in glob.get("starts", []) if "data_cost" in st]
        lines.append(f"global search: {glob['solved']} start(s) solved, kept {glob['chosen']} (pixel cost "
                     + "; ".join(costs) + ")")  # fmt: skip
        amb = glob.get("ambiguity")
        if amb:
            lines.append(
                f"AMBIGUOUS: start {amb['start']} fits as well (chi-square difference "
                f"{amb['cost_difference_chi2']:.3g} < {amb['threshold_chi2']:.3g}) with T_ds "
                f"{amb['rotation_rms_rad'] * 1e3:.3g} mrad / "
                f"{amb['translation_rms_m'] * 1e3:.3g} mm apart (included in the T_ds 1-sigma below)"
            )
        spread = glob.get("spread")
        if not amb and spread and spread.get("mean_mahalanobis2", 0.0) >= SPREAD_REPORTED:
            lines.append(
                f"start {spread['start']} fits as well and ends within the uncertainty, T_ds "
                f"{spread['rotation_rms_rad'] * 1e3:.3g} mrad / {spread['translation_rms_m'] * 1e3:.3g} mm apart "
                "(RMS; included in the T_ds 1-sigma below)"
            )
    sel = stats.get("model_selection")
    if sel and "gain_chi2" in sel:
        lines.append(
            f"model: {sel['model']} (free link offsets fit {sel['gain_chi2']:.3g} chi2 better than exactly "
            f"intersecting axes, threshold {sel['threshold_chi2']:.3g} for {sel['dof']} dof)"
        )
    if stats.get("held_by_prior"):
        lines.append(
            f"held by a weak prior (not determined by the data): {stats['held_by_prior']} direction(s) of the "
            "kinematics, see held_by_prior in calibration.yaml"
        )
    tds = stats.get("T_ds_std")
    if tds:
        lines.append(
            f"T_ds 1-sigma per snapshot: rotation median {tds['rotation_mrad']['median']:.3g} mrad "
            f"(max {tds['rotation_mrad']['max']:.3g}), translation median {tds['translation_mm']['median']:.3g} mm "
            f"(max {tds['translation_mm']['max']:.3g})"
        )
    elif stats.get("covariance", "ok") != "ok":
        lines.append(f"T_ds 1-sigma: not available ({stats['covariance']})")
    acc = stats.get("accuracy_over_range")
    if acc and acc.get("snapshot", {}).get("points") and acc.get("kinematics", {}).get("points"):
        s, k = acc["snapshot"], acc["kinematics"]
        rng = ", ".join(f"{lo:.1f}:{hi:.1f}" for lo, hi in acc["range_deg"])
        lines.append(
            f"predicted T_ds 1-sigma over the range {rng} deg ({acc['range_source']}): at a snapshot there worst "
            f"{s['worst_rotation_mrad']:.3g} mrad / {s['worst_translation_mm']:.3g} mm (mean "
            f"{s['mean_rotation_mrad']:.3g} / {s['mean_translation_mm']:.3g}); kinematics alone worst "
            f"{k['worst_rotation_mrad']:.3g} mrad / {k['worst_translation_mm']:.3g} mm (dcc-fg plan proposes what to "
            "record next)"
        )
    return "\n".join(lines)


def parameter_table(cal: GimbalCalibration, truth: GimbalCalibration | None = None) -> str:
    """Kinematic parameters of a ``GimbalCalibration``: status (observable / gauge-fixed / unobservable),
    estimate, 1-sigma and, when given, the truth (radians and metres)."""
    std = cal.kin_std if cal.kin_std is not None else np.full(len(cal.kin), np.nan)
    header = ["parameter", "status", "estimate", "1-sigma"] + (["truth"] if truth is not None else [])
    rows = []
    for k, (name, st) in enumerate(zip(cal.names, parameter_status(cal), strict=True)):
        row = [name, st, f"{cal.kin[k]: .6f}", _fmt(float(std[k]))]
        if truth is not None:
            row.append(f"{truth.kin[k]: .6f}")
        rows.append(row)
    return _rows("Kinematic parameters (rad, m)", header, rows)


__all__ = [
    "calibration_figures",
    "calibration_table",
    "chain_figure",
    "coverage_figure",
    "demo_table",
    "error_over_distance_figure",
    "joint_angles_figure",
    "joint_error_band_figure",
    "parameter_figure",
    "parameter_table",
    "residual_figure",
    "residual_grids",
    "residual_map_figure",
    "residual_map_summary",
    "save_figure",
    "snapshot_error_figure",
    "trajectory_topview_figure",
    "write_calibration_outputs",
    "write_report_pdf",
]
