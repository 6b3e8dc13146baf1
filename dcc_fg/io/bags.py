"""ROS1 ``.bag`` files and ROS2 bag folders (sqlite3 or mcap), through :mod:`rosbags`.

Reading streams: :class:`BagImagePairs` makes one pass over the bag to collect the header stamps
of the two image topics (and the optional ``sensor_msgs/JointState`` topic) and pair them, then
each iteration makes a second pass that decodes images as they come and yields a
:class:`~dcc_fg.io.folders.FramePair` as soon as both images of a pair have been read.  Only the
images waiting for their partner are held in memory, never the whole bag.

Image messages: ``sensor_msgs/Image`` (``mono8``, ``mono16``, ``8UC1``, ``16UC1``, ``rgb8``,
``bgr8``, ``rgba8``, ``bgra8``) and ``sensor_msgs/CompressedImage`` (anything ``cv2.imdecode``
reads).  Decoded images are (H, W) grey or (H, W, 3|4) BGR(A), uint8 or uint16, like
``cv2.imread``.  Timestamps are the messages' header stamps in ns (the bag's record time if a
stamp is zero).  Joint angles are ``JointState.position`` (radians), in the order of
``joint_names`` if given, else as recorded.

Writers (:func:`write_ros1_bag`, :func:`write_ros2_bag`) put image pairs and joint states into
new bags, for tests and simulators.
"""

from __future__ import annotations

import logging
import sqlite3
import struct
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.interfaces import Connection
from rosbags.rosbag1 import ReaderError as Rosbag1ReaderError
from rosbags.rosbag1 import Writer as Rosbag1Writer
from rosbags.rosbag2 import ReaderError as Rosbag2ReaderError
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Rosbag2Writer
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from dcc_fg.io.folders import FramePair
from dcc_fg.io.pairing import DEFAULT_TOLERANCE_NS, Pairing, check_pairing, nearest_within, pair_timestamps

log = logging.getLogger(__name__)

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
JOINT_STATE = "sensor_msgs/msg/JointState"
ROS1_MAGIC = b"#ROSBAG V2.0"

try:  # rosbags reads sqlite3 bags through apsw when it is installed
    from apsw import Error as _ApswError
except ImportError:  # pragma: no cover
    _ApswError = sqlite3.DatabaseError  # type: ignore[misc,assignment]

#: Errors rosbags (and the storage below it) raise on corrupt or truncated bags.
_BAG_ERRORS = (
    _ApswError,
    AnyReaderError,
    Rosbag1ReaderError,
    Rosbag2ReaderError,
    sqlite3.DatabaseError,
    struct.error,
    EOFError,
    OSError,
    KeyError,
    IndexError,
    AssertionError,
)

_CHANNELS = {"mono8": 1, "8UC1": 1, "mono16": 1, "16UC1": 1, "rgb8": 3, "bgr8": 3, "8UC3": 3, "rgba8": 4, "bgra8": 4}
_DTYPES = {"mono16": np.uint16, "16UC1": np.uint16}


def is_bag(path: str | Path) -> bool:
    """True for a ROS1 bag file (``.bag`` or ROS1 magic) or a ROS2 bag folder.

    A ROS2 bag folder has a ``metadata.yaml`` or ``*.db3`` / ``*.mcap`` storage files.
    """
    path = Path(path)
    if path.is_file():
        if path.suffix == ".bag":
            return True
        with path.open("rb") as f:
            return f.read(len(ROS1_MAGIC)) == ROS1_MAGIC
    if path.is_dir():
        return (path / "metadata.yaml").is_file() or any(path.glob("*.db3")) or any(path.glob("*.mcap"))
    return False


def _reader(path: Path) -> AnyReader:
    """An unopened AnyReader; the Humble typestore decodes bags without message definitions."""
    try:
        return AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
    except _BAG_ERRORS as exc:
        raise ValueError(f"{path}: cannot open bag ({exc})") from None


def stamp_ns(msg: Any, fallback_ns: int = 0) -> int:
    """Header stamp of a message in ns; ``fallback_ns`` if the stamp is zero."""
    stamp = msg.header.stamp
    ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
    return ns if ns != 0 else int(fallback_ns)


