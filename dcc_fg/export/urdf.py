"""The dynamic camera cluster as a URDF: static camera link, one revolute joint per DH link, gimbal camera link.

Frames (docs/architecture.md): ``s`` static camera, ``b`` gimbal base (DH frame 0), ``e`` end
effector (DH frame L), ``d`` gimbal (dynamic) camera. Both camera frames are *optical* frames, as
in ROS (REP 103 ``*_optical`` frames, and as dcc-fg projects): z forward along the optical axis, x
right, y down in the image. A URDF joint gives its child's pose in its parent (``T_parent_child``),
so the tree, from the root, is::

    static_camera_optical (s, root)
      gimbal_base_mount (fixed)         origin T_sb = inv(T_bs(tau_s))
    gimbal_base (b = DH frame 0)
      joint_1 (revolute, axis z)        origin identity; child = DH frame 0 turned by Rz(theta_1)
    gimbal_link_1
      joint_l, l = 2..L (revolute, z)   origin Tz(d_{l-1}) Tx(a_{l-1}) Rx(alpha_{l-1}) (= DH frame l-1)
    gimbal_link_L
      gimbal_end_effector_fixed (fixed) origin Tz(d_L) Tx(a_L) Rx(alpha_L); identity for L = 0
    gimbal_end_effector (e = DH frame L)
      gimbal_camera_mount (fixed)       origin T_ed = inv(T_de(tau_d))
    gimbal_camera_optical (d)

With every joint at its angle ``q_l = theta_l`` (the calibration's joint angles, rad, the same
numbers as in ``joint_angles.csv``), the pose of the gimbal camera link in the static camera link is
``T_sd(theta) = inv(T_bs) A_1(theta_1) ... A_L(theta_L) inv(T_de) = inv(T_ds(theta))`` with
``A_l = Rz(theta_l) Tz(d_l) Tx(a_l) Rx(alpha_l)`` (paper eq. 5). With *body frames* the root is the
static camera's ROS body frame (``static_camera``: x forward, y left, z up) and the gimbal camera
gets one too (``gimbal_camera``, between ``gimbal_end_effector`` and ``gimbal_camera_optical``);
each optical frame is its body frame turned by ``rpy = (-pi/2, 0, -pi/2)``, the usual ROS camera
convention, so the optical links and their relative pose are unchanged.

The joint angles are dcc-fg's ``theta``: the calibration fixes the constant offsets of ``theta_1``
and ``theta_L`` by convention (the gauge freedom, docs/architecture.md), so a gimbal driver's own
encoder zero can differ from them by a constant per joint; drive the URDF with dcc-fg's estimated
angles, or with encoder readings after adding that offset.

URDF ``rpy`` are fixed-axis roll, pitch, yaw: ``R = Rz(yaw) Ry(pitch) Rx(roll)``, the same 3-2-1
convention as dcc-fg's ``tau``; ``xyz`` in metres. Numbers are written with Python's shortest
round-trip representation, so the file holds the calibration to the last bit of a float64; before
returning, :func:`urdf_text` checks the forward kinematics of what it writes against ``T_ds``.
Joint limits are the observed range of the joint angles (:func:`observed_limits`), else +-pi; a
calibration does not know efforts and velocities, written as 0.

An N-camera cluster (a ``cameras:`` / ``chains:`` calibration, :mod:`dcc_fg.cluster`;
:func:`layout_joints`, :func:`layout_urdf_text`) has the same parts per chain and camera, names from
:func:`dcc_fg.export.naming.layout_names`::

    cam0_optical (s, root)
      camN_mount (fixed), static camN     origin T_s_cN = inv(T_cs)
      <chain>_base_mount (fixed)          origin inv(T_bs(tau_s)) of that chain, then its revolute
                                          joints and <chain>_end_effector as above
    <chain>_end_effector
      camN_mount (fixed), each camera on the chain   origin inv(T_de(tau_d)) of that camera

so the pose of ``camN_optical`` in ``cam0_optical`` is ``inv(T_cs(camN, theta))`` with each revolute
joint at its angle of the flat joint-angle vector (chains in file order).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from dcc_fg.cluster import CameraCluster
from dcc_fg.export.naming import ClusterNames, LayoutNames
from dcc_fg.model import GimbalCalibration
from factors import chain

FloatArray = NDArray[np.float64]

#: ``rpy`` of a camera's optical frame in its ROS body frame (x forward, y left, z up).
BODY_TO_OPTICAL_RPY = (-math.pi / 2, 0.0, -math.pi / 2)

#: The forward kinematics of the written URDF must reproduce ``inv(T_ds(theta))`` to this (m, and rad
#: for the rotation matrix entries) before the text is returned.
SELF_CHECK_TOLERANCE = 1e-10


@dataclass(frozen=True)
class UrdfJoint:
    """One URDF joint: ``child`` pose in ``parent`` = ``origin`` (then ``Rz(q)`` for a revolute joint).

    Attributes:
        name, parent, child: joint and link names.
        kind: ``fixed`` or ``revolute`` (axis: the joint frame's z axis).
        xyz: origin translation (m), in the parent link frame.
        rpy: origin rotation, fixed-axis roll, pitch, yaw (rad): ``R = Rz(yaw) Ry(pitch) Rx(roll)``.
        limits: (lower, upper) joint angle (rad) of a revolute joint.
    """

    name: str
    kind: Literal["fixed", "revolute"]
    parent: str
    child: str
    xyz: tuple[float, float, float]
    rpy: tuple[float, float, float]
    limits: tuple[float, float] | None = None

    def origin(self) -> FloatArray:
        """``T_parent_joint`` (4x4) from the written ``xyz`` / ``rpy``."""
        return chain.se3_from_tau(np.array([*self.rpy, *self.xyz], dtype=float))

    def transform(self, q: float = 0.0) -> FloatArray:
        """``T_parent_child`` (4x4) at joint angle ``q`` (rad; ignored by a fixed joint)."""
        if self.kind == "fixed":
            return self.origin()
        turn = np.eye(4)
        turn[:3, :3] = chain.rot_z(q)
        return self.origin() @ turn


def rpy_from_rotation(R: FloatArray) -> tuple[float, float, float]:
    """URDF ``(roll, pitch, yaw)`` of a rotation matrix, ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (rad).

    Accurate to rounding everywhere, gimbal lock (pitch = +-pi/2) included: the yaw is taken out
    first and roll and pitch are read from ``Rz(-yaw) R = Ry(pitch) Rx(roll)``, whose entries hold
    each angle's sine and cosine undivided (at the lock any split between roll and yaw is exact).
    """
    R = np.asarray(R, dtype=float)
    yaw = math.atan2(R[1, 0], R[0, 0])
    Rp = chain.rot_z(-yaw) @ R
    pitch = math.atan2(-Rp[2, 0], Rp[0, 0])
    roll = math.atan2(-Rp[1, 2], Rp[1, 1])
    return float(roll), float(pitch), float(yaw)


def _pose(T: FloatArray) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """(xyz, rpy) of a 4x4 rigid transform."""
    return (float(T[0, 3]), float(T[1, 3]), float(T[2, 3])), rpy_from_rotation(T[:3, :3])


def _link_offset(dh_row: FloatArray) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """(xyz, rpy) of the fixed part ``Tz(d) Tx(a) Rx(alpha)`` of a DH link ``[d, a, alpha]``."""
    d, a, alpha = (float(x) for x in dh_row)
    return (a, 0.0, d), (alpha, 0.0, 0.0)


def observed_limits(angles: FloatArray, margin: float = 0.0) -> FloatArray:
    """(L, 2) joint limits (rad): the smallest and largest angle of each joint in ``angles`` (N, L),
    widened by ``margin`` (rad) on both sides. NaN angles (unseen) are left out; a joint without any
    finite angle gets +-pi."""
    a = np.asarray(angles, dtype=float)
    if a.ndim != 2 or a.shape[0] == 0:
        raise ValueError(f"observed_limits needs (N, L) joint angles with N >= 1, got shape {a.shape}")
    seen = np.isfinite(a).any(axis=0)
    lo = np.min(np.where(np.isnan(a), np.inf, a), axis=0) - margin
    hi = np.max(np.where(np.isnan(a), -np.inf, a), axis=0) + margin
    return np.column_stack([np.where(seen, lo, -np.pi), np.where(seen, hi, np.pi)])


def cluster_joints(
    cal: GimbalCalibration,
    names: ClusterNames,
    limits: FloatArray | None = None,
    body_frames: bool = False,
) -> list[UrdfJoint]:
    """The URDF joints of ``cal`` (module docstring), parents before children.

    Args:
        cal: the calibration (``tau_s``, ``tau_d``, ``dh``; rad, m).
        names: link and joint names, with ``len(names.joints) == cal.n_joints``.
        limits: (L, 2) lower / upper joint angles (rad); None: +-pi.
        body_frames: root at the static camera's ROS body frame and a body frame for the gimbal camera.
    """
    L = cal.n_joints
    if len(names.joints) != L:
        raise ValueError(f"{len(names.joints)} joint names for a calibration with {L} joints")
    lim = _limits(limits, L)
    joints: list[UrdfJoint] = []
    if body_frames:
        joints.append(UrdfJoint(names.static_optical_joint, "fixed", names.static_body, names.static_optical,
                                (0.0, 0.0, 0.0), BODY_TO_OPTICAL_RPY))  # fmt: skip
    parts = ChainParts(names.base_mount, names.base, names.joints, names.links, names.end_effector_fixed,
                       names.end_effector)  # fmt: skip
    joints += _chain_joints(names.static_optical, parts, cal.T_bs(), cal.dh, lim)
    T_ed = chain.inv_se3(cal.T_de())
    joints += _camera_joints(names.end_effector, T_ed, names.gimbal_mount, names.gimbal_body, names.gimbal_optical,
                             names.gimbal_optical_joint, body_frames)  # fmt: skip
    return joints


@dataclass(frozen=True)
class ChainParts:
    """The names of one chain's links and joints: the fixed base mount, the base link b, the revolute
    joints and moving links, the fixed joint to the end effector, the end-effector link e."""

    base_mount: str
    base: str
    joints: tuple[str, ...]
    links: tuple[str, ...]
    end_effector_fixed: str
    end_effector: str


def _chain_joints(root: str, parts: ChainParts, T_bs: FloatArray, dh: FloatArray, lim: FloatArray) -> list[UrdfJoint]:
    """The joints of one chain below link ``root`` (the reference static camera's optical frame s):
    ``root -> b`` at ``inv(T_bs)``, one revolute joint per DH row ``[d, a, alpha]`` (limits ``lim`` (L, 2),
    rad), ``link L -> e`` at the last row's fixed part."""
    xyz, rpy = _pose(chain.inv_se3(T_bs))
    joints = [UrdfJoint(parts.base_mount, "fixed", root, parts.base, xyz, rpy)]
    parent = parts.base
    offset: tuple[tuple[float, float, float], tuple[float, float, float]] = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    for k in range(dh.shape[0]):
        lower, upper = (float(x) for x in lim[k])
        joints.append(UrdfJoint(parts.joints[k], "revolute", parent, parts.links[k], *offset, (lower, upper)))
        parent = parts.links[k]
        offset = _link_offset(dh[k])
    joints.append(UrdfJoint(parts.end_effector_fixed, "fixed", parent, parts.end_effector, *offset))
    return joints


def _camera_joints(
    parent: str,
    T_parent_optical: FloatArray,
    mount: str,
    body: str,
    optical: str,
    optical_joint: str,
    body_frames: bool,
) -> list[UrdfJoint]:
    """The fixed joint(s) placing a camera's optical link at ``T_parent_optical`` (4x4) in ``parent``:
    directly, or with ``body_frames`` through its ROS body link (optical = body turned by
    :data:`BODY_TO_OPTICAL_RPY`)."""
    if not body_frames:
        xyz, rpy = _pose(T_parent_optical)
        return [UrdfJoint(mount, "fixed", parent, optical, xyz, rpy)]
    T_optical_body = chain.inv_se3(chain.se3_from_tau(np.array([*BODY_TO_OPTICAL_RPY, 0.0, 0.0, 0.0])))
    xyz, rpy = _pose(T_parent_optical @ T_optical_body)
    return [
        UrdfJoint(mount, "fixed", parent, body, xyz, rpy),
        UrdfJoint(optical_joint, "fixed", body, optical, (0.0, 0.0, 0.0), BODY_TO_OPTICAL_RPY),
    ]


def _limits(limits: FloatArray | None, n: int) -> FloatArray:
    """(n, 2) joint limits (rad), +-pi where None; ValueError unless finite with lower <= upper."""
    lim = np.tile([-math.pi, math.pi], (n, 1)) if limits is None else np.asarray(limits, dtype=float).reshape(n, 2)
    if not np.all(np.isfinite(lim)) or np.any(lim[:, 0] > lim[:, 1]):
        raise ValueError(f"joint limits must be finite with lower <= upper (rad), got {lim.tolist()}")
    return lim


def layout_joints(
    cluster: CameraCluster, names: LayoutNames, limits: FloatArray | None = None, body_frames: bool = False
) -> list[UrdfJoint]:
    """The URDF joints of an N-camera ``cluster`` (module docstring), parents before children.

    Args:
        cluster: the cameras and chains (``T_cs`` of static cameras, ``tau_s`` / ``dh`` per chain,
            ``tau_d`` per chain camera; rad, m).
        names: from :func:`dcc_fg.export.naming.layout_names` for this cluster.
        limits: (J, 2) lower / upper joint angles (rad) in the flat joint order; None: +-pi.
        body_frames: root at cam0's ROS body frame and a body frame for every camera.
    """
    lim = _limits(limits, cluster.joint_count)
    if len(names.joints) != cluster.joint_count:
        raise ValueError(f"{len(names.joints)} joint names for a cluster with {cluster.joint_count} joints")
    ref = cluster.cameras[0].name
    root = names.optical[ref]
    joints: list[UrdfJoint] = []
    if body_frames:
        joints.append(UrdfJoint(names.optical_joint[ref], "fixed", names.body[ref], root, (0.0, 0.0, 0.0),
                                BODY_TO_OPTICAL_RPY))  # fmt: skip

    def camera(parent: str, name: str, T: FloatArray) -> list[UrdfJoint]:
        return _camera_joints(parent, T, names.mount[name], names.body[name], names.optical[name],
                              names.optical_joint[name], body_frames)  # fmt: skip

    for cam in cluster.cameras[1:]:
        if cam.is_static:
            joints += camera(root, cam.name, chain.inv_se3(cluster.T_cs(cam.name)))
    slices = cluster.joint_slices()
    for ch in cluster.chains:
        c = ch.name
        parts = ChainParts(
            names.base_mount[c], names.base[c], names.chain_joints[c], names.links[c], names.end_effector_fixed[c],
            names.end_effector[c],
        )  # fmt: skip
        joints += _chain_joints(root, parts, ch.T_bs(), ch.dh, lim[slices[ch.name]])
        for cam_name in cluster.cameras_on(ch.name):
            joints += camera(parts.end_effector, cam_name, chain.inv_se3(cluster.camera(cam_name).T_de()))
    return joints


def link_poses(joints: Sequence[UrdfJoint], q: Mapping[str, float]) -> dict[str, FloatArray]:
    """``T_root_link`` (4x4) of every link, revolute joint ``j`` at angle ``q[j]`` (rad); ``joints``
    parents before children (as :func:`cluster_joints` returns them)."""
    children = {j.child for j in joints}
    roots = [j.parent for j in joints if j.parent not in children]
    poses: dict[str, FloatArray] = {roots[0]: np.eye(4)} if roots else {}
    for j in joints:
        if j.parent not in poses:
            raise ValueError(f"joint {j.name}: parent link {j.parent} comes after it or is not connected to the root")
        poses[j.child] = poses[j.parent] @ j.transform(float(q.get(j.name, 0.0)))
    return poses


def relative_pose(joints: Sequence[UrdfJoint], q: Mapping[str, float], frame_from: str, frame_to: str) -> FloatArray:
    """``T_from_to``: the pose of link ``frame_to`` in link ``frame_from`` (maps points of ``frame_to``
    into ``frame_from``), revolute joints at ``q`` (rad)."""
    poses = link_poses(joints, q)
    return chain.inv_se3(poses[frame_from]) @ poses[frame_to]


def _number(x: float) -> str:
    """Shortest text that reads back as the same float64."""
    return repr(float(x))


def _vector(values: Sequence[float]) -> str:
    return " ".join(_number(v) for v in values)


def _comment(text: str) -> ET.Element:
    """An XML comment (``--`` is not allowed inside one)."""
    while "--" in text:
        text = text.replace("--", "- -")
    return ET.Comment(f" {text} ")


def self_check(cal: GimbalCalibration, joints: Sequence[UrdfJoint], names: ClusterNames, seed: int = 0) -> float:
    """Largest difference between the joints' forward kinematics ``T_s_d(q = theta)`` and
    ``inv(T_ds(theta))`` over a few joint angle sets (rad); RuntimeError (a bug) beyond
    :data:`SELF_CHECK_TOLERANCE`."""
    rng = np.random.default_rng(seed)
    worst = 0.0
    for theta in [np.zeros(cal.n_joints), *rng.uniform(-math.pi, math.pi, size=(4, cal.n_joints))]:
        q = dict(zip(names.joints, (float(x) for x in theta), strict=True))
        T_sd = relative_pose(joints, q, names.static_optical, names.gimbal_optical)
        worst = max(worst, float(np.abs(T_sd - chain.inv_se3(cal.T_ds(theta))).max()))
    if not worst <= SELF_CHECK_TOLERANCE:
        raise RuntimeError(f"URDF export: the chain's forward kinematics differ from inv(T_ds) by {worst:.3g}")
    return worst


def urdf_text(
    cal: GimbalCalibration,
    names: ClusterNames,
    limits: FloatArray | None = None,
    body_frames: bool = False,
    robot_name: str = "dcc_fg_cluster",
    notes: Sequence[str] = (),
) -> str:
    """The URDF XML of ``cal`` (module docstring), checked by :func:`self_check`.

    Args:
        cal: the calibration.
        names: link and joint names.
        limits: (L, 2) joint limits (rad); None: +-pi.
        body_frames: add the cameras' ROS body frames (root ``static_camera``).
        robot_name: the ``<robot name>``.
        notes: extra lines for the header comment (source file, where the limits came from).
    """
    joints = cluster_joints(cal, names, limits, body_frames)
    self_check(cal, joints, names)
    header = [
        "Dynamic camera cluster (dcc-fg): static camera s, gimbal base b, end effector e, gimbal camera d.",
        f"Root link {joints[0].parent}. Camera links {names.static_optical} (static camera s) and "
        f"{names.gimbal_optical} (gimbal camera d) are optical frames: z forward, x right, y down.",
        f"With revolute joint l at theta_l (rad, as in joint_angles.csv), the pose of {names.gimbal_optical} "
        f"in {names.static_optical} is T_sd(theta) = inv(T_ds(theta)).",
        "Joint axes: z of each joint frame (standard DH: A_l = Rz(theta_l) Tz(d_l) Tx(a_l) Rx(alpha_l)). "
        "Effort and velocity limits are not known from a calibration (written as 0).",
        *notes,
    ]
    return _robot_xml(robot_name, header, names.link_names(body_frames), joints)


def _robot_xml(robot_name: str, header: Sequence[str], links: Sequence[str], joints: Sequence[UrdfJoint]) -> str:
    """The URDF XML text: header comments, the links, the joints."""
    robot = ET.Element("robot", name=robot_name)
    for line in header:
        robot.append(_comment(line))
    for link in links:
        ET.SubElement(robot, "link", name=link)
    for j in joints:
        e = ET.SubElement(robot, "joint", name=j.name, type=j.kind)
        ET.SubElement(e, "parent", link=j.parent)
        ET.SubElement(e, "child", link=j.child)
        ET.SubElement(e, "origin", xyz=_vector(j.xyz), rpy=_vector(j.rpy))
        if j.kind == "revolute":
            lower, upper = j.limits or (-math.pi, math.pi)
            ET.SubElement(e, "axis", xyz="0 0 1")
            ET.SubElement(e, "limit", lower=_number(lower), upper=_number(upper), effort="0", velocity="0")
    ET.indent(robot, space="  ")
    return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"


def layout_self_check(cluster: CameraCluster, joints: Sequence[UrdfJoint], names: LayoutNames, seed: int = 0) -> float:
    """Largest difference between the joints' forward kinematics ``T_s_c(q = theta)`` of every camera c
    and ``inv(T_cs(c, theta))`` over a few flat joint-angle vectors (rad); RuntimeError (a bug) beyond
    :data:`SELF_CHECK_TOLERANCE`."""
    rng = np.random.default_rng(seed)
    J = cluster.joint_count
    root = names.optical[cluster.cameras[0].name]
    worst = 0.0
    for theta in [np.zeros(J), *rng.uniform(-math.pi, math.pi, size=(4, J))]:
        q = dict(zip(names.joints, (float(x) for x in theta), strict=True))
        poses = link_poses(joints, q)
        T_root_inv = chain.inv_se3(poses[root])
        for cam in cluster.camera_names:
            T_sc = T_root_inv @ poses[names.optical[cam]]
            worst = max(worst, float(np.abs(T_sc - chain.inv_se3(cluster.T_cs(cam, theta))).max()))
    if not worst <= SELF_CHECK_TOLERANCE:
        raise RuntimeError(f"URDF export: the cluster's forward kinematics differ from inv(T_cs) by {worst:.3g}")
    return worst


def layout_urdf_text(
    cluster: CameraCluster,
    names: LayoutNames,
    limits: FloatArray | None = None,
    body_frames: bool = False,
    robot_name: str = "dcc_fg_cluster",
    notes: Sequence[str] = (),
) -> str:
    """The URDF XML of an N-camera ``cluster`` (module docstring), checked by :func:`layout_self_check`.

    Args:
        cluster: the cameras and chains.
        names: link and joint names (:func:`dcc_fg.export.naming.layout_names`).
        limits: (J, 2) joint limits (rad) in the flat joint order; None: +-pi.
        body_frames: add every camera's ROS body frame (root: cam0's).
        robot_name: the ``<robot name>``.
        notes: extra lines for the header comment.
    """
    joints = layout_joints(cluster, names, limits, body_frames)
    layout_self_check(cluster, joints, names)
    root = names.optical[cluster.cameras[0].name]
    cams = ", ".join(f"{names.optical[c.name]} ({c.name}, {'static' if c.is_static else 'on chain ' + c.mount})"
                     for c in cluster.cameras)  # fmt: skip
    order = ", ".join(names.joints) or "none"
    header = [
        f"Dynamic camera cluster (dcc-fg), {len(cluster.cameras)} cameras: {cams}.",
        f"Root link {joints[0].parent if joints else root}. Camera links are optical frames: z forward, x right, "
        "y down. Chains: "
        + ", ".join(f"{names.base[c.name]} .. {names.end_effector[c.name]}" for c in cluster.chains)
        + ".",
        f"With the revolute joints ({order}) at the flat joint-angle vector theta (rad; chains in file order), the "
        f"pose of camN's link in {root} is T_s_camN(theta) = inv(T_cs(camN, theta)).",
        "Joint axes: z of each joint frame (standard DH: A_l = Rz(theta_l) Tz(d_l) Tx(a_l) Rx(alpha_l)). "
        "Effort and velocity limits are not known from a calibration (written as 0).",
        *notes,
    ]
    links = [joints[0].parent, *(j.child for j in joints)] if joints else [root]
    return _robot_xml(robot_name, header, links, joints)
