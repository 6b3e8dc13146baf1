"""``dcc-fg simulate flight``: a rendered VIO flight written as a ROS1 or ROS2 bag with its truth.

Output folder ``DIR``:

* ``flight.bag`` (ROS1) or ``flight/`` (ROS2 sqlite3 bag folder) with
  ``/imu0`` (``sensor_msgs/Imu``, 200 Hz, noisy, IMU frame I),
  ``/cam0/image_raw`` (static camera, mono8, 20 Hz), ``/cam1/image_raw`` (gimbal camera),
  and the truth the estimator must not read: ``/ground_truth/pose`` (``geometry_msgs/PoseStamped``,
  T_WI: body in the world, at the IMU rate) and ``/ground_truth/joints`` (``sensor_msgs/JointState``,
  radians, at the IMU rate);
* ``calibration.yaml``: the true chain and cameras (:meth:`GimbalCalibration.to_dict`) plus an
  ``imu:`` section (:meth:`ImuConfig.to_dict`: ``T_sI`` and the IMU noise the flight was made with);
* ``ground_truth.tum`` (``t[s] tx ty tz qx qy qz qw``, body in W, at the IMU rate) and
  ``ground_truth_joints.csv`` (``timestamp_ns,theta_1..theta_L`` at the camera frames).

Times are the simulation's times plus :data:`START_NS` (bags with stamps near zero confuse tools).
Images are rendered and written one frame at a time, in time order with the IMU.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from numpy.typing import NDArray
from tqdm import tqdm

from dcc_fg.data.vio import ImuConfig, ImuSamples, load_imu_config
from dcc_fg.io.bag_writer import BagWriter, joint_names
from dcc_fg.io.output_set import OutputSet
from dcc_fg.io.outputs import write_joint_angles_csv, write_text_atomic
from dcc_fg.io.tum import write_tum
from dcc_fg.model import GimbalCalibration, load_calibration
from dcc_fg.sim.flight_render import WorldRenderer, planes_from_world, render_flight
from dcc_fg.sim.trajectory import (
    FlightConfig,
    FlightTruth,
    JointMotion,
    World,
    default_static_mount,
    flight_calibration,
    simulate_flight,
)
from factors.camera import CameraModel

START_NS = 1_600_000_000 * 1_000_000_000
IMU_TOPIC = "/imu0"
STATIC_TOPIC = "/cam0/image_raw"
DYNAMIC_TOPIC = "/cam1/image_raw"
POSE_TOPIC = "/ground_truth/pose"
JOINT_TOPIC = "/ground_truth/joints"


@dataclass(frozen=True)
class FlightBag:
    """What :func:`write_flight` wrote."""

    bag: Path
    calibration: Path
    ground_truth: Path
    joints: Path
    truth: FlightTruth
    frames: int
    render_ms_per_pair: float  # CPU time of the process per rendered image pair
    seconds: float


def scale_camera(cam: CameraModel, scale: float) -> CameraModel:
    """The same lens at ``scale`` times the resolution (pixel centres at integer coordinates)."""
    if scale == 1.0:
        return cam
    fx, fy, cx, cy = cam.intrinsics
    w, h = cam.resolution
    return dataclasses.replace(
        cam,
        intrinsics=(fx * scale, fy * scale, (cx + 0.5) * scale - 0.5, (cy + 0.5) * scale - 0.5),
        resolution=(int(round(w * scale)), int(round(h * scale))),
    )


#: Comment line of ``ground_truth.tum``.
TUM_COMMENT = "t[s] tx ty tz qx qy qz qw (body/IMU frame in W)"


def scaled_flight_calibration(scale: float) -> GimbalCalibration:
    """The flight's gimbal and cameras (:func:`flight_calibration`) at ``scale`` times the resolution."""
    cal0 = flight_calibration()
    assert cal0.static_camera is not None and cal0.dynamic_camera is not None
    return dataclasses.replace(
        cal0,
        static_camera=scale_camera(cal0.static_camera, scale),
        dynamic_camera=scale_camera(cal0.dynamic_camera, scale),
    )