def decode_image(msg: Any, msgtype: str, where: str) -> NDArray[np.generic]:
    """Decode a deserialized ``sensor_msgs/Image`` or ``CompressedImage`` to a numpy image.

    Args:
        msg: the deserialized message.
        msgtype: its rosbags type name (``sensor_msgs/msg/Image`` ...).
        where: bag, topic and stamp for error messages.

    Returns:
        (H, W) or (H, W, 3|4) BGR(A) image, uint8 or uint16.

    Raises:
        ValueError: naming ``where`` for an unsupported encoding or data that does not decode.
    """
    data = np.asarray(msg.data, dtype=np.uint8)
    if msgtype == COMPRESSED_IMAGE:
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
        if img is None:
            raise ValueError(f"{where}: compressed image (format '{msg.format}') does not decode")
        return img
    if msgtype != IMAGE:
        raise ValueError(f"{where}: message type {msgtype} is not an image")
    enc = str(msg.encoding)
    if enc not in _CHANNELS:
        raise ValueError(f"{where}: image encoding '{enc}' is not supported ({', '.join(_CHANNELS)})")
    channels = _CHANNELS[enc]
    dtype = np.dtype(_DTYPES.get(enc, np.uint8))
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = w * channels * dtype.itemsize
    if h == 0 or w == 0 or step < row_bytes or data.size < step * h:
        raise ValueError(f"{where}: image does not decode ({enc} {w}x{h}, step {step}, {data.size} bytes of data)")
    rows = data[: step * h].reshape(h, step)[:, :row_bytes]
    img = np.ascontiguousarray(rows).view(dtype.newbyteorder(">" if msg.is_bigendian else "<"))
    img = img.astype(dtype.newbyteorder("="), copy=False).reshape(h, w, channels)
    if enc == "rgb8":
        return cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    if enc == "rgba8":
        return cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA)
    return img[:, :, 0] if channels == 1 else img


@contextmanager
def open_bag(path: Path) -> Iterator[AnyReader]:
    """An opened AnyReader; a truncated or corrupt bag -> ValueError naming it."""
    reader = _reader(path)
    try:
        reader.open()
    except _BAG_ERRORS as exc:
        raise ValueError(f"{path}: truncated or corrupt bag, cannot open it ({exc})") from None
    try:
        yield reader
    finally:
        reader.close()


def bag_messages(path: Path, reader: AnyReader, conns: list[Connection]) -> Iterator[tuple[Connection, int, Any]]:
    """(connection, record time ns, deserialized message); corrupt data -> ValueError naming the bag."""
    it = reader.messages(connections=conns)
    while True:
        try:
            item = next(it)
        except StopIteration:
            return
        except _BAG_ERRORS as exc:
            raise ValueError(f"{path}: truncated or corrupt bag ({type(exc).__name__}: {exc})") from None
        conn, t, raw = item
        try:
            msg = reader.deserialize(raw, conn.msgtype)
        except _BAG_ERRORS as exc:
            raise ValueError(f"{path}: topic {conn.topic}: message at {t} ns does not deserialize ({exc})") from None
        yield conn, t, msg


