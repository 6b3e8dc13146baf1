"""``dcc-fg vio BAG --calibration C.yaml ... --out OUT``: files in, trajectory files out.

Reads the gimbal calibration (``calibration.yaml`` of ``dcc-fg calibrate`` or ``dcc-fg simulate
flight``) and the IMU configuration (its ``imu:`` section, or a Kalibr ``imu.yaml`` for the noise
plus a Kalibr camchain with ``T_cam_imu`` for the mount), runs
:func:`~dcc_fg.vio.pipeline.run_vio_bag` with a progress bar showing the real-time factor, and
writes ``OUT/trajectory.tum``, ``OUT/joint_angles.csv`` (dcc, scc) and ``OUT/summary.json`` (with the
trajectory's ``health``, :func:`~dcc_fg.vio.health.vio_health`) as one output set
(:class:`~dcc_fg.io.output_set.OutputSet`): OUT is checked before the run, nothing is written when
the input is bad, the run fails or is interrupted, or the trajectory is unhealthy (exit code 3;
``--accept-unhealthy`` writes it marked ``healthy: false``). Options come from :class:`VioConfig`
(defaults, ``--config FILE``, then flags); ``summary.json`` records them with the version, the
command line, the inputs and the effective smoother and front-end settings.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from dcc_fg.commands import common
from dcc_fg.data.cameras import default_topic, run_cameras
from dcc_fg.data.vio import ImuConfig, load_imu_config
from dcc_fg.io import validate
from dcc_fg.io.output_set import OutputSet
from dcc_fg.model import GimbalCalibration, load_calibration
from dcc_fg.util.config import ConfigError, from_dict, to_plain
from dcc_fg.util.provenance import run_record
from dcc_fg.vio.backend import VioOptions, write_vio_outputs
from dcc_fg.vio.frontend import FrontendConfig
from dcc_fg.vio.health import vio_health
from dcc_fg.vio.pipeline import BagTopics, PipelineOptions, run_vio_bag
from dcc_fg.viz.rerun_log import VIO_IMAGE_CHOICES, RerunOptions, vio_recording

#: Kalibr imu.yaml keys -> ImuConfig fields
KALIBR_IMU_KEYS = {
    "accelerometer_noise_density": "accelerometer_noise_density",
    "accelerometer_random_walk": "accelerometer_random_walk",
    "gyroscope_noise_density": "gyroscope_noise_density",
    "gyroscope_random_walk": "gyroscope_random_walk",
    "update_rate": "rate_hz",
}


def kalibr_imu_config(imu_yaml: Path, T_sI: np.ndarray) -> ImuConfig:
    """IMU noise from a Kalibr ``imu.yaml`` (top level or under ``imu0``) and the mount ``T_sI``."""
    d = validate.load_yaml(imu_yaml, "Kalibr imu.yaml", "noise densities and random walks")
    section = "imu0." if isinstance(d.get("imu0"), dict) else ""
    d = d.get("imu0", d)
    kwargs: dict[str, Any] = {"T_sI": T_sI}
    for key, name in KALIBR_IMU_KEYS.items():
        if key in d:
            kwargs[name] = validate.number(d[key], f"{imu_yaml}: {section}{key}", positive=True)
        elif key != "update_rate":
            raise ValueError(f"{imu_yaml}: missing field '{section}{key}'")
    return ImuConfig(**kwargs)


def camchain_time_offsets(camchain: Path) -> tuple[float, float] | None:
    """Kalibr's ``timeshift_cam_imu`` of cam0 and cam1 (s, ``t_imu = t_cam + shift``), None if absent
    (cam1's defaults to 0 when only cam0 has one)."""
    d = validate.load_yaml(camchain, "Kalibr camchain-imucam", "cam0.T_cam_imu")
    shifts = []
    for cam in ("cam0", "cam1"):
        entry = d.get(cam)
        value = entry.get("timeshift_cam_imu") if isinstance(entry, dict) else None
        shifts.append(None if value is None else validate.number(value, f"{camchain}: {cam}.timeshift_cam_imu"))
    if shifts[0] is None and shifts[1] is None:
        return None
    return float(shifts[0] or 0.0), float(shifts[1] or 0.0)


def camchain_T_sI(camchain: Path) -> np.ndarray:
    """``T_cam_imu`` of ``cam0`` in a Kalibr camchain-imucam YAML (IMU -> static camera, 4x4)."""
    d = validate.load_yaml(camchain, "Kalibr camchain-imucam", "cam0.T_cam_imu")
    cam0 = d.get("cam0")
    if not isinstance(cam0, dict) or "T_cam_imu" not in cam0:
        raise ValueError(f"{camchain}: missing field 'cam0.T_cam_imu' (the IMU -> cam0 transform)")
    return validate.rigid_transform(cam0["T_cam_imu"], f"{camchain}: cam0.T_cam_imu")


@dataclass
class VioRunOptions:
    """Options of a ``dcc-fg vio`` run that are not smoother or front-end parameters.

    ``pixel_sigma``: feature noise in pixels (1 sigma; the smoother's normalized ``sigma`` is
    ``pixel_sigma`` / the static camera's mean focal length); ``sync_tolerance_ms``: static <-> gimbal
    image pairing tolerance by exposure time, milliseconds (None: half the slower camera's frame period,
    so a free-running gimbal camera pairs every static frame with its nearest image);
    ``dynamic_rejection``: the second stage of the gimbal outlier handling; ``frontend_worker``: ``auto`` |
    ``inline`` | ``process``; ``fit_initial_joints``: start the
    dcc joint angles from the first frame's static <-> gimbal matches; ``start_s``: skip the first seconds
    of the bag (from its first IMU sample); ``cameras``: the further cameras of an N-camera calibration to
    use (names, e.g. ``[cam1]``; None: every camera the mode can use: static cameras and cameras on a chain
    without joints in every mode, cameras on the primary chain in ``scc`` / ``dcc``);
    ``max_further_gap_ms``: the largest median stamp gap (ms) of a further camera's images to cam0's
    accepted (they are taken as triggered together).
    """

    pixel_sigma: float = 1.0
    sync_tolerance_ms: float | None = None
    dynamic_rejection: bool = True
    frontend_worker: str = "auto"
    fit_initial_joints: bool = True
    start_s: float = 0.0
    cameras: tuple[str, ...] | None = None
    max_further_gap_ms: float = 2.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.pixel_sigma) and self.pixel_sigma > 0):
            raise ValueError(f"pixel_sigma must be a positive number of pixels, got {self.pixel_sigma}")
        if self.sync_tolerance_ms is not None and not (
            np.isfinite(self.sync_tolerance_ms) and self.sync_tolerance_ms > 0
        ):
            raise ValueError(f"sync_tolerance_ms must be positive, got {self.sync_tolerance_ms}")
        if self.frontend_worker not in ("auto", "inline", "process"):
            raise ValueError(f"frontend_worker must be auto, inline or process, got {self.frontend_worker!r}")


