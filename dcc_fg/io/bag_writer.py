"""Streaming writer of ROS1 / ROS2 bags with images, IMU, poses and joint states (rosbags).

Messages are serialized and written one at a time, so a long simulated flight never sits in
memory.  The bag is written under a temporary name next to the target and renamed into place
when it is closed without an error, so a crash never leaves a truncated bag under the final name.

Types: ROS1 Noetic for ``ros=1`` (a ``.bag`` file), ROS2 Humble for ``ros=2`` (a bag folder,
sqlite3 or mcap storage).  Record time = header stamp.  Units: ns, m/s^2, rad/s, metres, radians.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from rosbags.rosbag1 import Writer as Rosbag1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Rosbag2Writer
from rosbags.typesys import Stores, get_typestore

from dcc_fg.io.bags import JOINT_STATE, _header, image_message, joint_state_message

IMU = "sensor_msgs/msg/Imu"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"


def quaternion_xyzw(R: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit quaternion ``[x, y, z, w]`` (w >= 0) of a rotation matrix."""
    m = np.asarray(R, dtype=float)
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = np.array([(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s])
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(max(1.0 + m[i, i] - m[j, j] - m[k, k], 1e-300))
        q = np.zeros(4)
        q[i] = 0.25 * s
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
        q[3] = (m[k, j] - m[j, k]) / s
    q /= np.linalg.norm(q)
    return q if q[3] >= 0 else -q


class BagWriter:
    """Context manager writing messages to a new bag (see the module docstring).

    Args:
        path: ``.bag`` file (ROS1) or bag folder (ROS2) to create; an existing one is replaced
            only once the new bag is complete.
        ros: 1 or 2.
        storage: ROS2 storage plugin.
    """

    def __init__(self, path: str | Path, ros: Literal[1, 2] = 2, storage: Literal["sqlite3", "mcap"] = "sqlite3"):
        if ros not in (1, 2):
            raise ValueError(f"ros must be 1 or 2, got {ros}")
        self.path = Path(path)
        self.ros = ros
        # written as <parent>/.<name>.partial/<name> so a ROS2 bag's storage file keeps the bag's name
        self._tmp_dir = self.path.with_name(f".{self.path.name}.partial")
        self._tmp = self._tmp_dir / self.path.name
        self.typestore = get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)
        self._storage = storage
        self._writer: Any = None
        self._conns: dict[str, Any] = {}
        self.counts: dict[str, int] = {}

    def __enter__(self) -> BagWriter:
        _remove(self._tmp_dir)
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
            _remove(self._tmp_dir)
            return
        _remove(self.path)
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

    def image(self, topic: str, stamp_ns: int, img: NDArray[np.generic], frame_id: str, compressed: bool = False):
        """``sensor_msgs/Image`` (mono8/mono16/bgr8/bgra8) or PNG ``CompressedImage``."""
        msgtype, msg = image_message(self.typestore, img, int(stamp_ns), frame_id, compressed)
        self.write(topic, msgtype, stamp_ns, msg)

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
            header=_header(self.typestore, int(stamp_ns), frame_id),
            orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=cov_none,
            angular_velocity=vec(x=float(gyro[0]), y=float(gyro[1]), z=float(gyro[2])),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=vec(x=float(acc[0]), y=float(acc[1]), z=float(acc[2])),
            linear_acceleration_covariance=np.zeros(9),
        )
        self.write(topic, IMU, stamp_ns if record_ns is None else record_ns, msg)

    def pose(self, topic: str, stamp_ns: int, T: NDArray[np.float64], frame_id: str = "world") -> None:
        """``geometry_msgs/PoseStamped`` of a 4x4 transform (child -> ``frame_id``, metres)."""
        t = self.typestore.types
        q = quaternion_xyzw(T[:3, :3])
        p = T[:3, 3]
        pose = t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=float(p[2])),
            orientation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        )
        msg = t[POSE_STAMPED](header=_header(self.typestore, int(stamp_ns), frame_id), pose=pose)
        self.write(topic, POSE_STAMPED, stamp_ns, msg)

    def joints(self, topic: str, stamp_ns: int, q: NDArray[np.float64], names: list[str] | None = None) -> None:
        """``sensor_msgs/JointState`` positions (radians); names ``joint_1..joint_L`` by default."""
        names = names or [f"joint_{k + 1}" for k in range(len(q))]
        self.write(topic, JOINT_STATE, stamp_ns, joint_state_message(self.typestore, q, int(stamp_ns), names))


def _remove(path: Path) -> None:
    if path.is_dir():
        shutil.rmtree(path)
    elif path.exists():
        path.unlink()
