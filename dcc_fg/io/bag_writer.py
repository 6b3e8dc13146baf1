"""Writing ROS1 / ROS2 bags with images, IMU, poses and joint states (rosbags): the one bag writer.

:class:`BagWriter` serializes and writes messages one at a time, so a long simulated flight never
sits in memory.  The bag is written under a temporary name next to the target and renamed into
place when it is closed without an error, so a crash never leaves a truncated bag under the final
name.  :func:`write_ros1_bag` / :func:`write_ros2_bag` write calibration image pairs through it.

Types: ROS1 Noetic for ``ros=1`` (a ``.bag`` file), ROS2 Humble for ``ros=2`` (a bag folder,
sqlite3 or mcap storage).  Record time = header stamp unless given.  Units: ns, m/s^2, rad/s,
metres, radians.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterable, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from rosbags.rosbag1 import Writer as Rosbag1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Rosbag2Writer
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore
from scipy.spatial.transform import Rotation

from dcc_fg.io.bags import COMPRESSED_IMAGE, IMAGE, JOINT_STATE
from dcc_fg.io.folders import FramePair

IMU = "sensor_msgs/msg/Imu"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"


def header_message(typestore: Typestore, stamp: int, frame_id: str) -> Any:
    """``std_msgs/Header`` at ``stamp`` ns (``seq = 0`` in ROS1)."""
    types = typestore.types
    time = types["builtin_interfaces/msg/Time"](sec=stamp // 1_000_000_000, nanosec=stamp % 1_000_000_000)
    fields = {name for name, _ in typestore.fielddefs["std_msgs/msg/Header"][1]}
    extra = {"seq": 0} if "seq" in fields else {}
    return types["std_msgs/msg/Header"](stamp=time, frame_id=frame_id, **extra)


def image_message(
    typestore: Typestore, img: NDArray[np.generic], stamp: int, frame_id: str, compressed: bool = False
) -> tuple[str, Any]:
    """(msgtype, message) for a numpy image; grey -> mono8 / mono16, 3 channels -> bgr8,
    4 channels -> bgra8; ``compressed`` gives a PNG ``CompressedImage``."""
    header = header_message(typestore, stamp, frame_id)
    if compressed:
        ok, buf = cv2.imencode(".png", img)
        if not ok:
            raise ValueError(f"cannot PNG-encode an image of shape {img.shape} {img.dtype}")
        msg = typestore.types[COMPRESSED_IMAGE](header=header, format="png", data=buf.reshape(-1).astype(np.uint8))
        return COMPRESSED_IMAGE, msg
    img = np.ascontiguousarray(img)
    channels = 1 if img.ndim == 2 else img.shape[2]
    encodings = {(np.dtype(np.uint8), 1): "mono8", (np.dtype(np.uint16), 1): "mono16"}
    encodings.update({(np.dtype(np.uint8), 3): "bgr8", (np.dtype(np.uint8), 4): "bgra8"})
    key = (img.dtype, channels)
    if key not in encodings:
        raise ValueError(f"no sensor_msgs/Image encoding for {img.dtype} images with {channels} channels")
    data = img.astype(img.dtype.newbyteorder("<"), copy=False).view(np.uint8).reshape(-1)
    msg = typestore.types[IMAGE](
        header=header,
        height=img.shape[0],
        width=img.shape[1],
        encoding=encodings[key],
        is_bigendian=0,
        step=img.shape[1] * channels * img.dtype.itemsize,
        data=data,
    )
    return IMAGE, msg


def joint_state_message(typestore: Typestore, q: NDArray[np.float64], stamp: int, names: Sequence[str]) -> Any:
    """``sensor_msgs/JointState`` with positions ``q`` (radians)."""
    return typestore.types[JOINT_STATE](
        header=header_message(typestore, stamp, ""),
        name=list(names),
        position=np.asarray(q, dtype=np.float64),
        velocity=np.zeros(0),
        effort=np.zeros(0),
    )


def joint_names(n_joints: int) -> list[str]:
    """Default joint names ``joint_1 .. joint_L``."""
    return [f"joint_{k + 1}" for k in range(n_joints)]


class BagWriter:
    """Context manager writing messages to a new bag (see the module docstring).

    Args:
        path: ``.bag`` file (ROS1) or bag folder (ROS2) to create; an existing one is replaced
            only once the new bag is complete, or refused (FileExistsError) if not ``overwrite``.
        ros: 1 or 2.
        storage: ROS2 storage plugin.
        overwrite: replace an existing bag at ``path``.
    """

    def __init__(
        self,
        path: str | Path,
        ros: Literal[1, 2] = 2,
        storage: Literal["sqlite3", "mcap"] = "sqlite3",
        overwrite: bool = True,
    ) -> None:
        if ros not in (1, 2):
            raise ValueError(f"ros must be 1 or 2, got {ros}")
        self.path = Path(path)
        self.ros = ros
        # written as <parent>/.<name>.partial/<name> so a ROS2 bag's storage file keeps the bag's name
        self._tmp_dir = self.path.with_name(f".{self.path.name}.partial")
        self._tmp = self._tmp_dir / self.path.name
        self.typestore = get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)
        self._storage = storage
        self._overwrite = overwrite
        self._writer: Any = None
        self._conns: dict[str, Any] = {}
        self.counts: dict[str, int] = {}

    def __enter__(self) -> BagWriter:
        if not self._overwrite and self.path.exists():
            raise FileExistsError(f"{self.path} exists already, not overwriting.")
        remove_path(self._tmp_dir)
        self._tmp_dir.mkdir(parents=True)
        if self.ros == 1:
            self._writer = Rosbag1Writer(self._tmp)
        else:
            plugin = StoragePlugin.MCAP if self._storage == "mcap" else StoragePlugin.SQLITE3
            self._writer = Rosbag2Writer(self._tmp, version=Rosbag2Writer.VERSION_LATEST, storage_plugin=plugin)
        self._writer.open()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self._writer.close()
        if exc_type is not None:
            remove_path(self._tmp_dir)
            return
        remove_path(self.path)
        os.replace(self._tmp, self.path)
        self._tmp_dir.rmdir()

    # ------------------------------------------------------------------ messages
    def write(self, topic: str, msgtype: str, stamp_ns: int, msg: Any) -> None:
        """Write one deserialized message (record time ``stamp_ns``)."""
        if topic not in self._conns:
            self._conns[topic] = self._writer.add_connection(topic, msgtype, typestore=self.typestore)
        ts = self.typestore
        data = ts.serialize_ros1(msg, msgtype) if self.ros == 1 else ts.serialize_cdr(msg, msgtype)
        self._writer.write(self._conns[topic], int(stamp_ns), data)
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def image(
        self,
        topic: str,
        stamp_ns: int,
        img: NDArray[np.generic],
        frame_id: str,
        compressed: bool = False,
        record_ns: int | None = None,
    ) -> None:
        """``sensor_msgs/Image`` (mono8/mono16/bgr8/bgra8) or PNG ``CompressedImage``; ``record_ns`` sets a
        record time different from the header stamp."""
        msgtype, msg = image_message(self.typestore, img, int(stamp_ns), frame_id, compressed)
        self.write(topic, msgtype, stamp_ns if record_ns is None else record_ns, msg)

    def imu(
        self,
        topic: str,
        stamp_ns: int,
        acc: NDArray[np.float64],
        gyro: NDArray[np.float64],
        frame_id: str = "imu",
        record_ns: int | None = None,
    ) -> None:
        """``sensor_msgs/Imu``: specific force ``acc`` (m/s^2), rate ``gyro`` (rad/s); no orientation
        (``orientation_covariance[0] = -1`` as the message definition asks).  ``record_ns`` sets a
        record time different from the header stamp (as a driver's late messages have)."""
        t = self.typestore.types
        vec = t["geometry_msgs/msg/Vector3"]
        cov_none = np.zeros(9)
        cov_none[0] = -1.0
        msg = t[IMU](
            header=header_message(self.typestore, int(stamp_ns), frame_id),
            orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=cov_none,
            angular_velocity=vec(x=float(gyro[0]), y=float(gyro[1]), z=float(gyro[2])),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=vec(x=float(acc[0]), y=float(acc[1]), z=float(acc[2])),
            linear_acceleration_covariance=np.zeros(9),
        )
        self.write(topic, IMU, stamp_ns if record_ns is None else record_ns, msg)

    def pose(self, topic: str, stamp_ns: int, T: NDArray[np.float64], frame_id: str = "world") -> None:
        """``geometry_msgs/PoseStamped`` of a 4x4 transform (child -> ``frame_id``, metres;
        unit quaternion with ``w >= 0``)."""
        t = self.typestore.types
        q = Rotation.from_matrix(T[:3, :3]).as_quat(canonical=True)  # x, y, z, w
        p = T[:3, 3]
        pose = t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=float(p[2])),
            orientation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        )
        msg = t[POSE_STAMPED](header=header_message(self.typestore, int(stamp_ns), frame_id), pose=pose)
        self.write(topic, POSE_STAMPED, stamp_ns, msg)

    def joints(self, topic: str, stamp_ns: int, q: NDArray[np.float64], names: list[str] | None = None) -> None:
        """``sensor_msgs/JointState`` positions (radians); names ``joint_1..joint_L`` by default."""
        names = names or joint_names(len(q))
        self.write(topic, JOINT_STATE, stamp_ns, joint_state_message(self.typestore, q, int(stamp_ns), names))

    def frame_pair(
        self, fr: FramePair, static_topic: str, dynamic_topic: str, joint_topic: str, compressed: bool = False
    ) -> None:
        """One calibration image pair: the static image at ``fr.timestamp_ns`` (frame ``cam0``), the
        dynamic one at ``fr.dynamic_timestamp_ns`` or ``fr.timestamp_ns`` (``cam1``) and, if the
        frame has joints, a ``JointState`` at the static stamp."""
        td = fr.dynamic_timestamp_ns or fr.timestamp_ns
        self.image(static_topic, fr.timestamp_ns, fr.static, "cam0", compressed)
        self.image(dynamic_topic, td, fr.dynamic, "cam1", compressed)
        if fr.joints is not None:
            self.joints(joint_topic, fr.timestamp_ns, fr.joints)