@dataclass
class TopicOptions:
    """Bag topics: ``imu`` (sensor_msgs/Imu), ``static`` and ``dynamic`` camera images. ``dynamic`` None:
    the primary gimbal camera's ``rostopic`` in the calibration, else ``/camN/image_raw`` (``/cam1/image_raw``
    for a two-camera calibration). Further cameras of a cluster are read from their ``rostopic`` (else
    ``/camN/image_raw``)."""

    imu: str = "/imu0"
    static: str = "/cam0/image_raw"
    dynamic: str | None = None


@dataclass
class VioOutputOptions:
    """``accept_unhealthy``: write a trajectory that failed its health checks (marked ``health.healthy:
    false`` in ``summary.json``) instead of refusing it."""

    accept_unhealthy: bool = False


#: What ``--rerun`` shows of a VIO run (help text).
RERUN_SHOWS = (
    "per keyframe, the body pose with the static camera and the gimbal chain at the estimated joint angles, the "
    "trajectory (and the ground truth), joint angles, speed and IMU biases over time; per frame each camera's "
    "tracked features (pixels; matched across the cameras or not, rejected by stage two) and at keyframes the "
    "window's landmarks. No camera images"
)

#: VioOptions fields a config may not set: they are computed from other options.
DERIVED_SMOOTHER_FIELDS = {"sigma": "run.pixel_sigma (pixels; sigma = pixel_sigma / focal length)"}


