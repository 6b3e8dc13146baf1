"""``dcc-fg calibrate`` / ``dcc-fg validate``: files in, calibration files out."""

from __future__ import annotations

import argparse
from pathlib import Path

from dcc_fg.calibrate import CalibrationOptions, calibrate
from dcc_fg.io.outputs import write_joint_angles_csv, write_json
from dcc_fg.model import load_calibration
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
    data = _load(args.data, args.camchain, args.target)
    initial, data = initial_values(args, data)
    opts = CalibrationOptions(
        mode=args.mode,
        formulation=args.formulation,
        pixel_sigma=args.pixel_sigma,
        robust=args.robust,
        robust_k=args.robust_k,
    )
    _write(Path(args.out), calibrate(data, initial, opts))
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
    data = _load(args.data, args.camchain, args.target)
    _write(Path(args.out), calibrate(data, cal, CalibrationOptions(mode="validate")))
    return 0
