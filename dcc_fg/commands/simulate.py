"""``dcc-fg simulate calibration | flight``: synthetic data sets with ground truth."""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from dcc_fg.commands import common
from dcc_fg.commands.simulate_cluster import CLUSTER_HELP, simulate_cluster_command
from dcc_fg.sim.cluster_flight import FLIGHT_PRESETS, check_flight_cluster, load_flight_cluster
from dcc_fg.sim.cluster_scene import PRESETS as CLUSTER_PRESETS
from dcc_fg.sim.flight_bag import write_flight
from dcc_fg.sim.mechanism_family import describe, family_member
from dcc_fg.sim.render import RenderConfig
from dcc_fg.sim.timing import (
    MAX_OFFSET_S,
    CameraTiming,
    check_jitter,
    check_offsets,
    check_phase,
    check_rates,
    parse_pair,
)
from dcc_fg.sim.trajectory import FlightConfig, locked_gimbal
from dcc_fg.sim.write_dataset import DYNAMIC_TOPIC, STATIC_TOPIC, CalibrationSimSpec, write_calibration_dataset
from dcc_fg.vio.backend import VioOptions

CALIBRATION_SUMMARY = "render a calibration data set of the paper's scenario (images + camchain/target/gimbal + truth)"
CALIBRATION_DESCRIPTION = (
    "Simulates the paper's 2-DOF gimbal calibration scenario (two 640x480 cameras, fx ~ 460 px, "
    "mild radial-tangential distortion, board 0.6-1.2 m away, joint angles on a jittered grid over the joint "
    "ranges) and renders every snapshot's two images through the true camera models, distortion included, "
    "with Gaussian blur and noise. Writes OUT/images/ (folder), OUT/images.bag (ros1) or OUT/images_bag/ "
    "(ros2), plus OUT/camchain.yaml, OUT/target.yaml, OUT/gimbal.yaml (perturbed initial kinematics: "
    "+N(0, 0.03 m) on lengths, +N(0, 10 deg) on angles) and OUT/ground_truth.yaml (true kinematics, true "
    "joint angles in rad per timestamp in ns, true T_ds and T_st per snapshot, 4x4 row-major, metres). "
    "With --random-mechanism SEED the scenario is instead member SEED of a randomized family (dcc_fg.sim."
    "mechanism_family): L = 1-3 joints, link offsets 0 (exactly intersecting axes, 1 in 4) or 1 mm-10 cm, twists "
    "near 90 deg or 20-160 deg, joint ranges +-8 to +-60 deg, random radtan/equidistant cameras (640x480 to "
    "1280x720, 50-90 deg horizontal field of view), a random checkerboard or AprilGrid and board distances "
    "scaled to it; ground_truth.yaml then also holds the drawn 'mechanism'. With --motion continuous the board "
    "and the gimbal keep moving while both cameras record at their own --rates, --phase, --time-offsets "
    "(convention t_imu = t_cam_stamp + t_offset) and --stamp-jitter."
)

FLIGHT_SUMMARY = "render a VIO flight (IMU, static and gimbal camera) into a ROS1/ROS2 bag"
FLIGHT_DESCRIPTION = (
    "A body flying rounded-rectangle loops in a textured box room with a freely moving 2-joint "
    "gimbal: /imu0 (200 Hz), /cam0/image_raw (static) and /cam1/image_raw (gimbal) at 20 Hz, truth on "
    "/ground_truth/pose and /ground_truth/joints; also calibration.yaml (with an imu: section), "
    "ground_truth.tum and ground_truth_joints.csv (gimbal joint angles at each gimbal image's true exposure "
    "time, keyed by its header stamp). --rates, --phase, --time-offsets and --stamp-jitter make the cameras "
    "unsynchronized (convention t_imu = t_cam_stamp + t_offset); the truth is then also in calibration.yaml "
    "flight.timing and ground_truth_frames.csv. --cluster adds cameras (an N-camera cluster): every camera's "
    "images on /camN/image_raw, the cluster's layout in calibration.yaml; a further gimbal chain moves on its own, "
    "its truth on /ground_truth/joints_<chain> and in ground_truth_joints_<chain>.csv."
)
FLIGHT_CLUSTER_HELP = (
    "fly an N-camera cluster instead of the two cameras: a preset, stereo+gimbal (cam0 + cam1 a static stereo "
    "pair 11 cm apart, cam2 the flight's gimbal camera) or gimbal-pair (cam1 the flight's gimbal camera, cam2 a "
    "thermal-like camera 4 cm beside it on the same gimbal), two-gimbals (cam1 the flight's gimbal camera, cam2 "
    "a thermal-like camera on a second 2-joint gimbal gimbal2 mounted 20 cm to the left, moving on its own), or a "
    "cluster calibration YAML file (cameras: / chains:, every camera with intrinsics, 2-joint chains; intrinsics "
    "scaled by --scale). The primary chain and its joint motion are the flight's; every further chain with joints "
    "moves on its own (other sinusoids and slews, locked with --gimbal locked), its truth on "
    "/ground_truth/joints_<chain> and in ground_truth_joints_<chain>.csv; further cameras are triggered with cam0 "
    "(its exposure times and stamps, whatever the timing flags); each camera's images on its rostopic or "
    "/camN/image_raw; calibration.yaml holds the cluster (cameras:/chains:) and flight.cluster"
)