@dataclass
class VioConfig:
    """Every option of ``dcc-fg vio`` (sections of the ``--config`` YAML).

    ``smoother``: :class:`~dcc_fg.vio.backend.VioOptions` (without ``sigma``, see ``run.pixel_sigma``);
    ``frontend``: overrides of :class:`~dcc_fg.vio.frontend.FrontendConfig`, whose defaults are scaled to
    the static camera's image size (:meth:`~dcc_fg.vio.frontend.FrontendConfig.for_resolution`).
    """

    run: VioRunOptions = field(default_factory=VioRunOptions)
    topics: TopicOptions = field(default_factory=TopicOptions)
    smoother: VioOptions = field(default_factory=lambda: VioOptions(keyframe_every=3))
    frontend: dict[str, Any] = field(default_factory=dict)
    output: VioOutputOptions = field(default_factory=VioOutputOptions)


def check_config(config: VioConfig, where: str) -> None:
    """Refuse derived smoother fields and unknown front-end options before any work starts."""
    default = VioConfig()
    for name, instead in DERIVED_SMOOTHER_FIELDS.items():
        if getattr(config.smoother, name) != getattr(default.smoother, name):
            raise ConfigError(f"{where}: smoother.{name} is computed; set {instead} instead")
    from_dict(FrontendConfig, config.frontend, f"{where}.frontend")


def frontend_config(config: VioConfig, calibration: GimbalCalibration) -> FrontendConfig:
    """The resolution-scaled front-end defaults with the config's overrides."""
    assert calibration.static_camera is not None
    base = FrontendConfig.for_resolution(*calibration.static_camera.resolution)
    return from_dict(FrontendConfig, config.frontend, "frontend", base)


def config_text_vio(config: VioConfig) -> dict[str, Any]:
    """``config`` as plain data, without the derived smoother fields (what ``--config`` accepts)."""
    data = to_plain(config)
    for name in DERIVED_SMOOTHER_FIELDS:
        data["smoother"].pop(name, None)
    return data


@dataclass(frozen=True)
class VioInputs:
    """Input files of a VIO run: the bag, the calibration and, optionally, Kalibr IMU files."""

    bag: str
    calibration: str
    imu_yaml: str | None = None
    camchain: str | None = None

    def paths(self) -> dict[str, str | None]:
        return dataclasses.asdict(self)

    def by_option(self, config_file: str | Path | None = None) -> dict[str, str | Path | None]:
        """The input paths by the option that gave them (``--config`` included), for the output checks."""
        return {
            "BAG": self.bag,
            "--calibration": self.calibration,
            "--imu-yaml": self.imu_yaml,
            "--camchain": self.camchain,
            "--config": config_file,
        }


def imu_config(inputs: VioInputs) -> ImuConfig:
    """IMU noise and mount: the calibration's ``imu:`` section, or ``--imu-yaml`` (+ ``--camchain`` for
    ``T_sI``, else the calibration's)."""
    cal_path = Path(inputs.calibration)
    if inputs.imu_yaml:
        if inputs.camchain:
            T_sI = camchain_T_sI(Path(inputs.camchain))
        else:
            embedded = load_imu_config(cal_path)
            if embedded is None:
                raise ValueError(
                    f"{cal_path}: no 'imu:' section; with --imu-yaml also give --camchain (Kalibr camchain with "
                    "cam0.T_cam_imu)"
                )
            T_sI = embedded.T_sI
        imu = kalibr_imu_config(Path(inputs.imu_yaml), T_sI)
        if inputs.camchain:
            imu = dataclasses.replace(imu, time_offsets=camchain_time_offsets(Path(inputs.camchain)))
        return imu
    imu = load_imu_config(cal_path)
    if imu is None:
        raise ValueError(
            f"{cal_path}: no 'imu:' section (T_sI and the IMU noise); add one or pass --imu-yaml and --camchain"
        )
    if inputs.camchain:
        shifts = camchain_time_offsets(Path(inputs.camchain))
        imu = dataclasses.replace(
            imu, T_sI=camchain_T_sI(Path(inputs.camchain)), time_offsets=shifts or imu.time_offsets
        )
    return imu


def camera_names(text: str) -> tuple[str, ...]:
    """``--cameras``: comma-separated camera names; ``none``: no further camera."""
    names = tuple(x.strip() for x in text.split(",") if x.strip())
    return () if names == ("none",) else names


def parse_angles(text: str, option: str) -> tuple[float, ...]:
    """``'1.57,0'`` or ``'1.57 0'`` -> (1.57, 0.0) (radians)."""
    try:
        return tuple(float(x) for x in text.replace(",", " ").split())
    except ValueError:
        raise ValueError(f"{option}: expected numbers (rad), got '{text}'") from None


