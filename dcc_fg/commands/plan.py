"""``dcc-fg plan CALIBRATION --range ... --tolerance ... --k K --objective worst|mean --out DIR``.

Reads the ``kinematics_information.npz`` that ``dcc-fg calibrate`` writes beside ``calibration.yaml``
(CALIBRATION is that folder, or the ``calibration.yaml`` in it) and proposes the next K snapshots
(:mod:`dcc_fg.planning.plan`): joint angles (deg, in the calibration's joint-angle convention, as in its
``joint_angles.csv``) and where to hold the target relative to the static camera. Writes, as one
output set (:class:`~dcc_fg.io.output_set.OutputSet`): ``OUT/plan.yaml`` (for a script driving the
gimbal), ``OUT/accuracy.png`` (predicted 1-sigma over the range with the planned angles) and
``OUT/accuracy.txt`` (the table); prints the list. Exit code 0 also when the tolerance is not yet
reached (``stop.tolerance_reached`` in plan.yaml says which).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from dcc_fg.commands import common
from dcc_fg.io.output_set import OutputSet
from dcc_fg.io.outputs import plain, write_text_atomic
from dcc_fg.model import load_calibration
from dcc_fg.planning.plan import OBJECTIVES, plan_snapshots
from dcc_fg.planning.predict import (
    INFORMATION_FILE,
    MODES,
    KinematicsInformation,
    accuracy_over_range,
    accuracy_table,
)
from dcc_fg.planning.range_spec import default_range, format_range, parse_range, parse_tolerance
from dcc_fg.plots.accuracy_map import accuracy_figure
from dcc_fg.plots.common import save_figure
from dcc_fg.util.provenance import run_record

KIN_TOL = 1e-9  # calibration.yaml and the information file must hold the same kinematics (rad, m)


def load_information(path: str | Path) -> tuple[KinematicsInformation, Path]:
    """The information file of a calibration folder (or of the folder of a ``calibration.yaml``), checked
    against the ``calibration.yaml`` beside it when there is one."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such calibration folder or file")
    folder = p if p.is_dir() else p.parent
    npz = folder / INFORMATION_FILE
    if not npz.exists():
        raise ValueError(
            f"{npz}: not found; dcc-fg plan needs the {INFORMATION_FILE} that dcc-fg calibrate writes beside "
            "calibration.yaml (re-run the calibration with this version)"
        )
    info = KinematicsInformation.load(npz)
    yaml_path = p if p.is_file() else folder / "calibration.yaml"
    if yaml_path.exists():
        cal = load_calibration(yaml_path)
        if cal.n_joints != info.n_joints or np.max(np.abs(cal.kin - info.kin)) > KIN_TOL:
            raise ValueError(f"{yaml_path} and {npz} hold different kinematics: re-run dcc-fg calibrate")
    return info, npz


def run_plan(args: argparse.Namespace) -> int:
    info, npz = load_information(args.calibration)
    ranges = parse_range(args.range, info.n_joints) if args.range else default_range(info.joint_angles)
    tolerance = parse_tolerance(args.tolerance)
    outputs = OutputSet(Path(args.out), "plan", {"CALIBRATION": args.calibration})
    with outputs:
        plan = plan_snapshots(info, ranges, tolerance, args.k, args.objective, args.predict)
        acc = accuracy_over_range(info, ranges)
        planned = np.array([s.theta for s in plan.snapshots]).reshape(-1, info.n_joints)
        doc: dict[str, Any] = {
            **plan.to_dict(),
            "range_source": "--range" if args.range else "data range plus margin",
            "calibration": str(args.calibration),
            "information_file": str(npz),
            "provenance": run_record(
                "plan",
                {"calibration": str(args.calibration)},
                {
                    "range": format_range(ranges),
                    "tolerance": args.tolerance,
                    "k": args.k,
                    "objective": args.objective,
                    "predict": args.predict,
                },
            ),  # fmt: skip
        }
        mode = args.predict if args.predict != "calibration" else "snapshot"
        fig = accuracy_figure(acc, info.joint_angles, planned, mode)
        paths = [
            write_yaml(outputs.path / "plan.yaml", doc),
            save_figure(fig, outputs.path / "accuracy.png"),
            write_text(outputs.path / "accuracy.txt", accuracy_table(acc) + "\n\n" + plan.text() + "\n"),
        ]
        final = [outputs.final(p) for p in paths]
    if not args.quiet:
        print(accuracy_table(acc, 6))
        print()
        print(plan.text())
        print("wrote " + ", ".join(str(p) for p in final))
    return 0


def write_yaml(path: Path, doc: dict[str, Any]) -> Path:
    write_text_atomic(path, yaml.safe_dump(plain(doc), sort_keys=False))
    return path


def write_text(path: Path, text: str) -> Path:
    write_text_atomic(path, text)
    return path


def add_parser(sub: Any, parent: argparse.ArgumentParser) -> None:
    """Register ``plan``."""
    p = common.add_command(
        sub, "plan", parent, "propose the next snapshots that most reduce the T_ds uncertainty over a range",
        "From a calibration folder (calibration.yaml and kinematics_information.npz of dcc-fg calibrate), predict the "
        "1-sigma of T_ds over the operating range and propose the next K snapshots (joint angles in deg, target "
        "distance and tilt) by expected information gain; stop when the predicted worst 1-sigma is within "
        "--tolerance.", run_plan,
    )  # fmt: skip
    p.add_argument("calibration", help="calibration folder of dcc-fg calibrate (or its calibration.yaml)")
    p.add_argument("--range", metavar="LO:HI,...", help='operating range, degrees per joint, e.g. "-30:30,-20:45" '
                   "(the calibration's joint-angle convention, as in joint_angles.csv); default: the range the "
                   "data covered plus 10%% of it (at least 2 deg) on each side")  # fmt: skip
    p.add_argument("--tolerance", default="1mrad,1mm", metavar="ROT,TRANS", help="largest acceptable worst-case "
                   "1-sigma of T_ds over the range: rotation (urad|mrad|rad|deg) and translation (um|mm|cm|m), "
                   "default 1mrad,1mm")  # fmt: skip
    p.add_argument("--k", type=int, default=5, help="largest number of snapshots to propose (default 5)")
    p.add_argument("--objective", choices=list(OBJECTIVES), default="worst", help="minimize the worst (smooth "
                   "maximum) or the mean 1-sigma over the range (default worst)")  # fmt: skip
    p.add_argument("--predict", choices=list(MODES), default="calibration", help="what the tolerance applies to: "
                   "calibration (default): the calibration's share of T_ds's error at a snapshot; snapshot: "
                   "also that snapshot's own noise; kinematics: T_ds from the kinematics, angles known")  # fmt: skip
    p.add_argument("--out", default="dcc_fg_plan", help="output folder for plan.yaml, accuracy.png and accuracy.txt "
                   f"(default ./dcc_fg_plan; not the calibration folder). {common.OUT_FOLDER_HELP}")  # fmt: skip