def remove_path(path: Path) -> None:
    """Delete a file or a folder tree if it exists."""
    if path.is_dir():
        shutil.rmtree(path)
    elif path.exists():
        path.unlink()


def write_frame_pair_bag(
    path: str | Path,
    frames: Iterable[FramePair],
    ros: Literal[1, 2],
    storage: Literal["sqlite3", "mcap"] = "sqlite3",
    topics: tuple[str, str, str] = ("/cam0/image_raw", "/cam1/image_raw", "/gimbal/joint_states"),
    compressed: bool = False,
) -> Path:
    """Write calibration image pairs to a new bag (FileExistsError if ``path`` exists).

    Each frame gives one image message per camera topic (record time = header stamp: the
    frame's ``timestamp_ns`` for the static image, ``dynamic_timestamp_ns`` or ``timestamp_ns``
    for the dynamic one) and, if it has joints, a ``JointState`` (names ``joint_1..joint_L``) at
    the static stamp.  ``topics`` are the static, dynamic and joint topics; ``compressed`` writes
    PNG ``CompressedImage`` messages.
    """
    with BagWriter(path, ros, storage, overwrite=False) as bag:
        for fr in frames:
            bag.frame_pair(fr, *topics, compressed=compressed)
    return Path(path)


def write_ros1_bag(
    path: str | Path,
    frames: Iterable[FramePair],
    static_topic: str = "/cam0/image_raw",
    dynamic_topic: str = "/cam1/image_raw",
    joint_topic: str = "/gimbal/joint_states",
    compressed: bool = False,
) -> Path:
    """Write frames to a new ROS1 bag file (ROS1 Noetic types), see :func:`write_frame_pair_bag`."""
    return write_frame_pair_bag(path, frames, 1, "sqlite3", (static_topic, dynamic_topic, joint_topic), compressed)


def write_ros2_bag(
    path: str | Path,
    frames: Iterable[FramePair],
    static_topic: str = "/cam0/image_raw",
    dynamic_topic: str = "/cam1/image_raw",
    joint_topic: str = "/gimbal/joint_states",
    compressed: bool = False,
    storage: Literal["sqlite3", "mcap"] = "sqlite3",
) -> Path:
    """Write frames to a new ROS2 bag folder (Humble types; ``storage``: sqlite3 or mcap plugin),
    see :func:`write_frame_pair_bag`."""
    return write_frame_pair_bag(path, frames, 2, storage, (static_topic, dynamic_topic, joint_topic), compressed)