def check_angles(values: tuple[float, ...] | None, n: int, option: str) -> None:
    if values is not None and (len(values) != n or not all(np.isfinite(values))):
        raise ValueError(f"{option}: expected {n} finite joint angles (rad), got {list(values)}")


def smoother_options(
    config: VioConfig, cal: GimbalCalibration, cal_path: Path, imu: ImuConfig | None = None
) -> VioOptions:
    """The smoother's options: the config's, with ``sigma`` from ``run.pixel_sigma``, checked angles and
    the time offsets' start values from ``--time-offsets``, else the calibration's / camchain's."""
    opts = config.smoother
    if opts.time_offsets is None and imu is not None and imu.time_offsets is not None:
        opts = dataclasses.replace(opts, time_offsets=tuple(imu.time_offsets))
    L = cal.n_joints
    check_angles(opts.theta_fixed, L, "--fixed-joints (smoother.theta_fixed)")
    check_angles(opts.theta_initial, L, "--initial-joints (smoother.theta_initial)")
    if opts.mode == "scc" and opts.theta_fixed is None:
        raise ValueError(f"--mode scc needs --fixed-joints with {L} angles (rad): the locked gimbal position")
    if cal.static_camera is None:
        raise ValueError(f"{cal_path}: no 'cam0' camera model (intrinsics of the static camera)")
    focal = float(np.mean(cal.static_camera.intrinsics[:2]))
    return dataclasses.replace(opts, sigma=config.run.pixel_sigma / focal)


class ProgressBar:
    """A tqdm bar on stderr showing the real-time factor (a no-op when ``show`` is False)."""

    def __init__(self, show: bool) -> None:
        self.bar = tqdm(unit="frame", desc="vio", file=sys.stderr) if show else None

    def __call__(self, done: int, total: int, elapsed: float, data_s: float) -> None:
        if self.bar is None:
            return
        self.bar.total = total
        self.bar.n = done
        if data_s > 0:
            self.bar.set_postfix_str(f"real-time factor {elapsed / data_s:.2f}")
        self.bar.refresh()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def run_vio(
    inputs: VioInputs,
    out: Path,
    config: VioConfig,
    progress: bool = False,
    quiet: bool = False,
    config_source: str = "options",
    config_file: str | Path | None = None,
    rerun: RerunOptions | None = None,
    rerun_ground_truth: str | Path | None = None,
) -> Any:
    """Validate the inputs and options, run the VIO over ``inputs.bag`` and write ``out``; returns the
    VioResult. ``config_source`` names where the options came from in error messages; ``config_file``
    (the ``--config`` file) is protected like the inputs. ``rerun``: also record the run for Rerun
    (:func:`dcc_fg.viz.rerun_log.vio_recording`: the tracks and landmarks per frame while it runs, the
    estimates after it; complete before the health checks, so an unhealthy trajectory can be inspected),
    with the ground truth ``rerun_ground_truth`` (TUM file or bag; default: the bag's own
    ``/ground_truth/pose`` topic when it has one).

    ``out`` is written as one output set (:class:`~dcc_fg.io.output_set.OutputSet`): checked before any
    work, written only when the run succeeds and its trajectory passes the health checks
    (:func:`~dcc_fg.vio.health.vio_health`; ``config.output.accept_unhealthy`` writes it anyway, marked
    ``health.healthy: false``)."""
    check_config(config, config_source)
    if rerun_ground_truth is not None:
        if rerun is None or not rerun.wanted:
            raise ValueError("--rerun-ground-truth is shown in a recording: give --rerun FILE.rrd or --rerun-spawn")
        if not Path(rerun_ground_truth).exists():
            raise FileNotFoundError(f"{rerun_ground_truth}: ground truth (--rerun-ground-truth) not found")
    cal_path, bag = Path(inputs.calibration), Path(inputs.bag)
    if not cal_path.is_file():
        raise FileNotFoundError(f"{cal_path}: calibration file not found")
    if not bag.exists():
        raise FileNotFoundError(f"{bag}: bag not found")
    outputs = OutputSet(out, "vio", inputs.by_option(config_file))
    cal = load_calibration(cal_path)
    imu = imu_config(inputs)
    options = smoother_options(config, cal, cal_path, imu)
    mono = options.mode == "mono"
    cluster = cal.cluster()
    primary = cluster.camera(cluster.primary_gimbal_camera)
    dynamic_topic = config.topics.dynamic or primary.rostopic or default_topic(primary.name)
    topics = BagTopics(config.topics.imu, config.topics.static, None if mono else dynamic_topic)
    further = run_cameras(cal, options.mode, options.theta_fixed, config.run.cameras)  # bad names: before the work
    pipeline = PipelineOptions(
        reject_dynamic=config.run.dynamic_rejection,
        fit_initial_joints=config.run.fit_initial_joints,
        tolerance_ns=None if config.run.sync_tolerance_ms is None else int(round(config.run.sync_tolerance_ms * 1e6)),
        worker=config.run.frontend_worker,
        frontend=frontend_config(config, cal),
        start_s=config.run.start_s,
        cameras=config.run.cameras,
        max_further_gap_ms=config.run.max_further_gap_ms,
    )
    with outputs:
        bar = ProgressBar(progress)
        recording = vio_recording(
            rerun or RerunOptions(), cal, imu.T_sI, options.mode, bag, rerun_ground_truth, topics, further
        )
        with recording as recorder:
            try:
                result, run = run_vio_bag(
                    bag, cal, imu, options, topics, pipeline, progress=bar if progress else None, observer=recorder
                )
            finally:
                bar.close()
            if recorder is not None:
                recorder.finish(result)
        health = common.judge_health(vio_health(result, imu, options), config.output.accept_unhealthy)
        provenance = run_record("vio", inputs.paths(), config)
        provenance["options"] = config_text_vio(config)
        provenance["effective_options"] = {"smoother": to_plain(options), "pipeline": to_plain(pipeline)}
        write_vio_outputs(
            outputs.path, result, {**provenance, "calibration": str(cal_path), "run": run, "health": health}
        )
    if not quiet:
        print_vio_summary(result, out, cal.n_joints)
    return result


