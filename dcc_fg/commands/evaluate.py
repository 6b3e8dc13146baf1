"""``dcc-fg evaluate OUT --ground-truth GT``: score a VIO run against ground truth (Tables IV-V)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from dcc_fg.commands import common
from dcc_fg.plots.vio_output import write_vio_figures
from dcc_fg.vio.evaluate import evaluate_output, format_evaluation

EVALUATE_SUMMARY = "score a VIO run (trajectory.tum, joint_angles.csv) against ground truth"
EVALUATE_DESCRIPTION = (
    "APE/RPE with evo (SE(3) alignment; Sim(3) for mono runs), normalized translation RMSE (%% of "
    "distance) and rotation RMSE (rad/m) as in the paper's Table IV, joint-angle RMSE per joint (Table V). "
    "Writes OUT/evaluation.json."
)


def evaluate_command(args: argparse.Namespace) -> int:
    out = Path(args.out)
    result = evaluate_output(out, Path(args.ground_truth), align=args.align)
    print(format_evaluation(result))
    saved = write_vio_figures(out, Path(args.ground_truth), align=result["alignment"])
    for path in saved.paths.values():
        print(f"wrote {path}")
    return 0


def add_parser(sub: Any, parent: argparse.ArgumentParser) -> None:
    e = common.add_command(sub, "evaluate", parent, EVALUATE_SUMMARY, EVALUATE_DESCRIPTION, evaluate_command)
    e.add_argument("out", help="output folder of dcc-fg vio (trajectory.tum, summary.json, joint_angles.csv)")
    e.add_argument(
        "--ground-truth",
        required=True,
        help="TUM file (t tx ty tz qx qy qz qw, body frame) or ROS1/ROS2 bag with /ground_truth/pose "
        "(geometry_msgs/PoseStamped) and /ground_truth/joints (sensor_msgs/JointState)",
    )
    e.add_argument(
        "--align", default="auto", choices=["auto", "se3", "sim3", "none"], help="default: sim3 for mono, else se3"
    )
