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
  ``ground_truth_joints.csv`` (``timestamp_ns,theta_1..theta_L``: one row per gimbal image,
  ``timestamp_ns`` = that image's *header stamp*, the angles at its *true exposure time*).

Camera timing (:class:`~dcc_fg.sim.timing.CameraTiming`, flags ``--rates``, ``--phase``,
``--time-offsets``, ``--stamp-jitter``): by default both cameras run at 20 Hz with identical stamps
on IMU sample times (the bag, ``calibration.yaml`` and the CSV files are then exactly those of the
synchronized simulator). Otherwise each camera renders at its own true exposure times (the body
pose and the joint angles at that instant, between IMU samples from the analytic trajectory) and
is stamped with the convention ``t_imu = t_cam_stamp + t_offset`` (an image exposed at true IMU
time t carries the stamp ``t - t_offset``, plus jitter); the IMU and truth topics are unchanged.
The truth then also holds

* ``calibration.yaml`` ``flight.timing``: ``convention``, ``rates_hz`` {static, dynamic},
  ``phase_s``, ``time_offsets_s`` {static, dynamic}, ``stamp_jitter_s``, ``images`` {static,
  dynamic} (counts) and ``frames_file``. It is a record of the simulation, not a calibration
  field: an estimator must not start from it;
* ``ground_truth_frames.csv``: ``camera,stamp_ns,exposure_ns,tx,ty,tz,qx,qy,qz,qw,theta_1..theta_L``,
  one row per image in exposure order (camera 0 static, 1 gimbal; header stamp and true exposure
  time in ns; body pose T_WI and joint angles at the exposure).

N-camera clusters (``cluster=`` / ``--cluster``, :mod:`dcc_fg.sim.cluster_flight`): a preset
(``stereo+gimbal``, ``gimbal-pair``) or a cluster calibration file adds cameras to the rig; its
primary chain and primary gimbal camera are the flight's, so the joint motion, the IMU, the truth
and the cam0 and primary gimbal images are those of the flight without the cluster (same seed).
Every further camera is triggered with cam0: it is rendered at cam0's true exposure times and
carries cam0's header stamps (whatever the timing flags do to the primary gimbal camera), with
image noise of its own stream. Topics: each camera's ``rostopic`` or ``/camN/image_raw``
(:func:`~dcc_fg.data.cameras.default_topic`; frame id ``camN``); the primary gimbal camera is the
"dynamic" camera of ``ground_truth_joints.csv`` and ``ground_truth_frames.csv`` (which list cam0
and the primary gimbal camera only: a further camera's truth is that of cam0's image). Then
``calibration.yaml`` holds the cluster in the ``cameras:`` / ``chains:`` form
(:meth:`GimbalCalibration.to_dict` of the layout), the ``imu:`` section, and ``flight.cluster``:
``source`` (preset or file), ``primary`` (the primary gimbal camera) and ``topics`` (camera -> topic).

Further gimbal chains (e.g. ``two-gimbals``: cam2 on chain ``gimbal2``): every further chain with
joints moves on its own (:func:`~dcc_fg.sim.cluster_flight.further_chain_motions`; the primary
chain's motion, IMU and truth stay those of the flight without the cluster), and its cameras are
rendered at that chain's angles at each exposure. Its truth, named with the suffix ``_<chain>``:
``/ground_truth/joints_<chain>`` (``sensor_msgs/JointState``, radians, at the IMU rate, like
``/ground_truth/joints``) and ``ground_truth_joints_<chain>.csv`` (``timestamp_ns,theta_1..theta_L``:
one row per image of the chain's first camera, keyed by its header stamp, the angles at its true
exposure time, like ``ground_truth_joints.csv``). ``flight.cluster`` then also holds ``chains``:
chain -> ``camera`` (that first camera), ``joints_topic``, ``joints_file`` and ``gimbal``
(``moving`` / ``locked``).

Times are the simulation's times plus :data:`START_NS` (bags with stamps near zero confuse tools).
Images are rendered and written one at a time, in time order with the IMU; an image's record time
(bag order) is its true exposure time, its header stamp the camera's stamp.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from dcc_fg.data.cameras import RunCamera, default_topic
from dcc_fg.data.vio import ImuConfig, ImuSamples, load_imu_config
from dcc_fg.io.bag_writer import BagWriter, image_message, joint_names
from dcc_fg.io.output_set import OutputSet
from dcc_fg.io.outputs import write_joint_angles_csv, write_text_atomic
from dcc_fg.io.tum import write_tum
from dcc_fg.model import GimbalCalibration, load_calibration
from dcc_fg.sim.cluster_flight import check_flight_cluster, further_chain_motions, load_flight_cluster, scale_camera
from dcc_fg.sim.flight_render import WorldRenderer, planes_from_world
from dcc_fg.sim.timing import CameraTiming
from dcc_fg.sim.trajectory import (
    FlightConfig,
    FlightTruth,
    JointMotion,
    World,
    chain_theta_at,
    default_static_mount,
    flight_calibration,
    simulate_flight,
    truth_at,
)
from factors.chain import inv_se3

FloatArray = NDArray[np.float64]

START_NS = 1_600_000_000 * 1_000_000_000
IMU_TOPIC = "/imu0"
STATIC_TOPIC = "/cam0/image_raw"
DYNAMIC_TOPIC = "/cam1/image_raw"
POSE_TOPIC = "/ground_truth/pose"
JOINT_TOPIC = "/ground_truth/joints"
JOINTS_NAME = "ground_truth_joints.csv"


def chain_joint_topic(chain: str) -> str:
    """Truth topic of a further chain's joint angles: ``/ground_truth/joints_<chain>``."""
    return f"{JOINT_TOPIC}_{chain}"


def chain_joints_name(chain: str) -> str:
    """Truth file of a further chain's joint angles: ``ground_truth_joints_<chain>.csv``."""
    return f"ground_truth_joints_{chain}.csv"


#: Per-image truth of an unsynchronized flight.
FRAMES_NAME = "ground_truth_frames.csv"


@dataclass(frozen=True)
class FlightBag:
    """What :func:`write_flight` wrote."""

    bag: Path
    calibration: Path
    ground_truth: Path
    joints: Path
    truth: FlightTruth
    frames: int  # static camera images (image pairs of a synchronized flight)
    render_ms_per_pair: float  # CPU time of the process per rendered image pair (per two images)
    seconds: float
    images: tuple[int, ...] = (0, 0)  # images written per camera, by run index (static, gimbal, further cameras)
    timing: CameraTiming = CameraTiming()
    frames_truth: Path | None = None  # ground_truth_frames.csv (unsynchronized timing only)
    topics: tuple[str, ...] = (STATIC_TOPIC, DYNAMIC_TOPIC)  # image topic per run index
    cluster: GimbalCalibration | None = None  # the true cluster of a --cluster flight (None: two cameras)
    chain_joints: dict[str, Path] = field(default_factory=dict)  # further chain -> ground_truth_joints_<chain>.csv


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


@dataclass(frozen=True)
class CameraFrame:
    """One image of a flight: ``camera`` its run index (0 static, 1 primary gimbal camera, 2.. further
    cameras of a cluster, :mod:`dcc_fg.data.cameras`), its true exposure time and header
    stamp (int64 ns from the start of the simulation, without :data:`START_NS`), and the truth at
    the exposure: ``T_WI`` (4, 4) body in the world, ``theta`` (L,) the primary chain's joint angles
    and ``chains`` further chain -> (L,) its joint angles (rad; empty for a flight with one gimbal)."""

    camera: int
    exposure_ns: int
    stamp_ns: int
    T_WI: FloatArray
    theta: FloatArray
    chains: dict[str, FloatArray] = field(default_factory=dict)


def camera_frames(truth: FlightTruth, timing: CameraTiming, seed: int, extra: Sequence[int] = ()) -> list[CameraFrame]:
    """Both cameras' frames (:meth:`CameraTiming.streams` over the flight, jitter drawn from
    ``seed``) with the truth at their exposure times, in exposure order (static first on ties, then
    by run index). ``extra``: run indices of further cameras triggered with the static camera (its
    exposure times and header stamps). Every frame carries the further chains' angles too
    (:func:`~dcc_fg.sim.trajectory.chain_theta_at`)."""
    streams = timing.streams(int(truth.t_ns[-1]), np.random.default_rng([seed, 15]))
    frames = []
    for s in streams:
        T_WI, theta = truth_at(truth, s.exposure_ns)
        chains = chain_theta_at(truth, s.exposure_ns)
        for camera in (s.camera, *extra) if s.camera == 0 else (s.camera,):
            frames += [
                CameraFrame(camera, int(e), int(st), T, th, {name: a[k] for name, a in chains.items()})
                for k, (e, st, T, th) in enumerate(zip(s.exposure_ns, s.stamp_ns, T_WI, theta, strict=True))
            ]
    frames.sort(key=lambda f: (f.exposure_ns, f.camera))
    return frames


def render_frames(
    renderer: WorldRenderer,
    frames: list[CameraFrame],
    calibration: GimbalCalibration,
    T_sI: FloatArray,
    noise_sigma: float = 2.0,
    seed: int = 0,
    extra: Sequence[RunCamera] = (),
) -> Iterator[NDArray[np.uint8]]:
    """The image of every frame, in order: the static camera at ``T_sW = T_sI inv(T_WI)``, the gimbal
    camera at ``T_ds(theta) T_sW``, a further camera ``c`` of ``extra`` (run index ``c.index``) at
    ``c.T_cs_at(theta) T_sW`` (on a further chain, ``c.slot`` >= 1: at that chain's angles
    ``chains[c.chain]`` of the frame), each with the truth at the frame's exposure time. Image noise of the
    static and gimbal cameras comes from one generator seeded ``seed`` in frame order, so
    synchronized frames get the same images as :func:`~dcc_fg.sim.flight_render.render_flight`
    (further cameras draw from a generator of their own and leave those images unchanged)."""
    cams = {0: calibration.static_camera, 1: calibration.dynamic_camera}
    if cams[0] is None or cams[1] is None:
        raise ValueError("the calibration must carry both camera models to render a flight")
    further = {c.index: c for c in extra}
    rng = np.random.default_rng(seed)
    rng_extra = np.random.default_rng([seed, 16])
    for f in frames:
        T_sW = T_sI @ inv_se3(f.T_WI)
        if f.camera in further:
            cam = further[f.camera]
            theta = f.theta
            if cam.on_gimbal and cam.slot >= 1:
                if cam.chain not in f.chains:
                    raise ValueError(f"{cam.name} is on chain {cam.chain!r}, which the flight does not move")
                theta = f.chains[cam.chain]
            yield renderer.render(cam.model, cam.T_cs_at(theta) @ T_sW, noise_sigma, rng_extra)
            continue
        T_cW = T_sW if f.camera == 0 else calibration.T_ds(f.theta) @ T_sW
        yield renderer.render(cams[f.camera], T_cW, noise_sigma, rng)


def _write_flight_bag(
    bag_path: Path,
    fmt: Literal["ros1", "ros2"],
    truth: FlightTruth,
    frames: list[CameraFrame],
    images: Iterator[NDArray[np.uint8]],
    progress: bool,
    topics: Sequence[str] = (STATIC_TOPIC, DYNAMIC_TOPIC),
    frame_ids: Sequence[str] = ("cam0", "cam1"),
) -> tuple[tuple[int, ...], float]:
    """IMU, ground-truth pose and joints (the primary chain's, then every further chain's of
    ``truth.extra_theta`` on :func:`chain_joint_topic`) at every IMU sample, and the rendered images,
    in time order.

    Header stamps are ``START_NS`` + the sample time (IMU, truth) or + the frame's header stamp
    (images); an image's record time (its place in the bag) is ``START_NS`` + its true exposure time,
    as if it arrived without latency (on ties: IMU, static, gimbal, further cameras). ``topics`` and
    ``frame_ids``: per run index.

    Returns:
        (images written per camera (by run index), CPU seconds spent rendering them).
    """
    names = joint_names(truth.theta.shape[1])
    further = [(chain_joint_topic(c), th, joint_names(th.shape[1])) for c, th in truth.extra_theta.items()]
    render_s = 0.0
    counts = [0] * len(topics)
    k = 0
    with (
        tqdm(total=len(frames), unit="image", desc="rendering", disable=not progress) as bar,
        BagWriter(bag_path, 1 if fmt == "ros1" else 2) as bag,
    ):

        def flush(until_ns: int, inclusive: bool) -> None:
            nonlocal k, render_s
            while k < len(frames) and (
                frames[k].exposure_ns < until_ns or (inclusive and frames[k].exposure_ns == until_ns)
            ):
                f = frames[k]
                r0 = time.process_time()
                img = next(images)
                render_s += time.process_time() - r0
                msgtype, msg = image_message(bag.typestore, img, START_NS + f.stamp_ns, frame_ids[f.camera])
                bag.write(topics[f.camera], msgtype, START_NS + f.exposure_ns, msg)
                counts[f.camera] += 1
                k += 1
                bar.update(1)

        for i, t in enumerate(truth.t_ns):
            flush(int(t), inclusive=False)
            stamp = START_NS + int(t)
            bag.imu(IMU_TOPIC, stamp, truth.imu.acc[i], truth.imu.gyro[i], "imu0")
            bag.pose(POSE_TOPIC, stamp, truth.T_WI[i], "world")
            bag.joints(JOINT_TOPIC, stamp, truth.theta[i], names)
            for topic, th, th_names in further:
                bag.joints(topic, stamp, th[i], th_names)
            flush(int(t), inclusive=True)
        if k != len(frames):
            raise RuntimeError(f"{len(frames) - k} images after the last IMU sample")
    return tuple(counts), render_s


def write_frames_csv(path: Path, frames: list[CameraFrame]) -> None:
    """``ground_truth_frames.csv``: one row per image, in exposure order (module docstring)."""
    L = frames[0].theta.size if frames else 0
    head = ["camera", "stamp_ns", "exposure_ns", "tx", "ty", "tz", "qx", "qy", "qz", "qw"]
    rows = [",".join(head + [f"theta_{j + 1}" for j in range(L)])]
    for f in frames:
        q = Rotation.from_matrix(f.T_WI[:3, :3]).as_quat(canonical=True)
        vals = [*f.T_WI[:3, 3], *q, *f.theta]
        rows.append(
            f"{f.camera},{START_NS + f.stamp_ns},{START_NS + f.exposure_ns}," + ",".join(f"{x:.12g}" for x in vals)
        )
    write_text_atomic(path, "\n".join(rows) + "\n")


def read_frames_csv(path: str | Path) -> dict[str, NDArray[Any]]:
    """``ground_truth_frames.csv`` read back: ``camera`` (N,) int, ``stamp_ns`` and ``exposure_ns``
    (N,) int64 (with :data:`START_NS`), ``T_WI`` (N, 4, 4), ``theta`` (N, L)."""
    lines = Path(path).read_text().splitlines()
    if not lines or not lines[0].startswith("camera,stamp_ns,exposure_ns"):
        raise ValueError(f"{path}: expected a header 'camera,stamp_ns,exposure_ns,...'")
    cols = [ln.split(",") for ln in lines[1:] if ln.strip()]
    ints = np.array([[int(c[0]), int(c[1]), int(c[2])] for c in cols], dtype=np.int64).reshape(-1, 3)
    vals = np.array([[float(x) for x in c[3:]] for c in cols], dtype=float).reshape(len(cols), -1)
    T = np.tile(np.eye(4), (len(cols), 1, 1))
    if len(cols):
        T[:, :3, :3] = Rotation.from_quat(vals[:, 3:7]).as_matrix()
        T[:, :3, 3] = vals[:, :3]
    return {"camera": ints[:, 0], "stamp_ns": ints[:, 1], "exposure_ns": ints[:, 2], "T_WI": T,
            "theta": vals[:, 7:]}  # fmt: skip


def _calibration_yaml(
    cal: GimbalCalibration,
    imu: ImuConfig,
    truth: FlightTruth,
    config: FlightConfig,
    seed: int,
    scale: float,
    timing: CameraTiming | None = None,
    images: tuple[int, ...] = (0, 0),
    cluster: dict[str, Any] | None = None,
    topics: Sequence[str] = (STATIC_TOPIC, DYNAMIC_TOPIC),
) -> dict[str, Any]:
    """``calibration.yaml``: the true chain and cameras, the ``imu:`` section and a ``flight:`` record
    (with ``flight.timing`` for a timing other than the synchronized default, ``flight.cluster`` =
    ``cluster`` for a cluster flight). ``topics``: the static and the primary gimbal camera's."""
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
            "static": topics[0],
            "dynamic": topics[1],
            "pose": POSE_TOPIC,
            "joints": JOINT_TOPIC,
        },
    }
    if cluster is not None:
        d["flight"]["cluster"] = cluster
    if timing is not None and not timing.is_default:
        d["flight"]["timing"] = {
            **timing.to_dict(),
            "images": {"static": images[0], "dynamic": images[1]},
            "frames_file": FRAMES_NAME,
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
    timing: CameraTiming | None = None,
    cluster: str | Path | None = None,
    extra_joints: Mapping[str, JointMotion] | None = None,
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
        timing: the cameras' rates, phase, time offsets and stamp jitter
            (:class:`~dcc_fg.sim.timing.CameraTiming`; default: both at 20 Hz, synchronized). The
            jitter is drawn from ``seed``.
        cluster: an N-camera cluster instead of the two cameras: a preset of
            :data:`~dcc_fg.sim.cluster_flight.FLIGHT_PRESETS` or a cluster calibration file
            (:func:`~dcc_fg.sim.cluster_flight.load_flight_cluster`; its camera models scaled by
            ``scale``). Further cameras follow cam0's timing (module docstring). Every further chain
            with joints moves with :func:`~dcc_fg.sim.cluster_flight.further_chain_motions`.
        extra_joints: motions of further chains of ``cluster`` (chain name -> motion, ``joints``'
            number of joints) replacing those defaults.
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
    joints = joints or JointMotion()
    cal = scaled_flight_calibration(scale) if cluster is None else load_flight_cluster(cluster, scale)
    extra = () if cluster is None else check_flight_cluster(cal, joints.n_joints)
    motions = {} if cluster is None else _chain_motions(cal, joints, extra_joints, cluster)
    if cluster is None and extra_joints:
        raise ValueError("extra_joints need a cluster with further chains (cluster=...)")
    topics, frame_ids, record = (STATIC_TOPIC, DYNAMIC_TOPIC), ("cam0", "cam1"), None
    if cluster is not None:
        topics, frame_ids, record = _cluster_topics(cal, extra, cluster, motions)
    T_sI = default_static_mount()
    imu = dataclasses.replace(imu or ImuConfig(), T_sI=T_sI)
    truth = simulate_flight(config, imu, joints, seed=seed, extra_joints=motions)
    imu = sensor_covering(imu, truth.imu)
    renderer = WorldRenderer(planes_from_world(World.around(config)), seed=seed)
    timing = timing or CameraTiming()
    frames = camera_frames(truth, timing, seed, [c.index for c in extra])
    images = render_frames(renderer, frames, cal, T_sI, noise_sigma=noise_sigma, seed=seed + 1, extra=extra)
    names = ("flight.bag" if fmt == "ros1" else "flight", "calibration.yaml", "ground_truth.tum",
             JOINTS_NAME)  # fmt: skip
    gimbal = [f for f in frames if f.camera == 1]
    chain_camera = {c: _first_camera_on(extra, c) for c in motions}  # run index of each chain's first camera
    with outputs:
        stage = outputs.path
        counts, render_s = _write_flight_bag(stage / names[0], fmt, truth, frames, images, progress, topics, frame_ids)
        d = _calibration_yaml(cal, imu, truth, config, seed, scale, timing, counts, record, topics)
        write_text_atomic(stage / names[1], yaml.safe_dump(d, sort_keys=False))
        write_tum(stage / names[2], truth.t_ns + START_NS, truth.T_WI, TUM_COMMENT, quaternion_decimals=12,
                  w_nonnegative=True)  # fmt: skip
        write_joint_angles_csv(
            stage / names[3],
            np.array([START_NS + f.stamp_ns for f in gimbal], dtype=np.int64),
            np.array([f.theta for f in gimbal]).reshape(len(gimbal), truth.theta.shape[1]),
        )
        for c, index in chain_camera.items():
            rows = [f for f in frames if f.camera == index]
            write_joint_angles_csv(
                stage / chain_joints_name(c),
                np.array([START_NS + f.stamp_ns for f in rows], dtype=np.int64),
                np.array([f.chains[c] for f in rows]).reshape(len(rows), truth.extra_theta[c].shape[1]),
            )
        if not timing.is_default:
            write_frames_csv(stage / FRAMES_NAME, [f for f in frames if f.camera < 2])
    bag_path, cal_path, gt_path, joints_path = (out / n for n in names)
    return FlightBag(
        bag=bag_path,
        calibration=cal_path,
        ground_truth=gt_path,
        joints=joints_path,
        truth=truth,
        frames=counts[0],
        render_ms_per_pair=2e3 * render_s / max(sum(counts), 1),
        seconds=time.perf_counter() - t_start,
        images=counts,
        timing=timing,
        frames_truth=None if timing.is_default else out / FRAMES_NAME,
        topics=tuple(topics),
        cluster=None if cluster is None else cal,
        chain_joints={c: out / chain_joints_name(c) for c in motions},
    )


def _chain_motions(
    cal: GimbalCalibration, joints: JointMotion, given: Mapping[str, JointMotion] | None, spec: str | Path
) -> dict[str, JointMotion]:
    """The motion of every further chain of a cluster flight: :func:`further_chain_motions`, with the
    ones ``given`` replacing them (ValueError for a chain the flight does not move or a wrong L)."""
    motions = further_chain_motions(cal, joints)
    for name, motion in (given or {}).items():
        if name not in motions:
            moved = ", ".join(motions) or "none"
            raise ValueError(f"{spec}: extra_joints for {name!r}, not a further chain with joints (those: {moved})")
        L = cal.cluster().chain(name).n_joints
        if motion.n_joints != L:
            raise ValueError(f"{spec}: extra_joints[{name!r}] moves {motion.n_joints} joint(s), the chain has {L}")
        motions[name] = motion
    return motions


def _first_camera_on(extra: Sequence[RunCamera], chain: str) -> int:
    """Run index of the first camera of ``extra`` on the further chain ``chain``."""
    return next(c.index for c in extra if c.on_gimbal and c.slot >= 1 and c.chain == chain)


def _cluster_topics(
    cal: GimbalCalibration,
    extra: Sequence[RunCamera],
    spec: str | Path,
    motions: Mapping[str, JointMotion] | None = None,
) -> tuple[list[str], list[str], dict[str, Any]]:
    """Image topics and frame ids per run index (cam0, the primary gimbal camera, ``extra``) of a
    cluster flight, and its ``flight.cluster`` record (with ``chains`` when further chains move:
    ``motions``). ValueError when two cameras share a topic (or use the IMU or a truth topic)."""
    cluster = cal.cluster()
    primary = cluster.primary_gimbal_camera
    names = ["cam0", primary, *(c.name for c in extra)]
    topics = [cluster.camera(n).rostopic or default_topic(n) for n in names]
    assert [c.index for c in extra] == list(range(2, 2 + len(extra)))
    motions = motions or {}
    taken = (IMU_TOPIC, POSE_TOPIC, JOINT_TOPIC, *(chain_joint_topic(c) for c in motions))
    if len(set(topics)) != len(topics) or set(topics) & set(taken):
        listed = ", ".join(f"{n}: {t}" for n, t in zip(names, topics, strict=True))
        raise ValueError(
            f"{spec}: every camera needs an image topic of its own, not {', '.join(taken)} either ({listed})"
        )
    by_name = dict(zip(names, topics, strict=True))
    record = {
        "source": str(spec),
        "primary": primary,
        "topics": {n: by_name[n] for n in cluster.camera_names},
    }
    if motions:
        record["chains"] = {
            c: {
                "camera": names[_first_camera_on(extra, c)],
                "joints_topic": chain_joint_topic(c),
                "joints_file": chain_joints_name(c),
                "gimbal": "locked" if m.sin_amplitude == 0.0 and m.slew_amplitude == 0.0 else "moving",
            }
            for c, m in motions.items()
        }
    return topics, names, record


def load_flight_calibration(path: str | Path) -> tuple[GimbalCalibration, ImuConfig]:
    """The calibration and IMU configuration of a ``calibration.yaml`` with an ``imu:`` section.

    A cluster flight's file (``flight.cluster``, written by ``simulate flight --cluster``) gives its
    whole cluster (:meth:`GimbalCalibration.cluster`; cam1 may be static); any other file must be
    usable as a static camera cam0 and a gimbal camera cam1
    (:meth:`GimbalCalibration.require_two_cameras` with ``allow_subset``).
    """
    imu = load_imu_config(path)
    if imu is None:
        raise ValueError(f"{path}: no 'imu:' section (T_sI and IMU noise are needed for VIO)")
    cal = load_calibration(path)
    if _is_cluster_flight(path):
        return cal, imu
    return cal.require_two_cameras("flight simulation", allow_subset=True), imu


def _is_cluster_flight(path: str | Path) -> bool:
    """The ``calibration.yaml`` has a ``flight.cluster`` record (a flight of ``simulate flight --cluster``)."""
    with Path(path).open() as f:
        d = yaml.safe_load(f)
    flight = d.get("flight") if isinstance(d, dict) else None
    return isinstance(flight, dict) and isinstance(flight.get("cluster"), dict)


def load_flight_timing(path: str | Path) -> CameraTiming:
    """The true camera timing of a simulated flight from its ``calibration.yaml`` (``flight.timing``;
    the synchronized default when there is none, as for default flights and earlier versions).

    For evaluation only: this is the simulation's truth, not a starting value for an estimator.
    """
    with Path(path).open() as f:
        d = yaml.safe_load(f)
    tm = (d.get("flight") or {}).get("timing") if isinstance(d, dict) else None
    if not tm:
        return CameraTiming()
    try:
        rates, offsets = tm["rates_hz"], tm["time_offsets_s"]
        return CameraTiming(
            (float(rates["static"]), float(rates["dynamic"])),
            float(tm["phase_s"]),
            (float(offsets["static"]), float(offsets["dynamic"])),
            float(tm["stamp_jitter_s"]),
        )
    except (KeyError, TypeError) as exc:
        raise ValueError(f"{path}: flight.timing is incomplete ({exc})") from None