def print_vio_summary(result: Any, out: Path, n_joints: int) -> None:
    s = result.stats
    print(
        f"{result.mode}: {s['keyframes']} keyframes over {s['data_duration_s']:.1f} s in "
        f"{s['processing_time_s']:.1f} s (real-time factor {s['real_time_factor']:.2f}), {s['landmarks']} landmarks, "
        f"{s['failed_updates']} failed updates"
    )
    n_segments = int(s.get("segment_count", 1) or 1)
    if n_segments > 1:
        reasons = "; ".join(str(seg.get("reason", "")) for seg in s.get("segments", [])[1:])
        print(
            f"the smoother restarted {n_segments - 1} time(s) ({reasons}): {n_segments} trajectory segments, also "
            f"written as {out / 'trajectory_segment_K.tum'} (K = 1..{n_segments}); evaluate each on its own"
        )
    if result.mode == "dcc" and result.theta.size:
        last = ", ".join(f"{x:.4f}" for x in result.theta[-1])
        print(f"final joint angles [{last}] rad")
    print(
        f"wrote {out / 'trajectory.tum'}, {out / 'summary.json'}"
        + (f", {out / 'joint_angles.csv'}" if result.mode != "mono" and n_joints else "")
    )


def vio_command(args: argparse.Namespace) -> int:
    """The ``dcc-fg vio`` subcommand (see :func:`add_parser`)."""
    rerun = replace(common.rerun_options(args), vio_images=args.rerun_images)
    config = common.effective_config(args, VioConfig, "vio")
    inputs = VioInputs(args.bag, args.calibration, args.imu_yaml, args.camchain)
    source = args.config or "command line"
    progress = common.progress_wanted(args)
    run_vio(inputs, Path(args.out), config, progress, args.quiet, source, args.config, rerun, args.rerun_ground_truth)
    return 0