def bounded(kind: type, minimum: float, positive: bool = False) -> Any:
    """An argparse ``type`` that accepts finite numbers >= ``minimum`` (> it when ``positive``)."""

    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a {kind.__name__}, got {text!r}") from None
        ok = math.isfinite(value) and (value > minimum if positive else value >= minimum)
        if not ok:
            raise argparse.ArgumentTypeError(f"must be {'>' if positive else '>='} {minimum:g}, got {text}")
        return value

    return parse


log = logging.getLogger("dcc_fg.simulate")


def _pair_type(flag: str, check: Any) -> Any:
    """An argparse ``type`` for ``A,B`` pairs validated by ``check`` (messages name ``flag``)."""

    def parse(text: str) -> tuple[float, float]:
        try:
            pair = parse_pair(text, flag)
            check(pair)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
        return pair

    return parse


def _number_type(flag: str, check: Any) -> Any:
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{flag} expects a number of seconds, got {text!r}") from None
        try:
            check(value)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
        return value

    return parse


def camera_timing(args: argparse.Namespace) -> CameraTiming:
    """The :class:`CameraTiming` of the ``--rates``, ``--phase``, ``--time-offsets`` and ``--stamp-jitter`` flags."""
    return CameraTiming(args.rates, args.phase, args.time_offsets, args.stamp_jitter)


TIMING_FLAGS = ("--rates", "--phase", "--time-offsets", "--stamp-jitter")


def add_timing_flags(p: argparse.ArgumentParser, where: str) -> None:
    """``--rates``, ``--phase``, ``--time-offsets``, ``--stamp-jitter`` (see :mod:`dcc_fg.sim.timing`)."""
    p.add_argument(
        "--rates",
        type=_pair_type("--rates", check_rates),
        default=CameraTiming.rates,
        metavar="R_STATIC,R_GIMBAL",
        help=f"frame rates of the static and the gimbal camera, Hz, > 0 (default 20,20: synchronized){where}",
    )
    p.add_argument(
        "--phase",
        type=_number_type("--phase", check_phase),
        default=CameraTiming.phase,
        metavar="SECONDS",
        help="start of the gimbal camera's stream relative to the static one's (true exposure times), s (default 0)",
    )
    p.add_argument(
        "--time-offsets",
        type=_pair_type("--time-offsets", check_offsets),
        default=CameraTiming.time_offsets,
        metavar="T_S,T_D",
        help="constant offset of each camera's header stamps from its true exposure time, s, "
        f"|offset| < {MAX_OFFSET_S}; convention t_imu = t_cam_stamp + t_offset (OpenVINS calib_camimu_dt, "
        "Kalibr timeshift_cam_imu): an image exposed at true time t is stamped t - t_offset (default 0,0)",
    )
    p.add_argument(
        "--stamp-jitter",
        type=_number_type("--stamp-jitter", check_jitter),
        default=CameraTiming.stamp_jitter,
        metavar="SECONDS",
        help="standard deviation of zero-mean Gaussian noise added to every header stamp, s, >= 0 (default 0; "
        "a warning if it makes a camera's stamps go backwards)",
    )


SIMULATE_OUT_HELP = (
    "It must not already hold a data set (any of the names this command writes) unless --force, nor be the result "
    "folder of another command. Everything is written into a hidden staging folder and moved into place together "
    "when complete: an error or Ctrl-C leaves the folder as it was"
)


