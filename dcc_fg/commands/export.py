"""``dcc-fg export CALIBRATION.yaml --format urdf|kalibr|joint-states --out PATH``.

* ``urdf``: the cluster as a URDF (:mod:`dcc_fg.export.urdf`): root = the static camera's optical
  frame (or, with ``--body-frames``, its ROS body frame), one revolute joint per DH link, the gimbal
  camera's optical frame at the end; joint limits = the observed range of ``--joints-csv`` or of the
  ``joint_angles.csv`` beside the calibration, else +-pi (logged);
* ``kalibr``: a Kalibr camchain frozen at ``--joints`` (:mod:`dcc_fg.export.kalibr`), plus the
  camchain-imucam form beside it where the calibration has an ``imu:`` section;
* ``joint-states``: ``--joints-csv`` as ``sensor_msgs/JointState`` in a ROS1 (``*.bag``) or ROS2
  bag (:mod:`dcc_fg.export.joint_states`), joint names as in the URDF.

A calibration in the ``cameras:`` / ``chains:`` form (:mod:`dcc_fg.cluster`, N cameras on one or
more chains) exports as a URDF with every camera and chain (:func:`dcc_fg.export.urdf.layout_urdf_text`;
joints, limits and joint-state columns in the flat joint order, chains in file order); its Kalibr export
needs a two-camera cluster (N-camera Kalibr export is not supported yet).

``--out`` is checked before any work (not an input, not inside an input folder, not an existing file
without ``--force``; a bag only ever replaces a joint-state bag); files are written under temporary
names and renamed into place together. Bad input raises ValueError / FileNotFoundError naming the
file, field or option (exit code 2).
"""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path
from typing import Any

from dcc_fg.cluster import CameraCluster
from dcc_fg.commands import common
from dcc_fg.data.vio import load_imu_config
from dcc_fg.export.joint_states import (
    DEFAULT_TOPIC,
    check_bag_out,
    read_joint_angles,
    ros_version,
    write_joint_state_bag,
)
from dcc_fg.export.kalibr import DEFAULT_TOPICS, camchain_text, frozen_camchain, imucam_path, parse_joint_angles
from dcc_fg.export.naming import ClusterNames, LayoutNames, cluster_names, layout_names, parse_joint_names
from dcc_fg.export.urdf import layout_urdf_text, observed_limits, urdf_text
from dcc_fg.io.output_set import OutputFiles, OutputPathError
from dcc_fg.model import GimbalCalibration, load_calibration
from dcc_fg.util.provenance import package_version

log = logging.getLogger("dcc_fg.commands.export")

FORMATS = ("urdf", "kalibr", "joint-states")

#: Which formats each option applies to (an option given for another format is refused).
OPTION_FORMATS: dict[str, tuple[str, ...]] = {
    "joints": ("kalibr",),
    "image_topics": ("kalibr",),
    "joints_csv": ("urdf", "joint-states"),
    "prefix": ("urdf", "joint-states"),
    "joint_names": ("urdf", "joint-states"),
    "static_frame": ("urdf",),
    "gimbal_frame": ("urdf",),
    "body_frames": ("urdf",),
    "limit_margin": ("urdf",),
    "robot_name": ("urdf",),
    "topic": ("joint-states",),
    "storage": ("joint-states",),
}

EXPORT_SUMMARY = "export a calibration as a URDF, a Kalibr camchain or a joint-state bag"
EXPORT_DESCRIPTION = (
    "Write a calibration.yaml for other robot software. --format urdf: the cluster as a URDF (root: the static "
    "camera's optical frame, z forward, x right, y down; one revolute joint per DH link about its z axis; the gimbal "
    "camera's optical frame at the end), so robot_state_publisher and /joint_states give the TF tree; the pose of "
    "the gimbal camera link in the static camera link is T_sd(theta) = inv(T_ds(theta)). --format kalibr: a Kalibr "
    "camchain with cam0 = static and cam1 = gimbal camera frozen at --joints (T_cn_cnm1 = T_ds(theta)), and the "
    "camchain-imucam form beside it where the calibration has an imu: section. --format joint-states: a "
    "joint_angles.csv (timestamp_ns,theta_1..theta_L, rad) as sensor_msgs/JointState in a ROS1 (.bag) or ROS2 bag, "
    "with the URDF's joint names. Units: metres, radians, integer nanoseconds."
)