def add_parser(sub: Any, parent: argparse.ArgumentParser) -> None:
    """Register ``dcc-fg vio`` on an argparse subparsers object."""
    v = common.add_command(
        sub, "vio", parent, "gimbal-aware visual-inertial odometry over a ROS1/ROS2 bag",
        "IMU-preintegrated keyframe fixed-lag smoother (GTSAM) whose states carry the gimbal joint angles (dcc), or "
        "hold them at known fixed angles (scc), or use the static camera only (mono). Reads sensor_msgs/Imu and two "
        "image topics; writes OUT/trajectory.tum (TUM: t[s] tx ty tz qx qy qz qw, body = IMU frame in a "
        "gravity-aligned world), OUT/joint_angles.csv (timestamp_ns,theta_1..theta_L, rad) and OUT/summary.json. "
        "Starts from standstill (the first 0.5 s of IMU at rest).", vio_command,
    )  # fmt: skip
    v.add_argument("bag", help="ROS1 .bag file or ROS2 bag folder")
    v.add_argument("--calibration", required=True, help="calibration.yaml with the chain (joints, tau_s, tau_d, dh), "
                   "cam0/cam1 intrinsics and, unless --imu-yaml is given, an 'imu:' section (T_sI 4x4 IMU -> static "
                   "camera, noise densities)")  # fmt: skip
    v.add_argument("--imu-yaml", help="Kalibr imu.yaml: noise densities (m/s^2/sqrt(Hz), rad/s/sqrt(Hz)), random walks")
    v.add_argument("--camchain", help="Kalibr camchain-imucam.yaml: takes T_sI from cam0.T_cam_imu")
    add_vio_flags(v)
    v.add_argument("--out", required=True, help="output folder for trajectory.tum, joint_angles.csv and "
                   f"summary.json. {common.OUT_FOLDER_HELP}")  # fmt: skip
    common.add_config_flag(v, "vio")
    common.add_rerun_flags(v, RERUN_SHOWS)
    v.add_argument("--rerun-ground-truth", metavar="GT", help="ground truth shown in the recording (TUM file, body "
                   "frame, or a bag with /ground_truth/pose and /ground_truth/joints), aligned as dcc-fg evaluate "
                   "aligns; default: the bag's own /ground_truth/pose topic when it has one")  # fmt: skip
    v.add_argument("--rerun-images", choices=VIO_IMAGE_CHOICES, default="keyframes", help="camera images in the "
                   "recording, under the tracks: of the keyframes (default; between keyframes the last keyframe's "
                   "image stays while the tracks move on), of all frames (a larger file), or none")  # fmt: skip


