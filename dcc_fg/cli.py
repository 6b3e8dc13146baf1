"""Command-line interface: ``dcc-fg demo | calibrate | validate``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _cmd_demo(args: argparse.Namespace) -> int:
    from dcc_fg.demo import run_demo

    run_demo(Path(args.out), seed=args.seed, n_joints=args.joints)
    return 0


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from dcc_fg.pipeline import run_calibrate

    return run_calibrate(args)


def _cmd_validate(args: argparse.Namespace) -> int:
    from dcc_fg.pipeline import run_validate

    return run_validate(args)


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from dcc_fg.vio.evaluate import evaluate_output, format_evaluation

    result = evaluate_output(Path(args.out), Path(args.ground_truth), align=args.align)
    print(format_evaluation(result))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dcc-fg",
        description="Encoderless calibration of dynamic camera clusters (a static camera plus a camera on a "
        "gimbal without encoders) on GTSAM factor graphs.",
    )
    sub = p.add_subparsers(dest="command", required=True)

    d = sub.add_parser(
        "demo",
        help="simulate the paper's study, calibrate, validate and compare with its Tables I-III",
        description="Simulates the paper's 2-DOF gimbal study (81 calibration + 81 validation snapshots, 9x7 "
        "chessboard, 0.4 px noise), runs encoderless calibration (bundle and two-way formulations) and validation, "
        "prints a table beside the paper's Tables I-III and writes calibration.yaml, joint_angles.csv, summary.json.",
    )
    d.add_argument("--out", default="dcc_fg_demo", help="output folder (default: ./dcc_fg_demo)")
    d.add_argument("--seed", type=int, default=0, help="random seed of the simulation (default 0)")
    d.add_argument("--joints", type=int, default=2, choices=[0, 1, 2, 3], help="number of gimbal joints L (default 2)")
    d.set_defaults(func=_cmd_demo)

    c = sub.add_parser(
        "calibrate",
        help="calibrate a DCC from target snapshots (bag, image folder or detection folder)",
        description="Estimate the gimbal kinematics (tau_s, tau_d in rad/m, DH d/a in m, alpha in rad) and, in "
        "encoderless mode, the joint angles (rad) of every snapshot.",
    )
    c.add_argument("data", help="ROS1 .bag, ROS2 bag folder, image folder (cam0/, cam1/) or detection folder")
    c.add_argument("--camchain", help="Kalibr camchain YAML with cam0 (static) and cam1 (dynamic) intrinsics")
    c.add_argument("--target", help="Kalibr target YAML (checkerboard or aprilgrid); detection folders carry their own")
    c.add_argument("--gimbal", help="initial kinematics YAML (joints, tau_s, tau_d, dh; rad and m)")
    c.add_argument("--joints", type=int, help="number of joints L when no --gimbal is given")
    c.add_argument(
        "--mode",
        default="encoderless",
        choices=["encoderless", "encoders"],
        help="joint angles unknown (encoderless) or read from joints.csv / JointState (encoders)",
    )
    c.add_argument(
        "--formulation",
        default="bundle",
        choices=["bundle", "two_way"],
        help="maximum-likelihood bundle (default) or the paper's two-way error",
    )
    c.add_argument(
        "--pixel-sigma",
        type=float,
        default=None,
        help="corner noise in pixels (1 sigma); default: estimated from the residuals",
    )
    c.add_argument("--robust", choices=["huber", "cauchy"], default=None, help="per-corner robust loss")
    c.add_argument("--robust-k", type=float, default=2.0, help="robust loss threshold in pixels (default 2)")
    c.add_argument("--out", default="dcc_fg_calibration", help="output folder")
    c.set_defaults(func=_cmd_calibrate)

    v = sub.add_parser(
        "validate",
        help="hold a calibration fixed and estimate only the joint angles of new snapshots",
        description="The paper's validation procedure: kinematics held at --calibration, joint angles (rad) estimated.",
    )
    v.add_argument("data", help="bag, image folder or detection folder")
    v.add_argument("--calibration", required=True, help="calibration.yaml written by dcc-fg calibrate")
    v.add_argument("--camchain", help="Kalibr camchain YAML (default: the intrinsics stored in the calibration)")
    v.add_argument("--target", help="Kalibr target YAML")
    v.add_argument("--out", default="dcc_fg_validation", help="output folder")
    v.set_defaults(func=_cmd_validate)

    e = sub.add_parser(
        "evaluate",
        help="score a VIO run (trajectory.tum, joint_angles.csv) against ground truth",
        description="APE/RPE with evo (SE(3) alignment; Sim(3) for mono runs), normalized translation RMSE (%% of "
        "distance) and rotation RMSE (rad/m) as in the paper's Table IV, joint-angle RMSE per joint (Table V). "
        "Writes OUT/evaluation.json.",
    )
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
    e.set_defaults(func=_cmd_evaluate)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except (ValueError, FileNotFoundError) as exc:
        print(f"dcc-fg {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
