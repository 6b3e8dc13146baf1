"""``dcc-fg vio BAG --calibration C.yaml ... --out OUT``: files in, trajectory files out.

Reads the gimbal calibration (``calibration.yaml`` of ``dcc-fg calibrate`` or ``dcc-fg simulate
flight``) and the IMU configuration (its ``imu:`` section, or a Kalibr ``imu.yaml`` for the noise
plus ``--T-sI`` / a Kalibr camchain with ``T_cam_imu`` for the mount), runs
:func:`~dcc_fg.vio.pipeline.run_vio_bag` with a progress bar showing the real-time factor, and
writes ``OUT/trajectory.tum``, ``OUT/joint_angles.csv`` (dcc, scc) and ``OUT/summary.json``
atomically; nothing is written when the input is bad.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from dcc_fg.model import load_calibration
from dcc_fg.vio.backend import VioOptions, write_vio_outputs
from dcc_fg.vio.pipeline import BagTopics, PipelineOptions, run_vio_bag
from dcc_fg.data.vio import ImuConfig, load_imu_config

#: Kalibr imu.yaml keys -> ImuConfig fields
KALIBR_IMU_KEYS = {
    "accelerometer_noise_density": "accelerometer_noise_density",
    "accelerometer_random_walk": "accelerometer_random_walk",
    "gyroscope_noise_density": "gyroscope_noise_density",
    "gyroscope_random_walk": "gyroscope_random_walk",
    "update_rate": "rate_hz",
}


def _yaml(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file not found")
    data = yaml.safe_load(path.read_text()) or {}
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a YAML mapping")
    return data


def kalibr_imu_config(imu_yaml: Path, T_sI: np.ndarray) -> ImuConfig:
    """IMU noise from a Kalibr ``imu.yaml`` (top level or under ``imu0``) and the mount ``T_sI``."""
    d = _yaml(imu_yaml)
    d = d.get("imu0", d)
    kwargs: dict[str, Any] = {"T_sI": T_sI}
    for key, field in KALIBR_IMU_KEYS.items():
        if key in d:
            kwargs[field] = float(d[key])
        elif key != "update_rate":
            raise ValueError(f"{imu_yaml}: missing field '{key}'")
    return ImuConfig(**kwargs)


def camchain_T_sI(camchain: Path) -> np.ndarray:
    """``T_cam_imu`` of ``cam0`` in a Kalibr camchain-imucam YAML (IMU -> static camera, 4x4)."""
    d = _yaml(camchain)
    cam0 = d.get("cam0")
    if not isinstance(cam0, dict) or "T_cam_imu" not in cam0:
        raise ValueError(f"{camchain}: missing field 'cam0.T_cam_imu' (the IMU -> cam0 transform)")
    T = np.asarray(cam0["T_cam_imu"], dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"{camchain}: 'cam0.T_cam_imu' must be a finite 4x4 matrix")
    return T


def _imu_config(args: argparse.Namespace) -> ImuConfig:
    cal_path = Path(args.calibration)
    if args.imu_yaml:
        if args.camchain:
            T_sI = camchain_T_sI(Path(args.camchain))
        else:
            embedded = load_imu_config(cal_path)
            if embedded is None:
                raise ValueError(
                    f"{cal_path}: no 'imu:' section; with --imu-yaml also give --camchain (Kalibr camchain with "
                    "cam0.T_cam_imu)"
                )
            T_sI = embedded.T_sI
        return kalibr_imu_config(Path(args.imu_yaml), T_sI)
    imu = load_imu_config(cal_path)
    if imu is None:
        raise ValueError(
            f"{cal_path}: no 'imu:' section (T_sI and the IMU noise); add one or pass --imu-yaml and --camchain"
        )
    if args.camchain:
        imu = dataclasses.replace(imu, T_sI=camchain_T_sI(Path(args.camchain)))
    return imu


def _angles(text: str | None, n: int, option: str) -> tuple[float, ...] | None:
    if text is None:
        return None
    try:
        values = tuple(float(x) for x in text.replace(",", " ").split())
    except ValueError:
        raise ValueError(f"{option}: expected {n} numbers (rad), got '{text}'") from None
    if len(values) != n or not all(np.isfinite(values)):
        raise ValueError(f"{option}: expected {n} finite joint angles (rad), got '{text}'")
    return values


def run_vio_command(args: argparse.Namespace) -> int:
    """The ``dcc-fg vio`` subcommand (see :func:`add_vio_parser`)."""
    cal_path = Path(args.calibration)
    if not cal_path.is_file():
        raise FileNotFoundError(f"{cal_path}: calibration file not found")
    bag = Path(args.bag)
    if not bag.exists():
        raise FileNotFoundError(f"{bag}: bag not found")
    cal = load_calibration(cal_path)
    imu = _imu_config(args)
    L = cal.n_joints
    fixed = _angles(args.fixed_joints, L, "--fixed-joints")
    if args.mode == "scc" and fixed is None:
        raise ValueError(f"--mode scc needs --fixed-joints with {L} angles (rad): the locked gimbal position")
    if cal.static_camera is None:
        raise ValueError(f"{cal_path}: no 'cam0' camera model (intrinsics of the static camera)")
    focal = float(np.mean(cal.static_camera.intrinsics[:2]))
    options = VioOptions(
        mode=args.mode,
        sigma=args.pixel_sigma / focal,
        keyframe_every=args.keyframe_every,
        lag=args.lag,
        theta_fixed=fixed,
        theta_initial=_angles(args.initial_joints, L, "--initial-joints"),
    )
    topics = BagTopics(args.imu_topic, args.static_topic, None if args.mode == "mono" else args.dynamic_topic)
    pipeline = PipelineOptions(
        reject_dynamic=not args.no_dynamic_rejection,
        tolerance_ns=int(round(args.sync_tolerance * 1e6)),
        worker=args.frontend,
    )
    bar = None
    show = not args.quiet and sys.stderr.isatty()
    if show:
        from tqdm import tqdm

        bar = tqdm(unit="frame", desc="vio", file=sys.stderr)

    def progress(done: int, total: int, elapsed: float, data_s: float) -> None:
        if bar is None:
            return
        bar.total = total
        bar.n = done
        if data_s > 0:
            bar.set_postfix_str(f"real-time factor {elapsed / data_s:.2f}")
        bar.refresh()

    try:
        result, run = run_vio_bag(bag, cal, imu, options, topics, pipeline, progress=progress if show else None)
    finally:
        if bar is not None:
            bar.close()
    out = Path(args.out)
    write_vio_outputs(out, result, {"calibration": str(cal_path), "run": run})
    s = result.stats
    print(
        f"{args.mode}: {s['keyframes']} keyframes over {s['data_duration_s']:.1f} s in {s['processing_time_s']:.1f} s "
        f"(real-time factor {s['real_time_factor']:.2f}), {s['landmarks']} landmarks, "
        f"{s['failed_updates']} failed updates"
    )
    if args.mode == "dcc" and result.theta.size:
        last = ", ".join(f"{x:.4f}" for x in result.theta[-1])
        print(f"final joint angles [{last}] rad")
    print(
        f"wrote {out / 'trajectory.tum'}, {out / 'summary.json'}"
        + (f", {out / 'joint_angles.csv'}" if args.mode != "mono" and L else "")
    )
    return 0


def add_vio_parser(sub: Any) -> None:
    """Register ``dcc-fg vio`` on an argparse subparsers object."""
    v = sub.add_parser(
        "vio",
        help="gimbal-aware visual-inertial odometry over a ROS1/ROS2 bag",
        description="IMU-preintegrated keyframe fixed-lag smoother (GTSAM) whose states carry the gimbal joint "
        "angles (dcc), or hold them at known fixed angles (scc), or use the static camera only (mono). Reads "
        "sensor_msgs/Imu and two image topics; writes OUT/trajectory.tum (TUM: t[s] tx ty tz qx qy qz qw, body = "
        "IMU frame in a gravity-aligned world), OUT/joint_angles.csv (timestamp_ns,theta_1..theta_L, rad) and "
        "OUT/summary.json. Starts from standstill (the first 0.5 s of IMU at rest).",
    )
    v.add_argument("bag", help="ROS1 .bag file or ROS2 bag folder")
    v.add_argument(
        "--calibration",
        required=True,
        help="calibration.yaml with the chain (joints, tau_s, tau_d, dh), cam0/cam1 intrinsics and, unless "
        "--imu-yaml is given, an 'imu:' section (T_sI 4x4 IMU -> static camera, noise densities)",
    )
    v.add_argument("--imu-yaml", help="Kalibr imu.yaml: noise densities (m/s^2/sqrt(Hz), rad/s/sqrt(Hz)), random walks")
    v.add_argument("--camchain", help="Kalibr camchain-imucam.yaml: takes T_sI from cam0.T_cam_imu")
    v.add_argument("--imu-topic", default="/imu0", help="sensor_msgs/Imu topic (default /imu0)")
    v.add_argument(
        "--static-topic", default="/cam0/image_raw", help="static camera image topic (default /cam0/image_raw)"
    )
    v.add_argument(
        "--dynamic-topic", default="/cam1/image_raw", help="gimbal camera image topic (default /cam1/image_raw)"
    )
    v.add_argument("--mode", default="dcc", choices=["dcc", "scc", "mono"], help="default dcc")
    v.add_argument(
        "--initial-joints",
        metavar="RAD",
        help="dcc: starting guess of the joint angles, e.g. '1.57,0' (rad); by default they are found from the "
        "first frame's static/gimbal matches",
    )
    v.add_argument("--fixed-joints", metavar="RAD", help="scc: the locked joint angles, e.g. '1.57,0' (rad)")
    v.add_argument("--pixel-sigma", type=float, default=1.0, help="feature noise, pixels (1 sigma; default 1)")
    v.add_argument("--keyframe-every", type=int, default=3, help="every n-th frame is a keyframe (default 3)")
    v.add_argument("--lag", type=float, default=1.5, help="smoother window, seconds (default 1.5)")
    v.add_argument(
        "--sync-tolerance", type=float, default=5.0, metavar="MS", help="image pairing tolerance, ms (default 5)"
    )
    v.add_argument(
        "--no-dynamic-rejection",
        action="store_true",
        help="keep every gimbal-camera track (skip the second stage of the two-stage outlier handling)",
    )
    v.add_argument(
        "--frontend",
        default="auto",
        choices=["auto", "inline", "process"],
        help="run the feature tracking inline, or in a second process on another core so it overlaps "
        "the smoother; auto (default) takes the second process when two or more cores are usable. "
        "benchmarks/bench_vio.py measures both on your machine",
    )
    v.add_argument("--out", required=True, help="output folder")
    v.add_argument("--quiet", action="store_true", help="no progress bar")
    v.set_defaults(func=run_vio_command)