def simulate_calibration_command(args: argparse.Namespace) -> int:
    """``dcc-fg simulate calibration``."""
    if getattr(args, "cluster", None) is not None:
        return simulate_cluster_command(args)
    render = RenderConfig(noise_sigma=args.noise, blur_sigma_px=args.blur)
    seed = args.random_mechanism
    if seed is not None:
        if args.target is not None:
            raise ValueError("--target cannot be combined with --random-mechanism (the family draws the target)")
        if args.joints == 0:
            raise ValueError("--random-mechanism needs --joints 1, 2 or 3 (or none: drawn by the family)")
    target = args.target or "checkerboard"
    timing = camera_timing(args)
    if args.motion == "held" and not timing.is_default:
        raise ValueError(f"{', '.join(TIMING_FLAGS)} need --motion continuous (held snapshots are image pairs)")
    spec = CalibrationSimSpec(
        target, args.format, args.seed, args.snapshots, args.joints, render, args.storage, random_mechanism=seed,
        motion=args.motion, timing=timing,
    )  # fmt: skip
    if seed is not None:
        print(describe(family_member(seed, args.joints, args.snapshots)))
    res = write_calibration_dataset(args.out, spec, force=args.force)
    what = f"{len(res.T_st)} image pairs"
    if res.images is not None:
        what = f"{res.images[0]} static + {res.images[1]} gimbal images of a continuous recording"
    print(
        f"rendered {what} in {res.render_time_s:.1f} s: {res.data}\n"
        f"wrote {res.camchain}, {res.target}, {res.gimbal}, {res.ground_truth}\n"
        f"calibrate with: dcc-fg calibrate {res.data} --camchain {res.camchain} --target {res.target} "
        f"--gimbal {res.gimbal} --out {Path(args.out) / 'calibration'}"
        + (" --sync interpolate" if res.images is not None else "")
    )
    return 0


def simulate_flight_command(args: argparse.Namespace) -> int:
    """``dcc-fg simulate flight``."""
    if args.duration is not None and args.pattern == "loops":
        raise ValueError("--duration and --pattern loops exclude each other (the loops take 90 s)")
    config = FlightConfig.short(args.duration) if args.duration is not None else FlightConfig()
    joints = locked_gimbal() if args.gimbal == "locked" else None
    timing = camera_timing(args)
    if args.cluster is not None:
        check_cluster_arg(args.cluster, args.scale)
    res = write_flight(
        args.out,
        args.format,
        config,
        seed=args.seed,
        scale=args.scale,
        joints=joints,
        progress=not args.quiet,
        force=args.force,
        timing=timing,
        cluster=args.cluster,
    )
    speed = float(np.linalg.norm(res.truth.v_W, axis=1).max()) if len(res.truth.v_W) else 0.0
    limit = VioOptions().max_speed
    if speed > limit:
        log.warning(
            "this flight reaches %.1f m/s, beyond the smoother's default max_speed of %g m/s (a divergence "
            "bound): run vio with --config setting smoother.max_speed above it, or simulate a longer --duration",
            speed,
            limit,
        )
    images = (
        f"{res.frames} frame pairs"
        if timing.is_default
        else f"{res.images[0]} static + {res.images[1]} gimbal images, truth per image in {res.frames_truth}"
    )
    if res.cluster is not None:
        per_topic = ", ".join(f"{t} {n}" for n, t in zip(res.images, res.topics, strict=True))
        images = f"{len(res.topics)} cameras, images per topic: {per_topic}" + (
            "" if timing.is_default else f", truth per image in {res.frames_truth}"
        )
    print(
        f"wrote {res.bag} ({images}, {res.truth.distance:.1f} m, "
        f"{res.render_ms_per_pair:.1f} ms CPU rendering per pair, {res.seconds:.1f} s), {res.calibration}, "
        f"{res.ground_truth}, {', '.join(str(p) for p in (res.joints, *res.chain_joints.values()))}"
    )
    return 0


def check_cluster_arg(spec: str, scale: float) -> None:
    """ValueError naming ``--cluster`` unless ``spec`` is a flight cluster preset or a usable cluster file."""
    if spec not in FLIGHT_PRESETS and not Path(spec).is_file():
        why = (
            f"{spec} is a preset of 'simulate calibration --cluster' only"
            if spec in CLUSTER_PRESETS
            else f"unknown preset {spec!r} and no such file"
        )
        raise ValueError(
            f"--cluster: {why} (flight presets: {', '.join(FLIGHT_PRESETS)}; or a cluster calibration YAML file)"
        )
    try:
        check_flight_cluster(load_flight_cluster(spec, scale))
    except ValueError as exc:
        raise ValueError(f"--cluster: {exc}") from None