def _given(args: argparse.Namespace, option: str) -> bool:
    value = getattr(args, option)
    return value is not None and value is not False


def check_options(args: argparse.Namespace) -> None:
    """Refuse options that do not apply to ``--format`` (ValueError naming them)."""
    for option, formats in OPTION_FORMATS.items():
        if _given(args, option) and args.format not in formats:
            flag = "--" + option.replace("_", "-")
            raise ValueError(f"{flag} does not apply to --format {args.format} (only to {', '.join(formats)})")


def names_from_args(args: argparse.Namespace, cal: GimbalCalibration, source: str) -> ClusterNames:
    """The URDF / joint-state names from ``--prefix``, ``--joint-names``, ``--static-frame``, ``--gimbal-frame``."""
    joints = parse_joint_names(args.joint_names, cal.n_joints, source) if args.joint_names is not None else None
    return cluster_names(
        cal.n_joints,
        prefix=args.prefix or "",
        joints=joints,
        static_frame=args.static_frame,
        gimbal_frame=args.gimbal_frame,
    )


def layout_names_from_args(args: argparse.Namespace, cluster: CameraCluster, source: str) -> LayoutNames:
    """The URDF / joint-state names of an N-camera cluster from ``--prefix`` and ``--joint-names`` (the
    flat joint order); ``--static-frame`` / ``--gimbal-frame`` are refused (the links are named per camera)."""
    for option in ("static_frame", "gimbal_frame"):
        if getattr(args, option, None) is not None:
            raise ValueError(
                f"--{option.replace('_', '-')}: {source} describes a cluster of {', '.join(cluster.camera_names)}; "
                "its camera links are named PREFIXcamN_optical (use --prefix)"
            )
    count = cluster.joint_count
    joints = parse_joint_names(args.joint_names, count, source) if args.joint_names is not None else None
    return layout_names(cluster.camera_names, [(c.name, c.n_joints) for c in cluster.chains], args.prefix or "", joints)


def _refuse_existing(paths: list[Path], force: bool) -> None:
    for p in paths:
        if p.exists() and not force:
            raise OutputPathError(f"--out {p}: exists; choose another name or pass --force to replace it")


def _header(cal_path: Path, fmt: str) -> str:
    return f"exported by dcc-fg {package_version()} (dcc-fg export, format {fmt}) from {cal_path.resolve()}"


def export_urdf(args: argparse.Namespace, cal_path: Path) -> list[Path]:
    """``--format urdf`` (module docstring); the paths written."""
    out = Path(args.out)
    beside = cal_path.parent / "joint_angles.csv"
    csv = Path(args.joints_csv) if args.joints_csv else (beside if beside.is_file() else None)
    outputs = OutputFiles({"--out": out}, {"CALIBRATION": cal_path, "--joints-csv": csv})
    _refuse_existing([out], args.force)
    margin = 0.0 if args.limit_margin is None else float(args.limit_margin)
    cal = load_calibration(cal_path)
    cluster = cal.cluster() if cal.layout is not None else None
    n_joints = cal.n_joints if cluster is None else cluster.joint_count
    names = names_from_args(args, cal, str(cal_path)) if cluster is None else None
    cluster_link_names = layout_names_from_args(args, cluster, str(cal_path)) if cluster is not None else None
    limits = None
    notes = [_header(cal_path, "urdf")]
    if n_joints and csv is not None:
        _, angles = read_joint_angles(csv, n_joints, str(cal_path), allow_unseen=True)
        limits = observed_limits(angles, margin)
        where = f"joint limits: the observed range of {len(angles)} rows of {csv.resolve()}"
        notes.append(where + (f", widened by {margin:g} rad" if margin else ""))
        log.info("%s: %s", out, where)
    elif n_joints:
        notes.append("joint limits: +-pi (no joint angles were given to take the observed range from)")
        log.info(
            "%s: joint limits set to +-pi rad: no joint_angles.csv beside %s and no --joints-csv to take the "
            "observed joint range from", out, cal_path,
        )  # fmt: skip
    robot = args.robot_name or "dcc_fg_cluster"
    if names is not None:
        text = urdf_text(cal, names, limits, bool(args.body_frames), robot, notes)
    else:
        assert cluster is not None and cluster_link_names is not None
        text = layout_urdf_text(cluster, cluster_link_names, limits, bool(args.body_frames), robot, notes)
    with outputs:
        outputs["--out"].write_text(text, encoding="utf-8")
    return [out]


