"""Reading ROS1 ``.bag`` files and ROS2 bag folders (sqlite3 or mcap), through :mod:`rosbags`.

Reading streams in two passes.  A first pass collects the header stamps of the image topics (and
whatever else a reader needs, e.g. joint states or IMU samples) and pairs them; a second pass
(:func:`stream_image_groups`) decodes the images as they come and hands over each group (a
static/dynamic pair, or a single image) as soon as all of its images have been read.  Only the
images waiting for their partner are held in memory, never the whole bag.
:class:`BagImagePairs` yields :class:`~dcc_fg.io.folders.FramePair` objects this way,
:class:`BagTopicImages` the images of one topic.

Image messages: ``sensor_msgs/Image`` (``mono8``, ``mono16``, ``8UC1``, ``16UC1``, ``rgb8``,
``bgr8``, ``rgba8``, ``bgra8``) and ``sensor_msgs/CompressedImage`` (anything ``cv2.imdecode``
reads).  Decoded images are (H, W) grey or (H, W, 3|4) BGR(A), uint8 or uint16, like
``cv2.imread``.  Timestamps are the messages' header stamps in ns (the bag's record time if a
stamp is zero).  Joint angles are ``JointState.position`` (radians), in the order of
``joint_names`` if given, else as recorded.

Repeated messages are dropped while reading, the same way on every pass (:class:`DuplicateFilter`):
exact duplicates (same topic, header stamp and bytes) on every topic, and a second, different image
with the stamp of an earlier one on an image topic (the first is kept); one warning per topic gives
the count.  Joint positions must be finite radians (within one turn).

Corrupt or truncated bags raise ``ValueError`` naming the bag; only the exceptions that rosbags
and its storage raise for bad files (:func:`is_bad_bag_error`) are turned into that message, so a
programming error still ends in its own traceback.  Writing: :mod:`dcc_fg.io.bag_writer`.
"""

from __future__ import annotations

import hashlib
import logging
import sqlite3
import struct
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np
from numpy.typing import NDArray
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.interfaces import Connection
from rosbags.rosbag1 import ReaderError as Rosbag1ReaderError
from rosbags.rosbag2 import ReaderError as Rosbag2ReaderError
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_typestore

from dcc_fg.io import validate
from dcc_fg.io.folders import FramePair
from dcc_fg.io.pairing import DEFAULT_TOLERANCE_NS, Pairing, check_pairing, nearest_within, pair_timestamps

log = logging.getLogger(__name__)

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
JOINT_STATE = "sensor_msgs/msg/JointState"
IMAGE_TYPES = (IMAGE, COMPRESSED_IMAGE)
ROS1_MAGIC = b"#ROSBAG V2.0"

try:  # rosbags reads sqlite3 bags through apsw when it is installed
    from apsw import Error as ApswError
except ImportError:  # pragma: no cover
    ApswError = sqlite3.DatabaseError  # type: ignore[misc,assignment]

#: What rosbags (and the storage below it) raise on corrupt or truncated bags: its reader errors,
#: sqlite's and apsw's database errors, and the low-level read errors of a file cut short.
#: Deserialization errors (``SerdeError``) reach us as ``AnyReaderError``.
BAG_ERRORS: tuple[type[BaseException], ...] = (
    ApswError,
    AnyReaderError,
    Rosbag1ReaderError,
    Rosbag2ReaderError,
    SerdeError,
    sqlite3.DatabaseError,
    struct.error,
    EOFError,
    OSError,
)

#: rosbags' own reader code, where an ``assert`` checks the file's structure (e.g. rosbag1's index records).
_ROSBAGS_READERS = ("/rosbags/rosbag1/", "/rosbags/rosbag2/")


def is_bad_bag_error(exc: BaseException) -> bool:
    """True for an exception that rosbags or its storage raises on a corrupt or truncated bag:
    one of :data:`BAG_ERRORS`, or an ``AssertionError`` raised inside rosbags' reader code (its
    structural checks); False for anything else, in particular errors of our own code."""
    if isinstance(exc, BAG_ERRORS):
        return True
    if not isinstance(exc, AssertionError):
        return False
    tb = exc.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    where = Path(tb.tb_frame.f_code.co_filename).as_posix() if tb is not None else ""
    return any(d in where for d in _ROSBAGS_READERS)