def add_calibration_parser(sub: Any, parent: argparse.ArgumentParser) -> None:
    p = common.add_command(
        sub, "calibration", parent, CALIBRATION_SUMMARY, CALIBRATION_DESCRIPTION, simulate_calibration_command
    )
    p.add_argument(
        "--target",
        choices=["checkerboard", "aprilgrid"],
        default=None,
        help="checkerboard: 10x7 inner corners, 0.06 m squares; aprilgrid: 6x6 tag36h11 tags of 0.06 m, "
        "spacing ratio 0.3 (default checkerboard; not allowed with --random-mechanism, which draws the target)",
    )
    p.add_argument(
        "--format",
        choices=["folder", "ros1", "ros2"],
        default="folder",
        help="image folder (cam0/<ns>.png, cam1/<ns>.png), ROS1 .bag or ROS2 bag folder; image topics "
        f"{STATIC_TOPIC} and {DYNAMIC_TOPIC} (default folder)",
    )
    p.add_argument(
        "--storage", choices=["sqlite3", "mcap"], default="sqlite3", help="ROS2 bag storage (default sqlite3)"
    )
    p.add_argument("--out", required=True, help=f"output folder (created). {SIMULATE_OUT_HELP}")
    p.add_argument("--force", action="store_true", help="replace the data set an earlier 'simulate calibration' "
                   "wrote into --out")  # fmt: skip
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="random seed of the scene and the image noise (default 0; with --random-mechanism only of the "
        "image noise)",
    )
    p.add_argument(
        "--random-mechanism",
        type=bounded(int, 0),
        default=None,
        metavar="SEED",
        help="simulate member SEED (>= 0) of the randomized mechanism family instead of the paper's scenario: "
        "mechanism, joint ranges, both cameras' intrinsics, target and distances are drawn from SEED, which "
        "also seeds the scene; prints a one-line description of the draw",
    )
    p.add_argument(
        "--snapshots", type=bounded(int, 1), default=81, help="number of image pairs (snapshots), default 81"
    )
    p.add_argument(
        "--joints",
        type=int,
        default=None,
        choices=[0, 1, 2, 3],
        help="number of gimbal joints L (default 2, or drawn by --random-mechanism, which allows 1-3)",
    )
    p.add_argument(
        "--noise",
        type=bounded(float, 0.0),
        default=RenderConfig.noise_sigma,
        help="image noise sigma, grey levels (default 2)",
    )
    p.add_argument(
        "--blur",
        type=bounded(float, 0.0),
        default=RenderConfig.blur_sigma_px,
        help="Gaussian blur sigma, pixels (default 0.6)",
    )
    p.add_argument(
        "--motion",
        choices=["held", "continuous"],
        default="held",
        help="held: one image pair per snapshot, the rig held still (default); continuous: the board (up to 30 deg/s, "
        "0.4 m/s) and the gimbal joints (up to 20 deg/s) keep moving through the snapshots while both cameras "
        "record at --rates, as a hand-held recording (--snapshots >= 2 waypoints; ground_truth.yaml then holds "
        "the truth at every image's true exposure time under 'images' and the timing under 'motion')",
    )
    add_timing_flags(p, "; with --motion continuous only")
    p.add_argument("--cluster", choices=CLUSTER_PRESETS, default=None, metavar="PRESET", help=CLUSTER_HELP)


def add_flight_parser(sub: Any, parent: argparse.ArgumentParser) -> None:
    f = common.add_command(sub, "flight", parent, FLIGHT_SUMMARY, FLIGHT_DESCRIPTION, simulate_flight_command)
    f.add_argument("--out", required=True, help=f"output folder (created). {SIMULATE_OUT_HELP}")
    f.add_argument("--force", action="store_true", help="replace the flight an earlier 'simulate flight' wrote "
                   "into --out")  # fmt: skip
    f.add_argument("--format", default="ros2", choices=["ros1", "ros2"], help="bag format (default ros2)")
    f.add_argument(
        "--duration",
        type=bounded(float, 0.0, positive=True),
        help="one short loop (16 m x 8 m) flown in this many seconds",
    )
    f.add_argument(
        "--pattern", choices=["loops"], help="the paper's two 30 m x 15 m loops, ~180 m in 90 s (the default)"
    )
    f.add_argument("--seed", type=int, default=0, help="seed of the IMU noise, textures and image noise")
    f.add_argument(
        "--scale",
        type=bounded(float, 0.0, positive=True),
        default=1.0,
        help="image resolution relative to 640x480 (default 1)",
    )
    f.add_argument(
        "--gimbal",
        default="moving",
        choices=["moving", "locked"],
        help="moving: sinusoids and +-30 deg slews at up to 60 deg/s per joint (default); locked: held at its mid "
        "position (for scc runs, angles in calibration.yaml flight.joints_locked, rad)",
    )
    add_timing_flags(f, "; the true timing is recorded in calibration.yaml flight.timing and per image in "
                     "ground_truth_frames.csv")  # fmt: skip
    f.add_argument("--cluster", default=None, metavar="PRESET|FILE", help=FLIGHT_CLUSTER_HELP)


def add_parser(sub: Any, parent: argparse.ArgumentParser) -> None:
    s = sub.add_parser(
        "simulate",
        help="write simulated data sets with ground truth (rendered calibration images, VIO flights)",
        description="Simulated data sets with ground truth. See 'dcc-fg simulate calibration --help'.",
    )
    s_sub = s.add_subparsers(dest="what", required=True)
    add_calibration_parser(s_sub, parent)
    add_flight_parser(s_sub, parent)