def export_kalibr(args: argparse.Namespace, cal_path: Path) -> list[Path]:
    """``--format kalibr`` (module docstring); the paths written."""
    out = Path(args.out)
    cal = load_calibration(cal_path).require_two_cameras("Kalibr export")
    if args.joints is None and cal.n_joints:
        raise ValueError(
            f"--format kalibr needs --joints THETA_1,...,THETA_L: the {cal.n_joints} joint angle(s) of {cal_path} at "
            "which the cluster is frozen (rad, or degrees with 'deg' after the last number)"
        )
    theta = parse_joint_angles(args.joints or "", cal.n_joints, str(cal_path))
    topics = DEFAULT_TOPICS
    if args.image_topics is not None:
        parts = tuple(t.strip() for t in args.image_topics.split(","))
        if len(parts) != 2 or not all(t.startswith("/") and " " not in t for t in parts):
            raise ValueError(f"--image-topics {args.image_topics!r}: expected two topics STATIC,GIMBAL (each '/...')")
        topics = (parts[0], parts[1])
    imu = load_imu_config(cal_path)
    targets: dict[str, str | Path | None] = {"--out": out, "camchain-imucam": imucam_path(out) if imu else None}
    outputs = OutputFiles(targets, {"CALIBRATION": cal_path})
    _refuse_existing([Path(p) for p in targets.values() if p is not None], args.force)
    header = [
        _header(cal_path, "kalibr"),
        f"cam0: static camera s; cam1: gimbal camera d frozen at theta = {[float(x) for x in theta]} rad",
        "cam1.T_cn_cnm1 = T_ds(theta): maps cam0 points into cam1 (m)",
    ]
    text = camchain_text(frozen_camchain(cal, theta, str(cal_path), topics), header)
    imu_text = None
    if imu is not None:
        imu_header = [*header, "camN.T_cam_imu: maps IMU points into camN (cam0: T_sI; cam1: T_ds(theta) T_sI); "
                      "timeshift_cam_imu (s): t_imu = t_cam + shift"]  # fmt: skip
        imu_text = camchain_text(frozen_camchain(cal, theta, str(cal_path), topics, imu), imu_header)
    with outputs:
        outputs["--out"].write_text(text, encoding="utf-8")
        if imu_text is not None:
            outputs["camchain-imucam"].write_text(imu_text, encoding="utf-8")
    return [Path(p) for p in targets.values() if p is not None]


def export_joint_states(args: argparse.Namespace, cal_path: Path) -> list[Path]:
    """``--format joint-states`` (module docstring); the paths written."""
    out = Path(args.out)
    if args.joints_csv is None:
        raise ValueError("--format joint-states needs --joints-csv joint_angles.csv (of dcc-fg calibrate or vio)")
    csv = Path(args.joints_csv)
    if args.storage is not None and ros_version(out) == 1:
        raise ValueError(f"--storage {args.storage} applies to ROS2 bag folders, but --out {out} (*.bag) is a ROS1 bag")
    check_bag_out(out, {"CALIBRATION": cal_path, "--joints-csv": csv})
    _refuse_existing([out], args.force)
    topic = args.topic or DEFAULT_TOPIC
    if not topic.startswith("/") or " " in topic:
        raise ValueError(f"--topic {topic!r}: a ROS topic name starts with '/' and has no spaces")
    cal = load_calibration(cal_path)
    if cal.layout is None:
        if cal.n_joints == 0:
            raise ValueError(f"{cal_path}: joints: 0 (a rigid camera pair): there are no joint angles to write")
        n_joints, joint_names = cal.n_joints, names_from_args(args, cal, str(cal_path)).joints
    else:
        cluster = cal.cluster()
        if cluster.joint_count == 0:
            raise ValueError(f"{cal_path}: every chain has joints: 0: there are no joint angles to write")
        n_joints, joint_names = cluster.joint_count, layout_names_from_args(args, cluster, str(cal_path)).joints
    stamps, angles = read_joint_angles(csv, n_joints, str(cal_path))
    n = write_joint_state_bag(out, stamps, angles, joint_names, topic, args.storage or "sqlite3")
    log.info("%s: %d sensor_msgs/JointState messages on %s (joints %s)", out, n, topic, ", ".join(joint_names))
    return [out]


EXPORTERS = {"urdf": export_urdf, "kalibr": export_kalibr, "joint-states": export_joint_states}


