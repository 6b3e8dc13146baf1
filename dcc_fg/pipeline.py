"""``dcc-fg calibrate`` / ``dcc-fg validate``: files in, calibration files out."""

from __future__ import annotations

import argparse
from pathlib import Path

from dcc_fg.calibrate import CalibrationOptions, calibrate
from dcc_fg.io.outputs import write_joint_angles_csv, write_json
from dcc_fg.model import GimbalCalibration, load_calibration
from dcc_fg.report import calibration_table


def _load(data: str, camchain: str | None, target: str | None):  # noqa: ANN202 - returns CalibrationDataset
    try:
        from dcc_fg.io.dataset import load_dataset
    except ImportError as exc:  # pragma: no cover - only while the readers are being built
        raise ValueError(f"reading {data} needs dcc_fg.io.dataset, which is not available: {exc}") from None
    return load_dataset(data, camchain=camchain, target=target)


def _write(out: Path, result, stats_name: str = "summary.json") -> None:  # noqa: ANN001
    out.mkdir(parents=True, exist_ok=True)
    result.calibration.save(out / "calibration.yaml")
    write_joint_angles_csv(out / "joint_angles.csv", result.timestamps_ns, result.joint_angles)
    write_json(out / stats_name, result.calibration.statistics)
    print(calibration_table(result.calibration.statistics))
    print(f"wrote {out / 'calibration.yaml'}, {out / 'joint_angles.csv'}, {out / stats_name}")


def run_calibrate(args: argparse.Namespace) -> int:
    """Calibrate from ``args.data`` with the initial kinematics of ``--gimbal``."""
    if args.gimbal is None:
        raise ValueError("--gimbal is required (automatic initialization without a gimbal.yaml is not available yet)")
    initial: GimbalCalibration = load_calibration(args.gimbal)
    data = _load(args.data, args.camchain, args.target)
    opts = CalibrationOptions(
        mode=args.mode,
        formulation=args.formulation,
        pixel_sigma=args.pixel_sigma,
        robust=args.robust,
        robust_k=args.robust_k,
    )
    result = calibrate(data, initial, opts)
    _write(Path(args.out), result)
    _report(Path(args.out), result, data, args)
    return 0


def run_validate(args: argparse.Namespace) -> int:
    """Hold ``--calibration`` fixed and estimate the joint angles of ``args.data``."""
    cal = load_calibration(args.calibration)
    data = _load(args.data, args.camchain, args.target)
    result = calibrate(data, cal, CalibrationOptions(mode="validate"))
    _write(Path(args.out), result)
    _report(Path(args.out), result, data, args)
    return 0


def _report(out: Path, result, data, args: argparse.Namespace) -> None:  # noqa: ANN001
    """With ``--report``: the calibration figures as ``OUT/calibration_*.png`` and ``OUT/report.pdf``."""
    if not getattr(args, "report", False):
        return
    from dcc_fg.plots.output import write_calibration_outputs
    from dcc_fg.report import parameter_table

    text = calibration_table(result.calibration.statistics) + "\n\n" + parameter_table(result.calibration)
    paths = write_calibration_outputs(out, result, text, target_points=data.target_points)
    print("wrote " + ", ".join(str(p) for p in paths))