class BagImagePairs:
    """Synchronized image pairs of two topics of a bag, streamed.

    Attributes:
        path: the bag file or folder.
        static_topic, dynamic_topic: image topics of the static and the dynamic camera.
        joint_topic: the ``sensor_msgs/JointState`` topic used, or None.
        pairing: the pairing of the two topics' stamps; its unpaired lists report the frames
            without a partner (also logged).
        joints: ``(stamps_ns, angles)`` of the joint topic, or None.
    """

    def __init__(
        self,
        path: str | Path,
        static_topic: str,
        dynamic_topic: str,
        joint_topic: str | None = None,
        tolerance_ns: int = DEFAULT_TOLERANCE_NS,
        joint_names: Sequence[str] | None = None,
    ) -> None:
        """Scan the bag's stamps (first pass) and pair them.

        Args:
            path: ROS1 ``.bag`` file or ROS2 bag folder.
            static_topic, dynamic_topic: image topics (``Image`` or ``CompressedImage``).
            joint_topic: ``JointState`` topic; ``"auto"`` takes the only JointState topic if
                there is exactly one; None reads no joints.
            tolerance_ns: pairing tolerance, ns.
            joint_names: order of the joints in the output (default: as recorded).

        Raises:
            ValueError: naming the bag and topic for a missing topic or wrong message type,
                naming the bag for a truncated or corrupt file, and naming both topics if
                no stamps pair.
        """
        self.path = Path(path)
        self.static_topic = static_topic
        self.dynamic_topic = dynamic_topic
        self.tolerance_ns = tolerance_ns
        self.joint_names = list(joint_names) if joint_names is not None else None
        stamps: dict[str, list[int]] = {static_topic: [], dynamic_topic: []}
        joint_stamps: list[int] = []
        joint_rows: list[NDArray[np.float64]] = []
        with self._open() as reader:
            conns = self._image_connections(reader)
            self.joint_topic = self._joint_topic(reader, joint_topic)
            if self.joint_topic is not None:
                conns += [c for c in reader.connections if c.topic == self.joint_topic]
            for conn, t, msg in self._messages(reader, conns):
                if conn.topic == self.joint_topic:
                    joint_stamps.append(stamp_ns(msg, t))
                    joint_rows.append(self._joint_positions(msg, t))
                else:
                    stamps[conn.topic].append(stamp_ns(msg, t))
        self._stamps = stamps
        self.pairing: Pairing = pair_timestamps(stamps[static_topic], stamps[dynamic_topic], tolerance_ns)
        check_pairing(
            self.pairing,
            len(stamps[static_topic]),
            len(stamps[dynamic_topic]),
            f"{self.path}: topic {static_topic}",
            f"{self.path}: topic {dynamic_topic}",
        )
        self.joints: tuple[NDArray[np.int64], NDArray[np.float64]] | None = None
        if self.joint_topic is not None:
            if not joint_rows:
                raise ValueError(f"{self.path}: topic {self.joint_topic} has no messages")
            self.joints = (np.array(joint_stamps, dtype=np.int64), np.stack(joint_rows))

    # -- helpers -------------------------------------------------------------------------------

    @contextmanager
    def _open(self) -> Iterator[AnyReader]:
        with open_bag(self.path) as reader:
            yield reader

    def _messages(self, reader: AnyReader, conns: list[Connection]) -> Iterator[tuple[Connection, int, Any]]:
        """(connection, record time ns, deserialized message); corrupt data -> ValueError naming the bag."""
        return bag_messages(self.path, reader, conns)

    def _image_connections(self, reader: AnyReader) -> list[Connection]:
        out = []
        for topic in (self.static_topic, self.dynamic_topic):
            conns = [c for c in reader.connections if c.topic == topic]
            if not conns:
                images = sorted({c.topic for c in reader.connections if c.msgtype in (IMAGE, COMPRESSED_IMAGE)})
                raise ValueError(
                    f"{self.path}: topic {topic} not found (image topics in the bag: {', '.join(images) or 'none'}; "
                    "set 'rostopic' in the camchain)"
                )
            bad = [c.msgtype for c in conns if c.msgtype not in (IMAGE, COMPRESSED_IMAGE)]
            if bad:
                raise ValueError(
                    f"{self.path}: topic {topic} has type {bad[0]}, not sensor_msgs/Image or CompressedImage"
                )
            out += conns
        return out

    def _joint_topic(self, reader: AnyReader, joint_topic: str | None) -> str | None:
        if joint_topic is None:
            return None
        if joint_topic == "auto":
            topics = sorted({c.topic for c in reader.connections if c.msgtype == JOINT_STATE})
            if len(topics) > 1:
                raise ValueError(f"{self.path}: several JointState topics ({', '.join(topics)}); name one")
            return topics[0] if topics else None
        conns = [c for c in reader.connections if c.topic == joint_topic]
        if not conns:
            raise ValueError(f"{self.path}: topic {joint_topic} not found")
        if any(c.msgtype != JOINT_STATE for c in conns):
            raise ValueError(f"{self.path}: topic {joint_topic} is not sensor_msgs/JointState")
        return joint_topic

    def _joint_positions(self, msg: Any, t: int) -> NDArray[np.float64]:
        pos = np.asarray(msg.position, dtype=np.float64)
        if self.joint_names is None:
            return pos
        names = list(msg.name)
        try:
            return pos[[names.index(n) for n in self.joint_names]]
        except ValueError:
            raise ValueError(
                f"{self.path}: topic {self.joint_topic} at {t} ns has joints {names}, not all of {self.joint_names}"
            ) from None

    # -- streaming -------------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self.pairing.pairs)

    def __iter__(self) -> Iterator[FramePair]:
        """Second pass: yield the pairs in the order their second image appears in the bag."""
        pair_of = {
            self.static_topic: {i: n for n, (i, _) in enumerate(self.pairing.pairs)},
            self.dynamic_topic: {j: n for n, (_, j) in enumerate(self.pairing.pairs)},
        }
        pair_stamps = [self._stamps[self.static_topic][i] for i, _ in self.pairing.pairs]
        jidx = nearest_within(pair_stamps, self.joints[0], self.tolerance_ns) if self.joints is not None else None
        pending: dict[int, dict[str, tuple[NDArray[np.generic], str, int]]] = {}
        count = {self.static_topic: 0, self.dynamic_topic: 0}
        with self._open() as reader:
            conns = self._image_connections(reader)
            for conn, t, msg in self._messages(reader, conns):
                k = count[conn.topic]
                count[conn.topic] += 1
                n = pair_of[conn.topic].get(k)
                if n is None:
                    continue
                ts = stamp_ns(msg, t)
                where = f"{self.path}: topic {conn.topic} at {ts} ns"
                pending.setdefault(n, {})[conn.topic] = (decode_image(msg, conn.msgtype, where), where, ts)
                if len(pending[n]) == 2:
                    got = pending.pop(n)
                    (s_img, s_where, s_ts), (d_img, d_where, d_ts) = got[self.static_topic], got[self.dynamic_topic]
                    joints = None
                    if self.joints is not None and jidx is not None and jidx[n] >= 0:
                        joints = self.joints[1][jidx[n]].copy()
                    yield FramePair(s_ts, s_img, d_img, joints, s_where, d_where, d_ts)


