"""``dcc-fg demo``: the paper's simulated study, calibrated and validated, beside Tables I-III."""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dcc_fg.commands import common
from dcc_fg.demo import run_demo
from dcc_fg.util.provenance import run_record


@dataclass
class DemoOptions:
    """``seed`` of the simulation, number of ``joints`` L, ``report`` (also OUT/report.pdf)."""

    seed: int = 0
    joints: int = 2
    report: bool = False


DEMO_SUMMARY = "simulate the paper's study, calibrate, validate and compare with its Tables I-III"
DEMO_DESCRIPTION = (
    "Simulates the paper's 2-DOF gimbal study (81 calibration + 81 validation snapshots, 9x7 "
    "chessboard, 0.4 px noise), runs encoderless calibration (bundle and two-way formulations) and validation, "
    "prints a table beside the paper's Tables I-III and writes calibration.yaml, joint_angles.csv, summary.json."
)


def demo_command(args: argparse.Namespace) -> int:
    options = DemoOptions(args.seed, args.joints, args.report)
    rerun = common.rerun_options(args)
    provenance = run_record("demo", {}, options)
    out = Path(args.out)
    run_demo(out, seed=options.seed, n_joints=options.joints, report=options.report, provenance=provenance, rerun=rerun)
    return 0


def add_parser(sub: Any, parent: argparse.ArgumentParser) -> None:
    d = common.add_command(sub, "demo", parent, DEMO_SUMMARY, DEMO_DESCRIPTION, demo_command)
    d.add_argument(
        "--out", default="dcc_fg_demo", help=f"output folder (default: ./dcc_fg_demo). {common.OUT_FOLDER_HELP}"
    )
    d.add_argument("--seed", type=int, default=0, help="random seed of the simulation (default 0)")
    d.add_argument("--joints", type=int, default=2, choices=[0, 1, 2, 3], help="number of gimbal joints L (default 2)")
    d.add_argument("--report", action="store_true", help="also write OUT/report.pdf (tables and figures)")
    common.add_rerun_flags(d, "the calibration snapshots' corners, detected and reprojected, and the chain's frames")
