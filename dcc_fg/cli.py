"""Command-line interface: ``dcc-fg demo | calibrate | validate | intrinsics | simulate | vio | evaluate``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import yaml


def _cmd_demo(args: argparse.Namespace) -> int:
    from dcc_fg.demo import run_demo

    run_demo(Path(args.out), seed=args.seed, n_joints=args.joints, report=getattr(args, "report", False))
    return 0


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from dcc_fg.pipeline import run_calibrate

    return run_calibrate(args)


def _cmd_validate(args: argparse.Namespace) -> int:
    from dcc_fg.pipeline import run_validate

    return run_validate(args)


def _cmd_intrinsics(args: argparse.Namespace) -> int:
    from dcc_fg.intrinsics import intrinsics_table, run_intrinsics
    from dcc_fg.io.outputs import write_json
    from dcc_fg.targets import load_target

    if not Path(args.target).is_file():
        raise ValueError(f"{args.target}: target file not found")
    result = run_intrinsics(
        args.data,
        load_target(args.target),
        camera=args.camera,
        model=args.model,
        out=args.out,
        topic=args.topic,
        every=args.every,
        max_views=args.max_views,
        min_corners=args.min_corners,
        max_rms=args.max_rms,
    )
    print(intrinsics_table(result))
    if args.summary:
        write_json(Path(args.summary), result.summary())
    print(f"wrote {args.out}" + (f", {args.summary}" if args.summary else ""))
    return 0


def _cmd_simulate_flight(args: argparse.Namespace) -> int:
    from dcc_fg.sim.flight_bag import write_flight
    from dcc_fg.sim.trajectory import FlightConfig, locked_gimbal

    if args.duration is not None and args.pattern == "loops":
        raise ValueError("--duration and --pattern loops exclude each other (the loops take 90 s)")
    config = FlightConfig.short(args.duration) if args.duration is not None else FlightConfig()
    joints = locked_gimbal() if args.gimbal == "locked" else None
    res = write_flight(
        args.out, args.format, config, seed=args.seed, scale=args.scale, joints=joints, progress=not args.quiet
    )
    print(
        f"wrote {res.bag} ({res.frames} frame pairs, {res.truth.distance:.1f} m, "
        f"{res.render_ms_per_pair:.1f} ms CPU rendering per pair, {res.seconds:.1f} s), {res.calibration}, "
        f"{res.ground_truth}, {res.joints}"
    )
    return 0


def _add_reader_options(p: argparse.ArgumentParser) -> None:
    """Options shared by calibrate and validate: image pairing, snapshot selection, output verbosity."""
    p.add_argument(
        "--sync-tolerance",
        type=float,
        default=5.0,
        metavar="MS",
        help="largest time difference between a static and a dynamic image of one snapshot, milliseconds; frames "
        "without a partner are reported (default 5)",
    )
    p.add_argument(
        "--min-common-points",
        type=int,
        default=8,
        metavar="N",
        help="use a snapshot only if both cameras see at least N of the same target corners (default 8)",
    )
    p.add_argument(
        "--corners",
        choices=["all", "common"],
        default="all",
        help="all: every detected corner of each camera (the maximum-likelihood use of the data, default); "
        "common: only the corners both cameras of a snapshot see, as cv2.stereoCalibrate uses them. common helps "
        "when the intrinsics fit the image periphery badly, where only one camera tends to see the board",
    )
    p.add_argument(
        "--quiet",
        action="store_true",
        help="no progress bar and no summary table (the progress bar, on stderr, is also off when stderr is not "
        "a terminal)",
    )


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from dcc_fg.plots.vio_output import write_vio_figures
    from dcc_fg.vio.evaluate import evaluate_output, format_evaluation

    out = Path(args.out)
    result = evaluate_output(out, Path(args.ground_truth), align=args.align)
    print(format_evaluation(result))
    saved = write_vio_figures(out, Path(args.ground_truth), align=result["alignment"])
    for path in saved.paths.values():
        print(f"wrote {path}")
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
    d.add_argument("--report", action="store_true", help="also write OUT/report.pdf (tables and figures)")
    d.set_defaults(func=_cmd_demo)

    c = sub.add_parser(
        "calibrate",
        help="calibrate a DCC from target snapshots (bag, image folder or detection folder)",
        description="Estimate the gimbal kinematics (tau_s, tau_d in rad/m, DH d/a in m, alpha in rad) and, in "
        "encoderless mode, the joint angles (rad) of every snapshot.",
    )
    c.add_argument("data", help="ROS1 .bag, ROS2 bag folder, image folder (cam0/, cam1/) or detection folder")
    c.add_argument(
        "--camchain",
        help="Kalibr camchain YAML: cam0 (static) and cam1 (dynamic) intrinsics in pixels, distortion, resolution and, "
        "for bags, each camera's image rostopic",
    )
    c.add_argument(
        "--target",
        help="Kalibr target YAML (checkerboard or aprilgrid; sizes in metres); detection folders carry their own",
    )
    c.add_argument("--gimbal", help="initial kinematics YAML (joints, tau_s, tau_d, dh; rad and m)")
    c.add_argument("--joints", type=int, help="number of joints L when no --gimbal is given")
    c.add_argument(
        "--init",
        choices=["auto", "gimbal"],
        default=None,
        help="initial values: 'gimbal' reads --gimbal; 'auto' estimates axes, DH links, mounts and joint "
        "angles from per-snapshot PnP (needs --joints). Default: gimbal if --gimbal is given, else auto",
    )
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
    c.add_argument(
        "--robust",
        choices=["huber", "cauchy"],
        default=None,
        help="per-corner robust loss (default: none, plain least squares)",
    )
    c.add_argument("--robust-k", type=float, default=2.0, help="robust loss threshold in pixels (default 2)")
    c.add_argument(
        "--out",
        default="dcc_fg_calibration",
        help="output folder for calibration.yaml, joint_angles.csv (ns, rad) and summary.json; files are replaced "
        "atomically and only after a successful run (default ./dcc_fg_calibration)",
    )
    _add_reader_options(c)
    c.add_argument(
        "--report", action="store_true", help="also save the figures (OUT/calibration_*.png) and OUT/report.pdf"
    )
    c.set_defaults(func=_cmd_calibrate)

    v = sub.add_parser(
        "validate",
        help="hold a calibration fixed and estimate only the joint angles of new snapshots",
        description="The paper's validation procedure: kinematics held at --calibration, joint angles (rad) estimated.",
    )
    v.add_argument("data", help="ROS1 .bag, ROS2 bag folder, image folder (cam0/, cam1/) or detection folder")
    v.add_argument("--calibration", required=True, help="calibration.yaml written by dcc-fg calibrate")
    v.add_argument(
        "--camchain",
        help="Kalibr camchain YAML (default: the intrinsics stored in the calibration; a bag then needs --camchain "
        "for its image topics)",
    )
    v.add_argument("--target", help="Kalibr target YAML (checkerboard or aprilgrid; sizes in metres)")
    v.add_argument(
        "--out",
        default="dcc_fg_validation",
        help="output folder for calibration.yaml (the held kinematics), joint_angles.csv (ns, rad) and "
        "summary.json; written only after a successful run (default ./dcc_fg_validation)",
    )
    _add_reader_options(v)
    v.add_argument(
        "--report", action="store_true", help="also save the figures (OUT/calibration_*.png) and OUT/report.pdf"
    )
    v.set_defaults(func=_cmd_validate)

    i = sub.add_parser(
        "intrinsics",
        help="calibrate one camera's intrinsics and write a Kalibr camchain YAML",
        description="Detect the target in one camera's images (bag topic or DATA/<camera>/<timestamp_ns>.png), "
        "calibrate pinhole intrinsics (fx, fy, cx, cy in pixels) and distortion with OpenCV, print the RMS "
        "reprojection error (pixels) and every parameter's 1-sigma, and write/update the camchain entry.",
    )
    i.add_argument("data", help="ROS1 .bag, ROS2 bag folder, or a folder with <camera>/<timestamp_ns>.png images")
    i.add_argument("--target", required=True, help="Kalibr target YAML (checkerboard or aprilgrid; metres)")
    i.add_argument("--camera", default="cam0", help="camchain entry and image sub-folder (default cam0)")
    i.add_argument(
        "--model",
        default="pinhole-radtan",
        choices=["pinhole-radtan", "pinhole-equidistant"],
        help="pinhole with radial-tangential (k1 k2 p1 p2) or equidistant (k1..k4) distortion",
    )
    i.add_argument("--topic", help="image topic in a bag (default /<camera>/image_raw)")
    i.add_argument("--every", type=int, default=1, help="use every n-th image (default 1)")
    i.add_argument("--max-views", type=int, default=80, help="at most this many views, evenly spaced (default 80)")
    i.add_argument("--min-corners", type=int, default=12, help="corners a view needs to be used (default 12)")
    i.add_argument(
        "--max-rms", type=float, default=2.0, help="refuse results with a larger RMS reprojection error (px, default 2)"
    )
    i.add_argument("--out", default="camchain.yaml", help="camchain YAML to write or update (default camchain.yaml)")
    i.add_argument("--summary", help="optional JSON file with the parameters, 1-sigma and reprojection error")
    i.set_defaults(func=_cmd_intrinsics)

    s = sub.add_parser(
        "simulate",
        help="write simulated data sets with ground truth (rendered calibration images, VIO flights)",
        description="Simulated data sets with ground truth. See 'dcc-fg simulate calibration --help'.",
    )
    s_sub = s.add_subparsers(dest="what", required=True)
    from dcc_fg.sim.write_dataset import add_simulate_calibration_parser

    add_simulate_calibration_parser(s_sub)
    f = s_sub.add_parser(
        "flight",
        help="render a VIO flight (IMU, static and gimbal camera) into a ROS1/ROS2 bag",
        description="A body flying rounded-rectangle loops in a textured box room with a freely moving 2-joint "
        "gimbal: /imu0 (200 Hz), /cam0/image_raw (static) and /cam1/image_raw (gimbal) at 20 Hz, truth on "
        "/ground_truth/pose and /ground_truth/joints; also calibration.yaml (with an imu: section), "
        "ground_truth.tum and ground_truth_joints.csv.",
    )
    f.add_argument("--out", required=True, help="output folder")
    f.add_argument("--format", default="ros2", choices=["ros1", "ros2"], help="bag format (default ros2)")
    f.add_argument("--duration", type=float, help="one short loop (16 m x 8 m) flown in this many seconds")
    f.add_argument(
        "--pattern", choices=["loops"], help="the paper's two 30 m x 15 m loops, ~180 m in 90 s (the default)"
    )
    f.add_argument("--seed", type=int, default=0, help="seed of the IMU noise, textures and image noise")
    f.add_argument("--scale", type=float, default=1.0, help="image resolution relative to 640x480 (default 1)")
    f.add_argument(
        "--gimbal",
        default="moving",
        choices=["moving", "locked"],
        help="moving: sinusoids and +-30 deg slews at up to 60 deg/s per joint (default); locked: held at its mid "
        "position (for scc runs, angles in calibration.yaml flight.joints_locked, rad)",
    )
    f.add_argument("--quiet", action="store_true", help="no progress bar")
    f.set_defaults(func=_cmd_simulate_flight)
    from dcc_fg.vio.command import add_vio_parser

    add_vio_parser(sub)
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
    except yaml.YAMLError as exc:
        print(f"dcc-fg {args.command}: error: malformed YAML: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
