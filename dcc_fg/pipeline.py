"""``dcc-fg calibrate`` / ``dcc-fg validate``: files in, calibration files out."""

from __future__ import annotations

import argparse
import io
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from dcc_fg.calibrate import CalibrationOptions, CalibrationResult, calibrate
from dcc_fg.io.camchain import CamchainEntry
from dcc_fg.model import GimbalCalibration, _plain, load_calibration, write_text_atomic
from dcc_fg.report import run_summary_table

#: Default of ``--min-common-points``: a snapshot needs this many target points seen by both cameras.
MIN_COMMON_POINTS = 8


def _stderr_is_terminal() -> bool:
    return sys.stderr.isatty()


def _load_options(args: argparse.Namespace, report: dict[str, Any]) -> dict[str, Any]:
    """Reader options from the command line: progress bar (stderr, only on a terminal and without
    ``--quiet``), pairing tolerance (``--sync-tolerance`` ms -> ns), ``--min-common-points``,
    ``--corners``, and the dict that receives the reader's counts for the summary."""
    report["min_common_points"] = int(getattr(args, "min_common_points", MIN_COMMON_POINTS))
    report["corners"] = str(getattr(args, "corners", "all"))
    return {
        "corners": report["corners"],
        "progress": not getattr(args, "quiet", False) and _stderr_is_terminal(),
        "tolerance_ns": int(round(float(getattr(args, "sync_tolerance", 5.0)) * 1e6)),
        "min_common_points": report["min_common_points"],
        "report": report,
    }


def _load(data: str, camchain: Any, target: str | None, corners: str = "all", **options: Any):  # noqa: ANN202
    """The CalibrationDataset of ``data``; ``corners='common'`` keeps only the corners both cameras
    of a snapshot see (``--corners``)."""
    from dcc_fg.data import common_corners
    from dcc_fg.io.dataset import load_dataset

    if corners not in ("all", "common"):
        raise ValueError(f"--corners must be all or common, got {corners}")
    dataset = load_dataset(data, camchain=camchain, target=target, **options)
    return common_corners(dataset) if corners == "common" else dataset


def _T_ds_std(result: CalibrationResult) -> dict[str, dict[str, float]] | None:
    """Median / max over snapshots of the T_ds 1-sigma (rotation mrad, translation mm; root of the
    trace of each 3x3 block of the Pose3 tangent covariance [omega, v])."""
    cov = result.T_ds_covariances
    if cov is None or len(cov) == 0 or not np.all(np.isfinite(cov)):
        return None
    rot = 1e3 * np.sqrt(np.trace(cov[:, :3, :3], axis1=1, axis2=2))
    tra = 1e3 * np.sqrt(np.trace(cov[:, 3:, 3:], axis1=1, axis2=2))
    return {
        "rotation_mrad": {"median": float(np.median(rot)), "max": float(rot.max())},
        "translation_mm": {"median": float(np.median(tra)), "max": float(tra.max())},
    }


def _observability(cal: GimbalCalibration) -> dict[str, Any] | None:
    """Observable / gauge-fixed / gauge-dependent kinematic parameter names (see dcc_fg.calibrate)."""
    if cal.observable is None:
        return None
    fixed = cal.gauge_fixed if cal.gauge_fixed is not None else np.zeros(len(cal.names), dtype=bool)
    return {
        "n_parameters": len(cal.names),
        "n_observable": int(np.count_nonzero(cal.observable)),
        "observable": [n for n, o in zip(cal.names, cal.observable, strict=True) if o],
        "gauge_fixed": [n for n, f in zip(cal.names, fixed, strict=True) if f],
        "gauge_dependent": [n for n, o, f in zip(cal.names, cal.observable, fixed, strict=True) if not o and not f],
    }