_CHANNELS = {"mono8": 1, "8UC1": 1, "mono16": 1, "16UC1": 1, "rgb8": 3, "bgr8": 3, "8UC3": 3, "rgba8": 4, "bgra8": 4}
_DTYPES = {"mono16": np.uint16, "16UC1": np.uint16}


class StampedImage(NamedTuple):
    """A decoded image, where it came from (``<bag>: topic <t> at <ns> ns``) and its header stamp (ns)."""

    image: NDArray[np.generic]
    where: str
    stamp_ns: int


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


def bag_reader(path: Path) -> AnyReader:
    """An unopened AnyReader (a context manager); the Humble typestore decodes bags without message definitions."""
    try:
        return AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
    except BAG_ERRORS as exc:
        raise ValueError(f"{path}: cannot open bag ({exc})") from None


def stamp_ns(msg: Any, fallback_ns: int = 0) -> int:
    """Header stamp of a message in ns; ``fallback_ns`` if the stamp is zero."""
    stamp = msg.header.stamp
    ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
    return ns if ns != 0 else int(fallback_ns)


def raw_stamp_ns(raw: bytes | memoryview, ros2: bool, fallback_ns: int = 0) -> int:
    """Header stamp (ns) of a serialized message that starts with a ``std_msgs/Header`` (Image,
    CompressedImage, JointState, Imu), read from its first bytes without deserializing the rest (an
    image message is mostly pixels); ``fallback_ns`` if the stamp is zero, as :func:`stamp_ns`.

    ROS 2 (CDR): a 4-byte encapsulation header (byte 1: 1 little-, 0 big-endian), then ``int32 sec,
    uint32 nanosec``. ROS 1: ``uint32 seq, uint32 secs, uint32 nsecs``, little-endian.

    Raises:
        ValueError: a message too short to hold a header.
    """
    view = memoryview(raw).cast("B")
    if len(view) < 12:
        raise ValueError(f"message of {len(view)} bytes is too short for a header")
    if ros2:
        order = "little" if view[1] & 1 else "big"
        sec = int.from_bytes(view[4:8], order, signed=True)
        nsec = int.from_bytes(view[8:12], order)
    else:
        sec = int.from_bytes(view[4:8], "little")
        nsec = int.from_bytes(view[8:12], "little")
    ns = sec * 1_000_000_000 + nsec
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
    reader = bag_reader(path)
    try:
        reader.open()
    except (*BAG_ERRORS, AssertionError) as exc:
        if not is_bad_bag_error(exc):
            raise
        raise ValueError(f"{path}: truncated or corrupt bag, cannot open it ({exc})") from None
    try:
        yield reader
    finally:
        reader.close()


#: Byte stride of an image message's fingerprint (:func:`_fingerprint`).
IMAGE_FINGERPRINT_STRIDE = 257


def _fingerprint(raw: bytes | memoryview, image: bool) -> bytes:
    """Digest of a serialized message: every byte for IMU / joint messages; for an image its length and
    every :data:`IMAGE_FINGERPRINT_STRIDE`-th byte (hashing whole images cost more than a second per
    minute of 20 Hz VGA pairs; an image repeating an earlier stamp is dropped either way, the digest
    only tells an exact duplicate from a different image in the counts)."""
    if not image:
        return hashlib.blake2b(raw, digest_size=16).digest()
    view = memoryview(raw).cast("B")
    sample = bytes(view[::IMAGE_FINGERPRINT_STRIDE]) + len(view).to_bytes(8, "little")
    return hashlib.blake2b(sample, digest_size=16).digest()