def add_vio_flags(v: argparse.ArgumentParser) -> None:
    """The flags that set VioConfig options (topics, smoother, run)."""
    opt = common.add_option
    opt(v, "--imu-topic", "topics.imu", help="sensor_msgs/Imu topic (default /imu0)")
    opt(v, "--static-topic", "topics.static", help="static camera image topic (default /cam0/image_raw)")
    opt(v, "--dynamic-topic", "topics.dynamic", help="gimbal camera image topic (default: the primary gimbal camera's "
        "rostopic in the calibration, else /camN/image_raw: /cam1/image_raw for a two-camera calibration)")  # fmt: skip
    opt(v, "--cameras", "run.cameras", type=camera_names, metavar="NAMES",
        help="N-camera calibration: the further cameras to use, e.g. 'cam1', or 'none' (default: every camera "
        "the mode can use: static cameras in every mode, cameras on the gimbal chain in scc/dcc; cam0 and in "
        "scc/dcc the first camera on the chain are always used); their images are read from their rostopic in "
        "the calibration, else /camN/image_raw")  # fmt: skip
    opt(v, "--max-further-gap", "run.max_further_gap_ms", type=float, metavar="MS", help="N-camera: the largest "
        "median stamp gap (ms) between a further camera's images and cam0's that is accepted (default 2): they are "
        "used as exposed at cam0's stamp, so a camera on its own clock is refused unless this allows it")  # fmt: skip
    opt(v, "--mode", "smoother.mode", choices=["dcc", "scc", "mono"], help="default dcc")
    opt(v, "--initial-joints", "smoother.theta_initial", type=lambda t: parse_angles(t, "--initial-joints"),
        metavar="RAD", help="dcc: starting guess of the joint angles, e.g. '1.57,0' (rad); by default they are found "
        "from the first frame's static/gimbal matches")  # fmt: skip
    opt(v, "--fixed-joints", "smoother.theta_fixed", type=lambda t: parse_angles(t, "--fixed-joints"), metavar="RAD",
        help="scc: the locked joint angles, e.g. '1.57,0' (rad)")  # fmt: skip
    opt(v, "--pixel-sigma", "run.pixel_sigma", type=float, help="feature noise, pixels (1 sigma; default 1)")
    opt(v, "--keyframe-every", "smoother.keyframe_every", type=int, help="every n-th frame is a keyframe (default 3)")
    opt(v, "--lag", "smoother.lag", type=float, help="smoother window, seconds (default: 2.5 with no persistent "
        "landmarks, 1.5 otherwise; see --persistent-landmarks)")  # fmt: skip
    opt(v, "--sync-tolerance", "run.sync_tolerance_ms", type=float, metavar="MS",
        help="static <-> gimbal image pairing tolerance by exposure time (stamp + offset), ms (default: half the "
        "slower camera's frame period: each static image takes its nearest gimbal image)")  # fmt: skip
    opt(v, "--time-offsets", "smoother.time_offsets", type=common.float_pair, metavar="T_S,T_D",
        help="start values of the static and gimbal camera's time offsets from the IMU clock, s, convention "
        "t_imu = t_cam_stamp + t_offset (Kalibr timeshift_cam_imu); default: the calibration's imu.time_offsets or "
        "the camchain's timeshift_cam_imu, else 0,0. Estimated online unless --fix-time-offsets")  # fmt: skip
    opt(v, "--fix-time-offsets", "smoother.estimate_time_offsets", action="store_false",
        help="hold the time offsets at their start values instead of estimating them")  # fmt: skip
    opt(v, "--landmarks", "smoother.landmarks", choices=["explicit", "smart"], help="explicit (default): a 3-D "
        "variable per landmark with robust reprojection factors; smart (experimental): one GTSAM smart projection "
        "factor per landmark (0.69x the main process's CPU on the 60 s benchmark flight with --lag 2.5, same "
        "translation RMSE, 1.2-1.4x the joint RMSE); needs estimated time offsets and no further cameras")  # fmt: skip
    opt(v, "--persistent-landmarks", "smoother.persistent_landmarks", choices=["auto", "all", "gimbal", "none"],
        help="which landmarks stay in the window while they are tracked: all; none: every landmark leaves with the "
        "oldest keyframe that saw it when it was made (its information kept as a prior on the keyframe states, "
        "triangulated afresh if still tracked), so no dense landmark marginal; gimbal: those a gimbal camera saw "
        "stay; auto (default): none with a 2.5 s window when the gimbal camera's images share the static camera's "
        "stamps (within 1 ms) and there is no further camera, else all with 1.5 s. Over eight synchronized 60 s "
        "benchmark flights none with 2.5 s takes 0.64x the wall time of all with 1.5 s at the same translation and "
        "joint RMSE (pooled within 3.5 %%; benchmarks/bench_vio_persistence.py; README, VIO throughput); on the "
        "unsynchronized benchmark flight (gimbal camera at 30 Hz on its own clock) it had 1.19x the translation RMSE "
        "of all: a warning says so when it is asked for there")  # fmt: skip
    opt(v, "--start", "run.start_s", type=float, metavar="S", help="skip the first S seconds of the bag (from its "
        "first IMU sample); the VIO then starts in motion unless the body is at rest there")  # fmt: skip
    opt(v, "--initialization", "smoother.initialization", choices=["auto", "standstill", "motion"], help="how the VIO "
        "starts without a given state: auto (default) at rest when the IMU and the static tracks are still over the "
        "first 0.5 s, else by visual-inertial alignment in motion; standstill or motion force one")  # fmt: skip
    opt(v, "--joint-sigmas", "smoother.joint_sigmas", action="store_true", help="dcc: each keyframe's joint-angle "
        "1-sigma from the window's marginal covariance before it leaves (OUT/joint_angles_sigma.csv, the band in "
        "the figures); measured: 4x the smoother time of a run without")  # fmt: skip
    opt(v, "--accept-unhealthy", "output.accept_unhealthy", action="store_true", help="write a trajectory that "
        "failed its health checks (divergence, covariance blow-up, vision unused) instead of refusing it with exit "
        "code 3; summary.json then says health: healthy: false, with the reasons")  # fmt: skip
    opt(v, "--no-dynamic-rejection", "run.dynamic_rejection", action="store_false", help="keep every gimbal-camera "
        "track (skip the second stage of the two-stage outlier handling)")  # fmt: skip
    opt(v, "--frontend", "run.frontend_worker", choices=["auto", "inline", "process"], help="run the feature tracking "
        "inline, or in a second process on another core so it overlaps the smoother; auto (default) takes the second "
        "process when two or more cores are usable. Both are deterministic (the same result on every run; the "
        "process applies the smoother's track rejections a few frames later than inline, so the two differ "
        "slightly). benchmarks/bench_vio.py measures both on your machine")  # fmt: skip