def _write_flight_bag(
    bag_path: Path,
    fmt: Literal["ros1", "ros2"],
    truth: FlightTruth,
    frames: Iterator[tuple[int, NDArray[np.uint8], NDArray[np.uint8]]],
    progress: bool,
) -> tuple[int, float]:
    """IMU, ground-truth pose and joints at every IMU sample, and the rendered image pairs at the
    frame times, in time order (stamps ``START_NS`` + simulation time).

    Returns:
        (image pairs written, CPU seconds spent rendering them).
    """
    frame_set = {int(t): k for k, t in enumerate(truth.frame_t_ns)}
    names = joint_names(truth.theta.shape[1])
    render_s = 0.0
    n_frames = 0
    with (
        tqdm(total=len(truth.frame_t_ns), unit="frame", desc="rendering", disable=not progress) as bar,
        BagWriter(bag_path, 1 if fmt == "ros1" else 2) as bag,
    ):
        for i, t in enumerate(truth.t_ns):
            stamp = START_NS + int(t)
            bag.imu(IMU_TOPIC, stamp, truth.imu.acc[i], truth.imu.gyro[i], "imu0")
            bag.pose(POSE_TOPIC, stamp, truth.T_WI[i], "world")
            bag.joints(JOINT_TOPIC, stamp, truth.theta[i], names)
            if int(t) in frame_set:
                r0 = time.process_time()
                t_frame, img_s, img_d = next(frames)
                render_s += time.process_time() - r0
                if t_frame != int(t):
                    raise RuntimeError(f"rendered frame at {t_frame} ns, expected {int(t)} ns")
                bag.image(STATIC_TOPIC, stamp, img_s, "cam0")
                bag.image(DYNAMIC_TOPIC, stamp, img_d, "cam1")
                n_frames += 1
                bar.update(1)
    return n_frames, render_s


def _calibration_yaml(
    cal: GimbalCalibration, imu: ImuConfig, truth: FlightTruth, config: FlightConfig, seed: int, scale: float
) -> dict[str, Any]:
    """``calibration.yaml``: the true chain and cameras, the ``imu:`` section and a ``flight:`` record."""
    locked = bool(np.ptp(truth.theta, axis=0).max() == 0.0)
    d = cal.to_dict()
    d["imu"] = imu.to_dict()
    d["flight"] = {
        "seed": seed,
        "duration_s": config.duration,
        "distance_m": truth.distance,
        "scale": scale,
        "start_ns": START_NS,
        "gimbal": "locked" if locked else "moving",
        "joints_locked": [float(x) for x in truth.theta[0]] if locked else None,
        "topics": {
            "imu": IMU_TOPIC,
            "static": STATIC_TOPIC,
            "dynamic": DYNAMIC_TOPIC,
            "pose": POSE_TOPIC,
            "joints": JOINT_TOPIC,
        },
    }
    return d


def sensor_covering(imu: ImuConfig, samples: ImuSamples) -> ImuConfig:
    """``imu`` with its measurement ranges (``acc_range`` m/s^2, ``gyro_range`` rad/s) widened to 1.25x
    the largest simulated sample where the flight exceeds them: the simulated sensor does not
    saturate, and the calibration.yaml written with the flight says so (a short, fast flight's
    corners reach beyond a real 16 g accelerometer)."""
    acc_max = float(np.max(np.abs(samples.acc))) if len(samples) else 0.0
    gyro_max = float(np.max(np.abs(samples.gyro))) if len(samples) else 0.0
    return dataclasses.replace(
        imu,
        acc_range=max(imu.acc_range, 1.25 * acc_max),
        gyro_range=max(imu.gyro_range, 1.25 * gyro_max),
    )