class DuplicateFilter:
    """Drops repeated messages of a topic, in the same way on every pass over a bag.

    * an **exact duplicate** (same topic, same header stamp, identical serialized bytes: a message
      recorded twice) is dropped: on an image topic if it repeats any of the topic's last
      :attr:`WINDOW` images, on other topics (IMU, joint states) if it repeats the topic's previous
      message (a sample that repeats an older one is a clock going backwards, which the reader
      of that topic judges);
    * a **different image with the stamp of an earlier image** of the same topic is dropped too
      (the first one is kept): two images cannot both be the frame of one instant.

    Attributes:
        exact: per topic, the number of exact duplicates dropped.
        same_stamp: per image topic, the number of different images dropped for a repeated stamp.
        first: per topic, the stamp (ns) of the first message dropped.
    """

    WINDOW = 10_000

    def __init__(self) -> None:
        self._recent: dict[str, OrderedDict[int, bytes]] = {}
        self.exact: dict[str, int] = {}
        self.same_stamp: dict[str, int] = {}
        self.first: dict[str, int] = {}

    def drop(self, topic: str, stamp: int, raw: bytes | memoryview, image: bool) -> bool:
        """True if the message (``raw`` bytes, header ``stamp`` ns) repeats an earlier one of ``topic``."""
        recent = self._recent.setdefault(topic, OrderedDict())
        digest = _fingerprint(raw, image)
        seen = recent.get(stamp)
        if seen is None or not (image or seen == digest):
            if not image:
                recent.clear()  # other topics: compare with the previous message only
            recent[stamp] = digest
            if len(recent) > self.WINDOW:
                recent.popitem(last=False)
            return False
        if seen == digest:
            self.exact[topic] = self.exact.get(topic, 0) + 1
        else:
            self.same_stamp[topic] = self.same_stamp.get(topic, 0) + 1
        self.first.setdefault(topic, stamp)
        return True

    def dropped(self, topic: str) -> int:
        """Messages of ``topic`` dropped so far."""
        return self.exact.get(topic, 0) + self.same_stamp.get(topic, 0)

    def log(self, path: Path) -> None:
        """One warning per topic with dropped messages."""
        for topic in sorted(set(self.exact) | set(self.same_stamp)):
            if self.exact.get(topic):
                log.warning(
                    "%s: topic %s: dropped %d exact duplicate messages (same header stamp and identical bytes as an "
                    "earlier message; first at %d ns)",
                    path, topic, self.exact[topic], self.first[topic],
                )  # fmt: skip
            if self.same_stamp.get(topic):
                log.warning(
                    "%s: topic %s: %d images have the header stamp of an earlier, different image; kept the first of "
                    "each stamp (first at %d ns). Check the camera driver's time stamps",
                    path, topic, self.same_stamp[topic], self.first[topic],
                )  # fmt: skip


def _raw_messages(path: Path, reader: AnyReader, conns: list[Connection]) -> Iterator[tuple[Connection, int, bytes]]:
    """(connection, record time ns, serialized bytes) in bag order; a truncated or corrupt bag ->
    ValueError naming it (other exceptions, e.g. a bug's AssertionError, keep their type)."""
    it = reader.messages(connections=conns)
    while True:
        try:
            item = next(it)
        except StopIteration:
            return
        except (*BAG_ERRORS, AssertionError) as exc:
            if not is_bad_bag_error(exc):
                raise
            raise ValueError(f"{path}: truncated or corrupt bag ({type(exc).__name__}: {exc})") from None
        yield item


def bag_messages(
    path: Path, reader: AnyReader, conns: list[Connection], duplicates: DuplicateFilter | None = None
) -> Iterator[tuple[Connection, int, Any]]:
    """(connection, record time ns, deserialized message); corrupt data -> ValueError naming the bag.

    Repeated messages are dropped by ``duplicates`` (see :class:`DuplicateFilter`; a new filter if
    None, which logs what it dropped when the bag has been read to the end).  Every pass over a
    bag drops the same messages, so message indices of one pass hold in the next.
    """
    dup = DuplicateFilter() if duplicates is None else duplicates
    for conn, t, raw in _raw_messages(path, reader, conns):
        try:
            msg = reader.deserialize(raw, conn.msgtype)
        except BAG_ERRORS as exc:
            raise ValueError(f"{path}: topic {conn.topic}: message at {t} ns does not deserialize ({exc})") from None
        if hasattr(msg, "header") and dup.drop(conn.topic, stamp_ns(msg, t), raw, conn.msgtype in IMAGE_TYPES):
            continue
        yield conn, t, msg
    if duplicates is None:
        dup.log(path)


def bag_image_stamps(
    path: Path, reader: AnyReader, conns: list[Connection], duplicates: DuplicateFilter
) -> Iterator[tuple[Connection, int, int]]:
    """(connection, record time ns, header stamp ns) of the image messages of ``conns``, in bag order,
    read from the messages' first bytes (:func:`raw_stamp_ns`; no image is deserialized); repeated
    messages are dropped by ``duplicates`` exactly as :func:`bag_messages` drops them, so a later
    :func:`bag_messages` pass sees the same messages in the same order."""
    for conn, t, raw in _raw_messages(path, reader, conns):
        try:
            stamp = raw_stamp_ns(raw, reader.is2, t)
        except ValueError as exc:
            raise ValueError(f"{path}: topic {conn.topic}: message at {t} ns does not deserialize ({exc})") from None
        if duplicates.drop(conn.topic, stamp, raw, True):
            continue
        yield conn, t, stamp