def _write(
    out: Path,
    result: CalibrationResult,
    stats_name: str = "summary.json",
    report: dict[str, Any] | None = None,
    quiet: bool = False,
) -> None:
    """Write calibration.yaml, joint_angles.csv and the summary JSON, all or nothing as far as
    possible: every text is serialized before the first file is touched, each file is replaced
    atomically; then print the summary table (unless ``quiet``)."""
    stats = result.calibration.statistics
    if report:
        stats["input"] = dict(report)
    if result.options.mode != "validate":
        obs = _observability(result.calibration)
        if obs is not None:
            stats["observability"] = obs
    tds = _T_ds_std(result)
    if tds is not None:
        stats["T_ds_std"] = tds
    cal_text = yaml.safe_dump(result.calibration.to_dict(), sort_keys=False)
    buf = io.StringIO()
    L = result.joint_angles.shape[1] if result.joint_angles.ndim == 2 else 0
    buf.write(",".join(["timestamp_ns"] + [f"theta_{j + 1}" for j in range(L)]) + "\n")
    for t, th in zip(result.timestamps_ns, result.joint_angles, strict=True):
        buf.write(",".join([str(int(t))] + [f"{x:.12g}" for x in th]) + "\n")
    json_text = json.dumps(_plain(stats), indent=2) + "\n"
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "calibration.yaml", cal_text)
    write_text_atomic(out / "joint_angles.csv", buf.getvalue())
    write_text_atomic(out / stats_name, json_text)
    if not quiet:
        print(run_summary_table(stats))
        print(f"wrote {out / 'calibration.yaml'}, {out / 'joint_angles.csv'}, {out / stats_name}")


def run_calibrate(args: argparse.Namespace) -> int:
    """Calibrate from ``args.data`` with the initial kinematics of ``--gimbal``."""
    report: dict[str, Any] = {}
    data = _load(args.data, args.camchain, args.target, **_load_options(args, report))
    initial, data = initial_values(args, data)
    opts = CalibrationOptions(
        mode=args.mode,
        formulation=args.formulation,
        pixel_sigma=args.pixel_sigma,
        robust=args.robust,
        robust_k=args.robust_k,
    )
    result = calibrate(data, initial, opts)
    _write(Path(args.out), result, report=report, quiet=getattr(args, "quiet", False))
    _report(Path(args.out), result, data, args)
    return 0


def initial_values(args: argparse.Namespace, data):  # noqa: ANN001, ANN201 - CalibrationDataset in and out
    """Initial kinematics from ``--gimbal`` (``--init gimbal``) or from the data (``--init auto``,
    the default without ``--gimbal``; needs ``--joints L``). The automatic joint angles are put
    into the snapshots as the starting guesses."""
    init = getattr(args, "init", None) or ("gimbal" if args.gimbal else "auto")
    if init == "gimbal":
        if args.gimbal is None:
            raise ValueError("--init gimbal needs --gimbal G.yaml")
        return load_calibration(args.gimbal), data
    if init != "auto":
        raise ValueError(f"--init must be auto or gimbal, got {init}")
    if args.joints is None:
        raise ValueError("--joints L is required when no --gimbal G.yaml is given (automatic initialization)")
    from dataclasses import replace

    from dcc_fg.auto_init import auto_initialize

    initial, thetas, _ = auto_initialize(data, int(args.joints))
    if args.mode == "encoders":  # joint readings come from the data; keep them
        return initial, data
    snaps = [replace(s, joints=t) for s, t in zip(data.snapshots, thetas, strict=True)]
    return initial, replace(data, snapshots=snaps)


def run_validate(args: argparse.Namespace) -> int:
    """Hold ``--calibration`` fixed and estimate the joint angles of ``args.data``."""
    cal = load_calibration(args.calibration)
    camchain: Any = args.camchain
    if camchain is None:  # the intrinsics stored in the calibration (no image topics: folders only)
        if cal.static_camera is None or cal.dynamic_camera is None:
            raise ValueError(f"{args.calibration}: has no cam0/cam1 intrinsics; give --camchain")
        camchain = {"cam0": CamchainEntry(cal.static_camera), "cam1": CamchainEntry(cal.dynamic_camera)}
    report: dict[str, Any] = {}
    data = _load(args.data, camchain, args.target, **_load_options(args, report))
    result = calibrate(data, cal, CalibrationOptions(mode="validate"))
    _write(Path(args.out), result, report=report, quiet=getattr(args, "quiet", False))
    _report(Path(args.out), result, data, args)
    return 0


def _report(out: Path, result, data, args: argparse.Namespace) -> None:  # noqa: ANN001
    """With ``--report``: the calibration figures as ``OUT/calibration_*.png`` and ``OUT/report.pdf``."""
    if not getattr(args, "report", False):
        return
    from dcc_fg.plots.output import write_calibration_outputs
    from dcc_fg.report import parameter_table

    text = run_summary_table(result.calibration.statistics) + "\n\n" + parameter_table(result.calibration)
    paths = write_calibration_outputs(out, result, text, target_points=data.target_points)
    if not getattr(args, "quiet", False):
        print("wrote " + ", ".join(str(p) for p in paths))