def write_flight(
    out: str | Path,
    fmt: Literal["ros1", "ros2"] = "ros2",
    config: FlightConfig | None = None,
    seed: int = 0,
    scale: float = 1.0,
    noise_sigma: float = 2.0,
    joints: JointMotion | None = None,
    imu: ImuConfig | None = None,
    progress: bool = False,
    force: bool = False,
) -> FlightBag:
    """Simulate, render and write a flight (see the module docstring).

    The files are written as one output set (:class:`~dcc_fg.io.output_set.OutputSet`, command
    ``simulate flight``): into a staging folder, moved into ``out`` only when everything is written
    (an interrupted rendering leaves ``out`` as it was).

    Args:
        out: output folder (created). It must not hold any of the flight's names (``flight``,
            ``calibration.yaml``, ...) nor be another command's result folder.
        fmt: ``ros1`` (``flight.bag``) or ``ros2`` (``flight/``).
        config: flight pattern (default: the paper's two loops, 90 s).
        seed: seeds the IMU noise, the textures and the image noise.
        scale: image resolution relative to the 640x480 cameras of the calibration simulator.
        noise_sigma: image noise, grey levels (1 sigma).
        joints, imu: gimbal motion and IMU noise (defaults of :mod:`dcc_fg.sim.trajectory`).
        progress: show a tqdm progress bar.
        force: replace a flight written earlier into ``out`` by ``simulate flight``.
    """
    if fmt not in ("ros1", "ros2"):
        raise ValueError(f"format must be ros1 or ros2, got {fmt!r}")
    if not 0.1 <= scale <= 2.0:
        raise ValueError(f"scale must be within [0.1, 2], got {scale}")
    t_start = time.perf_counter()
    out = Path(out)
    outputs = OutputSet(
        out,
        "simulate flight",
        replace_previous=force,
        replace_hint="pass --force to replace the flight simulated there before",
        replace_unowned=False,
    )
    config = config or FlightConfig()
    T_sI = default_static_mount()
    imu = dataclasses.replace(imu or ImuConfig(), T_sI=T_sI)
    truth = simulate_flight(config, imu, joints, seed=seed)
    imu = sensor_covering(imu, truth.imu)
    cal = scaled_flight_calibration(scale)
    renderer = WorldRenderer(planes_from_world(World.around(config)), seed=seed)
    frames = render_flight(renderer, truth, cal, T_sI, noise_sigma=noise_sigma, seed=seed + 1)
    names = ("flight.bag" if fmt == "ros1" else "flight", "calibration.yaml", "ground_truth.tum",
             "ground_truth_joints.csv")  # fmt: skip
    with outputs:
        stage = outputs.path
        n_frames, render_s = _write_flight_bag(stage / names[0], fmt, truth, frames, progress)
        d = _calibration_yaml(cal, imu, truth, config, seed, scale)
        write_text_atomic(stage / names[1], yaml.safe_dump(d, sort_keys=False))
        write_tum(stage / names[2], truth.t_ns + START_NS, truth.T_WI, TUM_COMMENT, quaternion_decimals=12,
                  w_nonnegative=True)  # fmt: skip
        idx = truth.index_of(truth.frame_t_ns)
        write_joint_angles_csv(stage / names[3], truth.frame_t_ns + START_NS, truth.theta[idx])
    bag_path, cal_path, gt_path, joints_path = (out / n for n in names)
    return FlightBag(
        bag=bag_path,
        calibration=cal_path,
        ground_truth=gt_path,
        joints=joints_path,
        truth=truth,
        frames=n_frames,
        render_ms_per_pair=1e3 * render_s / max(n_frames, 1),
        seconds=time.perf_counter() - t_start,
    )


def load_flight_calibration(path: str | Path) -> tuple[GimbalCalibration, ImuConfig]:
    """The calibration and IMU configuration of a ``calibration.yaml`` with an ``imu:`` section."""
    imu = load_imu_config(path)
    if imu is None:
        raise ValueError(f"{path}: no 'imu:' section (T_sI and IMU noise are needed for VIO)")
    return load_calibration(path), imu