def image_topic_connections(reader: AnyReader, path: Path, topic: str, hint: str = "") -> list[Connection]:
    """The connections of image ``topic``; ValueError naming the bag and topic if it is missing
    (listing the image topics, then ``hint``) or holds something other than images."""
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        images = sorted({c.topic for c in reader.connections if c.msgtype in IMAGE_TYPES})
        raise ValueError(
            f"{path}: topic {topic} not found (image topics in the bag: {', '.join(images) or 'none'}{hint})"
        )
    bad = [c.msgtype for c in conns if c.msgtype not in IMAGE_TYPES]
    if bad:
        raise ValueError(f"{path}: topic {topic} has type {bad[0]}, not sensor_msgs/Image or CompressedImage")
    return conns


def stream_image_groups(
    path: Path,
    topics: Sequence[str],
    groups: Sequence[Sequence[int]],
    convert: Callable[[NDArray[np.generic]], NDArray[np.generic]] | None = None,
) -> Iterator[tuple[int, list[StampedImage | None]]]:
    """Second pass of a bag: decode the images of ``groups`` and yield each group once it is complete.

    Args:
        path: the bag.
        topics: image topics (already checked with :func:`image_topic_connections`).
        groups: per group, the index of its message within each topic's message sequence (in the
            order of ``topics``), e.g. the ``(i, j)`` pairs of a :class:`~dcc_fg.io.pairing.Pairing`;
            a negative index means the group has no image of that topic (None in its place).
        convert: applied to each decoded image before it waits for its partner (e.g. to grey).

    Yields:
        ``(group index, images in the order of topics)``, in the order in which the last image of
        each group appears in the bag; messages outside every group are skipped undecoded.
    """
    group_of = [{idx[k]: n for n, idx in enumerate(groups) if idx[k] >= 0} for k in range(len(topics))]
    need = [sum(1 for i in idx if i >= 0) for idx in groups]
    slot = {topic: k for k, topic in enumerate(topics)}
    count = [0] * len(topics)
    pending: dict[int, dict[int, StampedImage]] = {}
    with open_bag(path) as reader:
        conns = [c for c in reader.connections if c.topic in slot]
        # the first pass logged the dropped duplicates; this one drops the same messages silently
        for conn, t, msg in bag_messages(path, reader, conns, DuplicateFilter()):
            k = slot[conn.topic]
            n = group_of[k].get(count[k])
            count[k] += 1
            if n is None:
                continue
            ts = stamp_ns(msg, t)
            where = f"{path}: topic {conn.topic} at {ts} ns"
            img = decode_image(msg, conn.msgtype, where)
            pending.setdefault(n, {})[k] = StampedImage(convert(img) if convert else img, where, ts)
            if len(pending[n]) == need[n]:
                got = pending.pop(n)
                yield n, [got.get(i) for i in range(len(topics))]


def joint_state_topic(reader: AnyReader, path: Path, joint_topic: str | None) -> str | None:
    """The ``JointState`` topic to read: ``joint_topic`` checked, the only one for ``"auto"``, or None."""
    if joint_topic is None:
        return None
    if joint_topic == "auto":
        topics = sorted({c.topic for c in reader.connections if c.msgtype == JOINT_STATE})
        if len(topics) > 1:
            raise ValueError(f"{path}: several JointState topics ({', '.join(topics)}); name one")
        return topics[0] if topics else None
    conns = [c for c in reader.connections if c.topic == joint_topic]
    if not conns:
        raise ValueError(f"{path}: topic {joint_topic} not found")
    if any(c.msgtype != JOINT_STATE for c in conns):
        raise ValueError(f"{path}: topic {joint_topic} is not sensor_msgs/JointState")
    return joint_topic


class MessageReference(NamedTuple):
    """One kept image message of a bag: its ``topic``, record time (ns, the bag's clock) and header stamp
    (ns; the record time when the header stamp is zero). Kept messages of a topic have distinct stamps
    (:class:`DuplicateFilter`), so the first message of ``topic`` at ``record_ns`` with ``stamp_ns`` is it."""

    topic: str
    record_ns: int
    stamp_ns: int

    def where(self, path: Path) -> str:
        """How errors name the message: ``<bag>: topic <topic> at <stamp> ns``."""
        return f"{path}: topic {self.topic} at {self.stamp_ns} ns"


