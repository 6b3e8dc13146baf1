"""Joint angles of a calibration or a VIO run (``joint_angles.csv``) as ``sensor_msgs/JointState`` in a bag.

Played back with the exported URDF (same joint names, :mod:`dcc_fg.export.naming`) through
``robot_state_publisher``, the bag moves the gimbal camera's TF frame as dcc-fg estimated it (RViz,
Foxglove). One message per CSV row: header stamp and record time = ``timestamp_ns`` (integer ns,
never parsed through a float), ``position`` = ``theta_1..theta_L`` (rad), ``name`` the joint names,
``velocity`` / ``effort`` empty, ``frame_id`` empty. Rows are written in time order.

A path ending in ``.bag`` is a ROS1 bag (Noetic message types), any other a ROS2 bag folder (Humble
types; sqlite3 or mcap storage); both are written by :class:`dcc_fg.io.bag_writer.BagWriter`
(under a temporary name, renamed into place when complete).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from dcc_fg.io import validate
from dcc_fg.io.bag_writer import BagWriter
from dcc_fg.io.bags import BAG_ERRORS, JOINT_STATE, is_bag, open_bag
from dcc_fg.io.output_set import OutputPathError, check_writable_location, input_conflict

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]

DEFAULT_TOPIC = "/joint_states"


def expected_header(n_joints: int) -> list[str]:
    """``timestamp_ns,theta_1,...,theta_L``: the columns of ``joint_angles.csv``."""
    return ["timestamp_ns", *(f"theta_{k + 1}" for k in range(n_joints))]


def read_joint_angles(
    path: str | Path, n_joints: int, calibration: str, allow_unseen: bool = False
) -> tuple[IntArray, FloatArray]:
    """A ``joint_angles.csv`` of ``dcc-fg calibrate`` / ``validate`` / ``vio`` for an L-joint calibration.

    ``allow_unseen``: NaN angles are kept (``dcc-fg calibrate --cluster`` writes NaN for a chain that no
    camera saw in a snapshot); the other angles are checked as always.

    Returns:
        (N,) int64 stamps (ns, exact) and (N, L) joint angles (rad), in the file's row order.

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file (and line): a header other than ``timestamp_ns,theta_1..theta_L``
            with the calibration's L (``calibration`` names it), a row with the wrong number of
            fields, a stamp that is not a non-negative integer (ns), an angle that is not a finite
            number of radians within one turn, or no rows.
    """
    path = Path(path)
    text = validate.read_text(path, "joint angles CSV", ",".join(expected_header(n_joints)))
    lines = [(k, ln.strip()) for k, ln in enumerate(text.splitlines(), start=1) if ln.strip()]
    want = expected_header(n_joints)
    if not lines:
        raise ValueError(f"{path}: empty file; expected the header {','.join(want)} and one row per stamp")
    header = [c.strip() for c in lines[0][1].split(",")]
    if header != want:
        raise ValueError(
            f"{path}:{lines[0][0]}: columns {','.join(header)}; expected {','.join(want)} ({calibration} has "
            f"{n_joints} joint(s); a joint_angles.csv of dcc-fg calibrate, validate or vio with that calibration)"
        )
    stamps: list[int] = []
    rows: list[list[float]] = []
    line_of_row: list[int] = []
    for k, ln in lines[1:]:
        fields = [f.strip() for f in ln.split(",")]
        if len(fields) != len(want):
            raise ValueError(f"{path}:{k}: {len(fields)} fields, expected {len(want)} ({','.join(want)})")
        try:
            stamp = int(fields[0])
        except ValueError:
            raise ValueError(f"{path}:{k}: timestamp_ns {fields[0]!r} is not an integer (ns)") from None
        if stamp < 0:
            raise ValueError(f"{path}:{k}: timestamp_ns {stamp} is negative")
        try:
            rows.append([float(x) for x in fields[1:]])
        except ValueError:
            raise ValueError(f"{path}:{k}: not a number in '{ln}'") from None
        stamps.append(stamp)
        line_of_row.append(k)
    if not stamps:
        raise ValueError(f"{path}: no rows after the header {','.join(want)}")
    angles = np.array(rows, dtype=float).reshape(len(rows), n_joints)
    validate.check_joint_angles(np.where(np.isnan(angles), 0.0, angles) if allow_unseen else angles, str(path),
                                line_of_row)  # fmt: skip
    return np.array(stamps, dtype=np.int64), angles


def ros_version(out: Path) -> Literal[1, 2]:
    """1 for a ``.bag`` path (ROS1 bag file), 2 otherwise (ROS2 bag folder)."""
    return 1 if out.suffix == ".bag" else 2


def _only_joint_states(path: Path) -> bool:
    """True when ``path`` is a readable bag whose every connection is a ``sensor_msgs/JointState`` topic
    (a bag this export wrote earlier: it may be replaced)."""
    try:
        with open_bag(path) as reader:
            return bool(reader.connections) and all(c.msgtype == JOINT_STATE for c in reader.connections)
    except (ValueError, *BAG_ERRORS, AssertionError):
        return False


def check_bag_out(out: Path, inputs: Mapping[str, str | Path | None], option: str = "--out") -> None:
    """Refuse, before any work, a bag path that is an input, inside an input folder or holding an
    input, that clashes with an existing file or folder of the other kind, or that exists and holds
    anything but joint states (a recording is never replaced); the nearest existing folder must be
    writable. OutputPathError (a ValueError) naming ``option`` and the path."""
    reason = input_conflict(out, inputs, option)
    if reason:
        raise OutputPathError(reason)
    ros = ros_version(out)
    if out.exists() or out.is_symlink():
        kind = "a ROS1 bag file (.bag)" if ros == 1 else "a ROS2 bag folder (any name not ending in .bag)"
        wrong = out.is_dir() if ros == 1 else not out.is_dir()
        if wrong:
            raise OutputPathError(f"{option} {out}: exists as a {'folder' if out.is_dir() else 'file'}, but names "
                                  f"{kind}; choose another {option}")  # fmt: skip
        if not (is_bag(out) and _only_joint_states(out)):
            raise OutputPathError(
                f"{option} {out}: exists and is not a joint-state bag written by dcc-fg export (it may be a recording "
                f"or other data); remove it or choose another {option}"
            )
    check_writable_location(out.parent, option, "bag")


def write_joint_state_bag(
    out: str | Path,
    stamps_ns: IntArray,
    angles: FloatArray,
    names: Sequence[str],
    topic: str = DEFAULT_TOPIC,
    storage: Literal["sqlite3", "mcap"] = "sqlite3",
) -> int:
    """Write one ``sensor_msgs/JointState`` per row (module docstring) into a new bag at ``out``
    (ROS1 for ``*.bag``, else ROS2 with ``storage``); an existing bag there is replaced only once the
    new one is complete. Returns the number of messages.

    Args:
        out: bag path.
        stamps_ns: (N,) int64 stamps, ns.
        angles: (N, L) joint angles, rad.
        names: the L joint names (the URDF's).
        topic: the JointState topic.
        storage: ROS2 storage plugin.
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    a = np.asarray(angles, dtype=float).reshape(stamps.shape[0], -1)
    if a.shape[1] != len(names):
        raise ValueError(f"{a.shape[1]} joint angles per row but {len(names)} joint names")
    if not topic.startswith("/") or " " in topic:
        raise ValueError(f"--topic {topic!r}: a ROS topic name starts with '/' and has no spaces")
    order = np.argsort(stamps, kind="stable")
    with BagWriter(Path(out), ros_version(Path(out)), storage, overwrite=True) as bag:
        for i in order:
            bag.joints(topic, int(stamps[i]), a[i], list(names))
    return int(stamps.shape[0])