def read_bag_pairs(
    path: str | Path,
    static_topic: str,
    dynamic_topic: str,
    joint_topic: str | None = None,
    tolerance_ns: int = DEFAULT_TOLERANCE_NS,
    joint_names: Sequence[str] | None = None,
) -> BagImagePairs:
    """Open a bag and pair its two image topics (see :class:`BagImagePairs`)."""
    return BagImagePairs(path, static_topic, dynamic_topic, joint_topic, tolerance_ns, joint_names)


class BagTopicImages:
    """The images of one topic of a bag, streamed in record order (one camera's intrinsics).

    Attributes:
        path: the bag file or folder; topic: the image topic.
    """

    def __init__(self, path: str | Path, topic: str) -> None:
        """Check that ``topic`` exists and holds images (ValueError naming the bag and topic)."""
        self.path = Path(path)
        self.topic = topic
        with open_bag(self.path) as reader:
            self._count = sum(c.msgcount for c in self._connections(reader))

    def _connections(self, reader: AnyReader) -> list[Connection]:
        conns = [c for c in reader.connections if c.topic == self.topic]
        if not conns:
            images = sorted({c.topic for c in reader.connections if c.msgtype in (IMAGE, COMPRESSED_IMAGE)})
            raise ValueError(f"{self.path}: topic {self.topic} not found (image topics: {', '.join(images) or 'none'})")
        bad = [c.msgtype for c in conns if c.msgtype not in (IMAGE, COMPRESSED_IMAGE)]
        if bad:
            raise ValueError(f"{self.path}: topic {self.topic} has type {bad[0]}, not sensor_msgs/Image")
        return conns

    def __len__(self) -> int:
        return self._count

    def __iter__(self) -> Iterator[tuple[int, NDArray[np.generic], str]]:
        """Yield ``(header stamp ns, image, where)``; one decoded image in memory at a time."""
        with open_bag(self.path) as reader:
            for conn, t, msg in bag_messages(self.path, reader, self._connections(reader)):
                ts = stamp_ns(msg, t)
                where = f"{self.path}: topic {self.topic} at {ts} ns"
                yield ts, decode_image(msg, conn.msgtype, where), where