class PairReference(NamedTuple):
    """A synchronized pair's two messages (:meth:`BagImagePairs.references`) and its joint angles (rad)."""

    static: MessageReference
    dynamic: MessageReference
    joints: NDArray[np.float64] | None


def fetch_image(reader: AnyReader, path: Path, ref: MessageReference) -> NDArray[np.generic]:
    """Decode the image message ``ref`` of the opened bag ``path`` by its record time (a time-indexed read:
    only the messages recorded in that nanosecond are looked at).

    Raises:
        ValueError: naming the bag, topic and stamp when the message is not there (a bag changed since it
            was scanned) or does not decode.
    """
    conns = [c for c in reader.connections if c.topic == ref.topic]
    try:
        for conn, t, raw in reader.messages(connections=conns, start=ref.record_ns, stop=ref.record_ns + 1):
            msg = reader.deserialize(raw, conn.msgtype)
            if stamp_ns(msg, t) == ref.stamp_ns:
                return decode_image(msg, conn.msgtype, ref.where(path))
    except BAG_ERRORS as exc:
        raise ValueError(f"{ref.where(path)}: cannot read the message ({type(exc).__name__}: {exc})") from None
    raise ValueError(f"{ref.where(path)}: no such message recorded at {ref.record_ns} ns (has the bag changed?)")


