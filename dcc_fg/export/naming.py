"""Names of the exported cluster's links (TF frames) and joints, shared by the URDF and the joint-state bag.

A ``sensor_msgs/JointState`` stream drives a URDF through ``robot_state_publisher`` only when its
joint names are the URDF's, so both exports take their names from one :class:`ClusterNames`.

Default names (every one behind ``prefix``; see :func:`cluster_names`):

* links: ``static_camera_optical`` (frame s, the URDF's root), ``gimbal_base`` (frame b = DH frame 0),
  ``gimbal_link_1 .. gimbal_link_L`` (the moving links), ``gimbal_end_effector`` (frame e = DH frame L),
  ``gimbal_camera_optical`` (frame d); with body frames also ``static_camera`` and ``gimbal_camera``
  (ROS body convention, x forward, y left, z up, REP 103);
* revolute joints: ``joint_1 .. joint_L`` (as ``dcc-fg simulate`` names them in its bags), or the
  names given (used verbatim, without the prefix: a gimbal driver's names are what they are);
* fixed joints: ``gimbal_base_mount`` (s -> b), ``gimbal_end_effector_fixed`` (link L -> e),
  ``gimbal_camera_mount`` (e -> d, the ``tau_d`` mount), and with body frames
  ``static_camera_optical_joint`` / ``gimbal_camera_optical_joint``.

An N-camera cluster (a ``cameras:`` / ``chains:`` calibration, :mod:`dcc_fg.cluster`) is named per
camera and chain instead (:func:`layout_names`): ``camN_optical``, ``<chain>_base``,
``<chain>_link_l``, ``<chain>_end_effector``, revolute ``joint_l`` (one chain) or ``<chain>_joint_l``.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

#: A name usable as a URDF link / joint name and a TF frame id (no spaces, no leading slash).
NAME_PATTERN = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-/]*$")


@dataclass(frozen=True)
class ClusterNames:
    """Every link and joint name of the exported cluster (see the module docstring).

    Attributes:
        static_optical: link of the static camera frame s (optical: z forward, x right, y down).
        static_body: the static camera's ROS body frame (x forward, y left, z up); used only with body frames.
        base: the gimbal base frame b (DH frame 0).
        links: the L moving links; link l turns with joint l.
        end_effector: frame e (DH frame L).
        gimbal_optical: link of the gimbal camera frame d (optical).
        gimbal_body: the gimbal camera's ROS body frame; used only with body frames.
        joints: the L revolute joints, joint l turning by theta_l (rad).
        base_mount, end_effector_fixed, gimbal_mount: the fixed joints s -> b, link L -> e, e -> d.
        static_optical_joint, gimbal_optical_joint: the fixed joints body -> optical (body frames only).
    """

    static_optical: str
    static_body: str
    base: str
    links: tuple[str, ...]
    end_effector: str
    gimbal_optical: str
    gimbal_body: str
    joints: tuple[str, ...]
    base_mount: str
    end_effector_fixed: str
    gimbal_mount: str
    static_optical_joint: str
    gimbal_optical_joint: str

    def link_names(self, body_frames: bool) -> list[str]:
        """Every link of the URDF, root first."""
        body = [self.static_body] if body_frames else []
        tail = [self.gimbal_body] if body_frames else []
        return [*body, self.static_optical, self.base, *self.links, self.end_effector, *tail, self.gimbal_optical]

    def joint_names(self, body_frames: bool) -> list[str]:
        """Every joint of the URDF (fixed and revolute)."""
        names = [self.base_mount, *self.joints, self.end_effector_fixed, self.gimbal_mount]
        return names + ([self.static_optical_joint, self.gimbal_optical_joint] if body_frames else [])


def check_name(name: str, what: str) -> str:
    """``name`` if it is a usable link / joint / frame name, else ValueError naming ``what``."""
    if not NAME_PATTERN.match(name):
        raise ValueError(
            f"{what} {name!r} is not a usable URDF / TF name (letters, digits, '_', '.', '-', '/'; not starting "
            "with '/', '.' or '-', no spaces)"
        )
    return name


def parse_joint_names(text: str, n_joints: int, source: str) -> tuple[str, ...]:
    """``a,b,c`` -> the L joint names (checked: L of them, distinct, usable); errors name ``source``
    (the option and the calibration file)."""
    names = tuple(s.strip() for s in text.split(",")) if text.strip() else ()
    if len(names) != n_joints:
        raise ValueError(f"--joint-names {text!r}: {len(names)} name(s) given, but {source} has {n_joints} joint(s)")
    for n in names:
        check_name(n, "--joint-names: joint name")
    if len(set(names)) != len(names):
        raise ValueError(f"--joint-names {text!r}: the joint names must be distinct")
    return names


def cluster_names(
    n_joints: int,
    prefix: str = "",
    joints: Sequence[str] | None = None,
    static_frame: str | None = None,
    gimbal_frame: str | None = None,
) -> ClusterNames:
    """The names for an L-joint cluster (module docstring): ``prefix`` + the defaults; ``joints``
    (verbatim), ``static_frame`` and ``gimbal_frame`` (the two optical camera links, verbatim)
    replace theirs.

    Raises:
        ValueError: a name that is not usable, the wrong number of joint names, or two links or two
            joints of the same name.
    """
    p = prefix
    if p:
        check_name(p, "--prefix")
    joint_list = tuple(joints) if joints is not None else tuple(f"{p}joint_{k + 1}" for k in range(n_joints))
    if len(joint_list) != n_joints:
        raise ValueError(f"{len(joint_list)} joint names for {n_joints} joints")
    names = ClusterNames(
        static_optical=static_frame or f"{p}static_camera_optical",
        static_body=f"{p}static_camera",
        base=f"{p}gimbal_base",
        links=tuple(f"{p}gimbal_link_{k + 1}" for k in range(n_joints)),
        end_effector=f"{p}gimbal_end_effector",
        gimbal_optical=gimbal_frame or f"{p}gimbal_camera_optical",
        gimbal_body=f"{p}gimbal_camera",
        joints=joint_list,
        base_mount=f"{p}gimbal_base_mount",
        end_effector_fixed=f"{p}gimbal_end_effector_fixed",
        gimbal_mount=f"{p}gimbal_camera_mount",
        static_optical_joint=f"{p}static_camera_optical_joint",
        gimbal_optical_joint=f"{p}gimbal_camera_optical_joint",
    )
    for what, value in (("static frame", names.static_optical), ("gimbal frame", names.gimbal_optical)):
        check_name(value, what)
    for n in joint_list:
        check_name(n, "joint name")
    for kind, values in (("link", names.link_names(True)), ("joint", names.joint_names(True))):
        dup = sorted({v for v in values if values.count(v) > 1})
        if dup:
            raise ValueError(f"two {kind}s would both be named {', '.join(dup)}; choose other names")
    return names


@dataclass(frozen=True)
class LayoutNames:
    """Link and joint names of an N-camera cluster's URDF (:func:`layout_names`).

    Attributes:
        optical, body: camera -> its optical link (z forward, x right, y down) / ROS body link.
        mount, optical_joint: camera -> the fixed joint placing it (from cam0's optical link for a
            static camera, from its chain's end effector otherwise) / its body -> optical joint.
        base, end_effector, base_mount, end_effector_fixed: chain -> frame b, frame e, the fixed joints
            cam0 -> b and link L -> e.
        links: chain -> its L moving links.
        joints: the revolute joints of every chain, in the order of the flat joint-angle vector.
        chain_joints: chain -> its revolute joints.
    """

    optical: dict[str, str]
    body: dict[str, str]
    mount: dict[str, str]
    optical_joint: dict[str, str]
    base: dict[str, str]
    links: dict[str, tuple[str, ...]]
    end_effector: dict[str, str]
    base_mount: dict[str, str]
    end_effector_fixed: dict[str, str]
    joints: tuple[str, ...]
    chain_joints: dict[str, tuple[str, ...]]


def layout_names(
    cameras: Sequence[str],
    chains: Sequence[tuple[str, int]],
    prefix: str = "",
    joints: Sequence[str] | None = None,
) -> LayoutNames:
    """Names for a cluster of ``cameras`` (``cam0`` first) and ``chains`` ((name, L), in flat-vector order).

    Links ``PREFIXcamN_optical`` / ``PREFIXcamN`` (body), ``PREFIX<chain>_base``, ``PREFIX<chain>_link_l``,
    ``PREFIX<chain>_end_effector``; fixed joints ``PREFIXcamN_mount``, ``PREFIXcamN_optical_joint``,
    ``PREFIX<chain>_base_mount``, ``PREFIX<chain>_end_effector_fixed``; revolute joints
    ``PREFIXjoint_l`` for one chain (as for two cameras), ``PREFIX<chain>_joint_l`` for several, or
    ``joints`` verbatim (the flat order).

    Raises:
        ValueError: a name that is not usable, the wrong number of joint names, or two links or two
            joints of the same name.
    """
    p = prefix
    if p:
        check_name(p, "--prefix")
    total = sum(n for _, n in chains)
    if joints is None:
        flat = [
            f"{p}joint_{k + 1}" if len(chains) == 1 else f"{p}{c}_joint_{k + 1}" for c, n in chains for k in range(n)
        ]
    else:
        flat = list(joints)
    if len(flat) != total:
        raise ValueError(f"{len(flat)} joint names for {total} joints")
    per_chain, k = {}, 0
    for c, n in chains:
        per_chain[c] = tuple(flat[k : k + n])
        k += n
    names = LayoutNames(
        optical={c: f"{p}{c}_optical" for c in cameras},
        body={c: f"{p}{c}" for c in cameras},
        mount={c: f"{p}{c}_mount" for c in cameras},
        optical_joint={c: f"{p}{c}_optical_joint" for c in cameras},
        base={c: f"{p}{c}_base" for c, _ in chains},
        links={c: tuple(f"{p}{c}_link_{k + 1}" for k in range(n)) for c, n in chains},
        end_effector={c: f"{p}{c}_end_effector" for c, _ in chains},
        base_mount={c: f"{p}{c}_base_mount" for c, _ in chains},
        end_effector_fixed={c: f"{p}{c}_end_effector_fixed" for c, _ in chains},
        joints=tuple(flat),
        chain_joints=per_chain,
    )
    for n in flat:
        check_name(n, "joint name")
    links = [*names.optical.values(), *names.body.values(), *names.base.values(), *names.end_effector.values()]
    links += [x for v in names.links.values() for x in v]
    joint_list = [*names.mount.values(), *names.optical_joint.values(), *names.base_mount.values()]
    joint_list += [*names.end_effector_fixed.values(), *flat]
    for kind, values in (("link", links), ("joint", joint_list)):
        dup = sorted({v for v in values if values.count(v) > 1})
        if dup:
            raise ValueError(f"two {kind}s would both be named {', '.join(dup)}; choose other names")
    return names