# ---------------------------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------------------------


def _header(typestore: Typestore, stamp: int, frame_id: str) -> Any:
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
    header = _header(typestore, stamp, frame_id)
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
        header=_header(typestore, stamp, ""),
        name=list(names),
        position=np.asarray(q, dtype=np.float64),
        velocity=np.zeros(0),
        effort=np.zeros(0),
    )


def _write(
    path: Path,
    frames: Iterable[FramePair],
    ros: Literal[1, 2],
    storage: Literal["sqlite3", "mcap"],
    static_topic: str,
    dynamic_topic: str,
    joint_topic: str,
    compressed: bool,
) -> Path:
    typestore = get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)
    writer: Rosbag1Writer | Rosbag2Writer
    if ros == 1:
        writer = Rosbag1Writer(path)
    else:
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        writer = Rosbag2Writer(path, version=Rosbag2Writer.VERSION_LATEST, storage_plugin=plugin)

    def serialize(msg: Any, msgtype: str) -> bytes | memoryview:
        return typestore.serialize_ros1(msg, msgtype) if ros == 1 else typestore.serialize_cdr(msg, msgtype)

    conns: dict[str, Any] = {}
    with writer:

        def conn(topic: str, msgtype: str) -> Any:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=typestore)
            return conns[topic]

        for fr in frames:
            td = fr.dynamic_timestamp_ns or fr.timestamp_ns
            for topic, img, stamp, frame in (
                (static_topic, fr.static, fr.timestamp_ns, "cam0"),
                (dynamic_topic, fr.dynamic, td, "cam1"),
            ):
                msgtype, msg = image_message(typestore, img, stamp, frame, compressed)
                writer.write(conn(topic, msgtype), stamp, serialize(msg, msgtype))
            if fr.joints is not None:
                names = [f"joint_{k + 1}" for k in range(len(fr.joints))]
                msg = joint_state_message(typestore, fr.joints, fr.timestamp_ns, names)
                writer.write(conn(joint_topic, JOINT_STATE), fr.timestamp_ns, serialize(msg, JOINT_STATE))
    return path


def write_ros1_bag(
    path: str | Path,
    frames: Iterable[FramePair],
    static_topic: str = "/cam0/image_raw",
    dynamic_topic: str = "/cam1/image_raw",
    joint_topic: str = "/gimbal/joint_states",
    compressed: bool = False,
) -> Path:
    """Write frames to a new ROS1 bag file (``rosbags.rosbag1.Writer``, ROS1 Noetic types).

    Each frame gives one image message per camera topic (record time = header stamp: the
    frame's ``timestamp_ns`` for the static image, ``dynamic_timestamp_ns`` or ``timestamp_ns``
    for the dynamic one) and, if it has joints, a ``JointState`` (names ``joint_1..joint_L``) at
    the static stamp.  ``compressed`` writes PNG ``CompressedImage`` messages.
    """
    return _write(Path(path), frames, 1, "sqlite3", static_topic, dynamic_topic, joint_topic, compressed)


def write_ros2_bag(
    path: str | Path,
    frames: Iterable[FramePair],
    static_topic: str = "/cam0/image_raw",
    dynamic_topic: str = "/cam1/image_raw",
    joint_topic: str = "/gimbal/joint_states",
    compressed: bool = False,
    storage: Literal["sqlite3", "mcap"] = "sqlite3",
) -> Path:
    """Write frames to a new ROS2 bag folder (``rosbags.rosbag2.Writer``, Humble types).

    Same messages as :func:`write_ros1_bag`; ``storage`` selects the sqlite3 or mcap plugin.
    """
    return _write(Path(path), frames, 2, storage, static_topic, dynamic_topic, joint_topic, compressed)