class BagImagePairs:
    """Synchronized image pairs of two topics of a bag, streamed.

    Attributes:
        path: the bag file or folder.
        static_topic, dynamic_topic: image topics of the static and the dynamic camera.
        joint_topic: the ``sensor_msgs/JointState`` topic used, or None.
        pairing: the pairing of the two topics' stamps; its unpaired lists report the frames
            without a partner (also logged).
        joints: ``(stamps_ns, angles)`` of the joint topic, or None.
        duplicates: the repeated messages dropped (see :class:`DuplicateFilter`).
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
        record: dict[str, list[tuple[int, int]]] = {static_topic: [], dynamic_topic: []}  # record time, position
        joint_stamps: list[int] = []
        joint_rows: list[NDArray[np.float64]] = []
        hint = "; set 'rostopic' in the camchain"
        with open_bag(self.path) as reader:
            conns = [c for topic in stamps for c in image_topic_connections(reader, self.path, topic, hint)]
            self.joint_topic = joint_state_topic(reader, self.path, joint_topic)
            self.duplicates = DuplicateFilter()
            # the image stamps from the messages' headers alone (images are not deserialized here)
            for position, (conn, t, stamp) in enumerate(bag_image_stamps(self.path, reader, conns, self.duplicates)):
                stamps[conn.topic].append(stamp)
                record[conn.topic].append((t, position))
            if self.joint_topic is not None:
                joint_conns = [c for c in reader.connections if c.topic == self.joint_topic]
                for _, t, msg in bag_messages(self.path, reader, joint_conns, self.duplicates):
                    joint_stamps.append(stamp_ns(msg, t))
                    joint_rows.append(self._joint_positions(msg, t))
        self.duplicates.log(self.path)
        self._stamps = stamps
        self._record = record
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
            if len({row.shape for row in joint_rows}) != 1:
                counts = sorted({row.shape[0] for row in joint_rows})
                raise ValueError(f"{self.path}: topic {self.joint_topic}: messages have {counts} joint positions")
            angles = np.stack(joint_rows)
            validate.check_joint_angles(angles, f"{self.path}: topic {self.joint_topic} position")
            self.joints = (np.array(joint_stamps, dtype=np.int64), angles)

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

    def __len__(self) -> int:
        return len(self.pairing.pairs)

    def _pair_joints(self) -> list[NDArray[np.float64] | None]:
        """Per pair of :attr:`pairing`, the joint angles nearest to its static stamp (None: none)."""
        if self.joints is None:
            return [None] * len(self.pairing.pairs)
        pair_stamps = [self._stamps[self.static_topic][i] for i, _ in self.pairing.pairs]
        jidx = nearest_within(pair_stamps, self.joints[0], self.tolerance_ns)
        return [self.joints[1][j].copy() if j >= 0 else None for j in jidx]

    def __iter__(self) -> Iterator[FramePair]:
        """Second pass: yield the pairs in the order their second image appears in the bag."""
        joints = self._pair_joints()
        topics = (self.static_topic, self.dynamic_topic)
        for n, (s, d) in stream_image_groups(self.path, topics, self.pairing.pairs):
            assert s is not None and d is not None  # every group is a pair
            yield FramePair(s.stamp_ns, s.image, d.image, joints[n], s.where, d.where, d.stamp_ns)

    def references(self) -> list[PairReference]:
        """Where each pair's two messages are, without decoding them, in the order :meth:`__iter__` yields
        the pairs (that of the bag position of a pair's later message): for readers that fetch the
        images themselves (:func:`fetch_image`, e.g. detection workers)."""
        joints = self._pair_joints()
        refs = []
        for n, (i, j) in enumerate(self.pairing.pairs):
            (t_s, pos_s), (t_d, pos_d) = self._record[self.static_topic][i], self._record[self.dynamic_topic][j]
            static = MessageReference(self.static_topic, t_s, self._stamps[self.static_topic][i])
            dynamic = MessageReference(self.dynamic_topic, t_d, self._stamps[self.dynamic_topic][j])
            refs.append((max(pos_s, pos_d), PairReference(static, dynamic, joints[n])))
        refs.sort(key=lambda r: r[0])
        return [r for _, r in refs]


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
            self._count = sum(c.msgcount for c in image_topic_connections(reader, self.path, topic))

    def __len__(self) -> int:
        return self._count

    def __iter__(self) -> Iterator[tuple[int, NDArray[np.generic], str]]:
        """Yield ``(header stamp ns, image, where)``; one decoded image in memory at a time."""
        with open_bag(self.path) as reader:
            conns = image_topic_connections(reader, self.path, self.topic)
            for conn, t, msg in bag_messages(self.path, reader, conns):
                ts = stamp_ns(msg, t)
                where = f"{self.path}: topic {self.topic} at {ts} ns"
                yield ts, decode_image(msg, conn.msgtype, where), where


IMU_TYPE = "sensor_msgs/msg/Imu"


@dataclass(frozen=True)
class ImuImageStamps:
    """First pass of a VIO bag: the whole IMU topic (in bag order, unvalidated) and the image stamps.

    Attributes:
        imu_t_ns: (N,) header stamps, ns; imu_acc: (N, 3) ``linear_acceleration``, m/s^2;
            imu_gyro: (N, 3) ``angular_velocity``, rad/s.
        image_stamps: per image topic, the header stamps in bag order, ns.
    """

    imu_t_ns: NDArray[np.int64]
    imu_acc: NDArray[np.float64]
    imu_gyro: NDArray[np.float64]
    image_stamps: dict[str, list[int]]


def _typed_connections(reader: AnyReader, path: Path, topic: str, accepted: tuple[str, ...]) -> list[Connection]:
    """The connections of ``topic``; ValueError listing the bag's topics if it is missing or of another type."""
    found = [c for c in reader.connections if c.topic == topic]
    if not found:
        available = sorted({f"{c.topic} ({c.msgtype})" for c in reader.connections})
        raise ValueError(f"{path}: topic {topic} not found; the bag has: {', '.join(available)}")
    for c in found:
        if c.msgtype not in accepted:
            raise ValueError(f"{path}: topic {topic} has type {c.msgtype}, expected {' or '.join(accepted)}")
    return found


def scan_imu_and_image_stamps(path: Path, imu_topic: str, image_topics: Sequence[str]) -> ImuImageStamps:
    """Read the ``sensor_msgs/Imu`` topic and the header stamps of the image topics (one pass).

    Raises:
        ValueError: naming the bag and topic for a missing topic or a wrong message type (listing
            the bag's topics), naming the bag for a truncated or corrupt file.
    """
    t_imu: list[int] = []
    rows: list[tuple[float, ...]] = []
    stamps: dict[str, list[int]] = {topic: [] for topic in image_topics}
    with open_bag(path) as reader:
        conns = _typed_connections(reader, path, imu_topic, (IMU_TYPE,))
        for topic in image_topics:
            conns += _typed_connections(reader, path, topic, IMAGE_TYPES)
        for conn, t, msg in bag_messages(path, reader, conns):
            if conn.topic == imu_topic:
                t_imu.append(stamp_ns(msg, t))
                a, w = msg.linear_acceleration, msg.angular_velocity
                rows.append((a.x, a.y, a.z, w.x, w.y, w.z))
            else:
                stamps[conn.topic].append(stamp_ns(msg, t))
    data = np.array(rows, dtype=float).reshape(-1, 6)
    return ImuImageStamps(np.array(t_imu, dtype=np.int64), data[:, :3], data[:, 3:], stamps)