def export_command(args: argparse.Namespace) -> int:
    """Check the options and ``--out``, then write the export; ``wrote ...`` unless ``--quiet``."""
    check_options(args)
    cal_path = Path(args.calibration)
    if not cal_path.is_file():
        raise FileNotFoundError(f"{cal_path}: calibration file not found")
    paths = EXPORTERS[args.format](args, cal_path)
    if not args.quiet:
        print("wrote " + ", ".join(str(p) for p in paths))
    return 0


def _angle_margin(text: str) -> float:
    """argparse ``type`` of ``--limit-margin``: a finite, non-negative number (rad)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expects a number of radians, got {text!r}") from None
    if not (math.isfinite(value) and value >= 0.0):
        raise argparse.ArgumentTypeError(f"expects a finite non-negative number of radians, got {text!r}")
    return value


def add_parser(sub: Any, parent: argparse.ArgumentParser) -> None:
    p = common.add_command(sub, "export", parent, EXPORT_SUMMARY, EXPORT_DESCRIPTION, export_command)
    p.add_argument("calibration", metavar="CALIBRATION", help="calibration.yaml of dcc-fg calibrate (or a gimbal.yaml)")
    p.add_argument("--format", required=True, choices=FORMATS, help="what to write (see above)")
    p.add_argument(
        "--out",
        required=True,
        help="urdf: the .urdf file; kalibr: the camchain .yaml (the camchain-imucam form goes beside it: "
        "camchain*.yaml -> camchain-imucam*.yaml, else NAME-imucam.yaml); joint-states: a ROS1 bag file if it ends "
        "in .bag, else a ROS2 bag folder. Checked before any work: not an input or inside an input folder; written "
        "under a temporary name and renamed into place when complete",
    )
    p.add_argument("--force", action="store_true", help="replace --out if it exists (a bag only if it holds nothing "
                   "but JointState topics)")  # fmt: skip
    g = p.add_argument_group("urdf and joint-states")
    g.add_argument("--joints-csv", metavar="CSV", help="urdf: joint limits from the observed range of this "
                   "joint_angles.csv (default: the one beside CALIBRATION, else +-pi); joint-states: the angles to "
                   "write (timestamp_ns,theta_1..theta_L, rad; of dcc-fg calibrate, validate or vio)")  # fmt: skip
    g.add_argument("--prefix", help="prepended to every link and default joint name (e.g. 'gimbal0_')")
    g.add_argument("--joint-names", metavar="A,B,...", help="the L revolute joint names, used verbatim (default "
                   "PREFIXjoint_1..PREFIXjoint_L); must match the gimbal's /joint_states names")  # fmt: skip
    u = p.add_argument_group("urdf")
    u.add_argument("--static-frame", metavar="NAME", help="name of the static camera's optical link (default "
                   "PREFIXstatic_camera_optical), e.g. the frame_id of its images")  # fmt: skip
    u.add_argument("--gimbal-frame", metavar="NAME", help="name of the gimbal camera's optical link (default "
                   "PREFIXgimbal_camera_optical)")  # fmt: skip
    u.add_argument("--body-frames", action="store_true", help="add each camera's ROS body frame (x forward, y left, "
                   "z up; PREFIXstatic_camera is then the root), the optical frames turned by rpy (-pi/2, 0, -pi/2) "
                   "from them")  # fmt: skip
    u.add_argument("--limit-margin", type=_angle_margin, metavar="RAD", help="widen the observed joint range by "
                   "this much on both sides (rad, default 0)")  # fmt: skip
    u.add_argument("--robot-name", help="the URDF robot name (default dcc_fg_cluster)")
    k = p.add_argument_group("kalibr")
    k.add_argument("--joints", metavar="THETA", help="joint angles THETA_1,...,THETA_L at which the cluster is "
                   "frozen: radians, or degrees with 'deg' after the last number (90,5deg); a first negative value "
                   "needs '=': --joints=-0.2,0.1")  # fmt: skip
    k.add_argument("--image-topics", metavar="STATIC,GIMBAL", help="rostopic of cam0 and cam1 (default "
                   f"{','.join(DEFAULT_TOPICS)})")  # fmt: skip
    j = p.add_argument_group("joint-states")
    j.add_argument("--topic", help=f"the sensor_msgs/JointState topic (default {DEFAULT_TOPIC})")
    j.add_argument("--storage", choices=["sqlite3", "mcap"], help="ROS2 bag storage (default sqlite3)")
