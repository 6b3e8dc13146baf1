"""Readers: timestamp pairing, image folders, ROS1/ROS2 bags, yac detection folders, load_dataset.

Bags and folders are written here with synthetic images and read back; real detection files are
read from ``../shared/data`` (relative to the repository root) when present.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from conftest import shared_data as real

import dcc_fg.io.bag_writer as bag_writer
import dcc_fg.io.folders as folders
from dcc_fg.data import Observation
from dcc_fg.io.bag_writer import write_ros1_bag, write_ros2_bag
from dcc_fg.io.bags import (
    BagImagePairs,
    MessageReference,
    decode_image,
    fetch_image,
    open_bag,
    raw_stamp_ns,
    read_bag_pairs,
)
from dcc_fg.io.camchain import CamchainEntry
from dcc_fg.io.folders import FramePair, ImageFolder, read_joints_csv, write_image_folder
from dcc_fg.io.layout import detect_layout
from dcc_fg.io.outputs import read_joint_angles_csv, write_joint_angles_csv
from dcc_fg.io.pairing import check_pairing, nearest_within, pair_timestamps, stamp_jitter_s
from dcc_fg.io.tum import read_tum, write_tum
from dcc_fg.sources.dataset import load_dataset
from dcc_fg.sources.detections import read_detection_csv, read_detection_folder, write_detection_csv
from dcc_fg.targets import TargetGeometry
from factors.camera import CameraModel

T0 = 1_700_000_000_000_000_000  # ns
PERIOD = 50_000_000  # 20 Hz
BOARD = TargetGeometry.checkerboard(9, 6, 0.02)
SIZE = (240, 180)  # width, height


def board_image(shift: int, square: int = 16) -> np.ndarray:
    """A 9x6 inner-corner chessboard (the square before corner 0 black), shifted by ``shift`` px."""
    img = np.full((SIZE[1], SIZE[0]), 255, np.uint8)
    x0, y0 = 30 + shift, 30 + shift // 2
    for i in range(-1, 9):
        for j in range(-1, 6):
            if (i + j) % 2 == 0:
                u, v = x0 + i * square, y0 + j * square
                img[v : v + square, u : u + square] = 0
    return img


def camchain() -> dict[str, CamchainEntry]:
    cam = CameraModel((200.0, 200.0, 120.0, 90.0), "radtan", (0.0, 0.0, 0.0, 0.0), SIZE)
    return {"cam0": CamchainEntry(cam, "/cam0/image_raw"), "cam1": CamchainEntry(cam, "/cam1/image_raw")}


def frames(n: int = 3, joints: bool = True, jitter_ns: int = 1_000_000) -> list[FramePair]:
    out = []
    for k in range(n):
        ts = T0 + k * PERIOD
        q = np.array([0.1 * k, -0.2 * k, 0.05]) if joints else None
        out.append(FramePair(ts, board_image(2 * k), board_image(3 * k + 1), q, dynamic_timestamp_ns=ts + jitter_ns))
    return out


# ---------------------------------------------------------------------------------------------
# Pairing
# ---------------------------------------------------------------------------------------------


def test_pairing_one_to_one_within_tolerance() -> None:
    p = pair_timestamps([0, 100, 200, 300], [5, 98, 260, 500], tolerance_ns=10)
    assert p.pairs == [(0, 0), (1, 1)]
    assert p.unpaired_static == [200, 300]
    assert p.unpaired_dynamic == [260, 500]
    # Two static frames compete for one dynamic frame: the closer one wins, the other is reported.
    p = pair_timestamps([0, 7], [5], tolerance_ns=10)
    assert p.pairs == [(1, 0)] and p.unpaired_static == [0]
    # Unsorted input.
    p = pair_timestamps([300, 0], [1, 299], tolerance_ns=2)
    assert sorted(p.pairs) == [(0, 1), (1, 0)]
    assert p.pairs[0] == (1, 0)  # sorted by static time


def test_nearest_within() -> None:
    idx = nearest_within([0, 50, 100, 1000], [98, 2, 49], tolerance_ns=5)
    assert idx.tolist() == [1, 2, 0, -1]
    assert nearest_within([1], [], 5).tolist() == [-1]


def test_timestamps_that_never_pair_name_both_streams() -> None:
    p = pair_timestamps([0, 100], [1_000_000, 1_000_100], tolerance_ns=10)
    with pytest.raises(ValueError, match=r"never pair.*left cam.*right cam"):
        check_pairing(p, 2, 2, "left cam", "right cam")
    with pytest.raises(ValueError, match="right cam: no frames"):
        check_pairing(pair_timestamps([0], [], 10), 1, 0, "left cam", "right cam")


# ---------------------------------------------------------------------------------------------
# Image folders
# ---------------------------------------------------------------------------------------------


def test_image_folder_round_trip_lazy_and_unpaired(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    src = frames(3)
    src[1] = FramePair(
        src[1].timestamp_ns,
        src[1].static.astype(np.uint16) * 257,
        cv2.cvtColor(src[1].dynamic, cv2.COLOR_GRAY2BGR),
        src[1].joints,
        dynamic_timestamp_ns=src[1].dynamic_timestamp_ns,
    )
    root = write_image_folder(tmp_path / "data", src)
    cv2.imwrite(str(root / "cam0" / f"{T0 + 10 * PERIOD}.png"), src[0].static)  # no partner
    cv2.imwrite(str(root / "cam1" / f"{T0 - PERIOD}.png"), src[0].static)  # no partner
    calls = []
    real_read = folders.read_image
    monkeypatch.setattr(folders, "read_image", lambda p: calls.append(p) or real_read(p))
    data = ImageFolder(root, tolerance_ns=2_000_000)
    assert len(data) == 3 and calls == []  # nothing read yet
    assert data.pairing.unpaired_static == [T0 + 10 * PERIOD]
    assert data.pairing.unpaired_dynamic == [T0 - PERIOD]
    it = iter(data)
    first = next(it)
    assert len(calls) == 2  # one pair read at a time
    got = [first, *it]
    for g, s in zip(got, src, strict=True):
        assert g.timestamp_ns == s.timestamp_ns and g.dynamic_timestamp_ns == s.dynamic_timestamp_ns
        assert g.static.dtype == s.static.dtype and np.array_equal(g.static, s.static)
        assert np.array_equal(g.dynamic, s.dynamic)
        assert g.joints is not None and s.joints is not None and np.allclose(g.joints, s.joints)
        assert g.static_source.endswith(f"{s.timestamp_ns}.png")


def test_image_folder_errors_name_the_file(tmp_path: Path) -> None:
    root = write_image_folder(tmp_path / "data", frames(2, joints=False))
    bad = root / "cam1" / f"{T0 + PERIOD + 1_000_000}.png"
    bad.write_bytes(b"not a png")
    with pytest.raises(ValueError, match=f"{bad.name}: image does not decode"):
        list(ImageFolder(root))
    (root / "cam0" / "frame_a.png").write_bytes(b"")
    with pytest.raises(ValueError, match="frame_a.png: file name must be <timestamp_ns>"):
        ImageFolder(root)
    (root / "cam0" / "frame_a.png").unlink()
    with pytest.raises(ValueError, match=r"never pair.*cam0.*cam1"):
        ImageFolder(root, tolerance_ns=10)  # the cam1 frames are 1 ms late
    shutil.rmtree(root / "cam1")
    with pytest.raises(ValueError, match="cam1: folder missing"):
        ImageFolder(root)


def test_nanosecond_stamps_stay_integers(tmp_path: Path) -> None:
    """EuRoC-epoch stamps (~1.4e18 ns) are not multiples of 256 ns: a float64 would round them."""
    stamps = np.array([1403636580013555456, 1403636580013555457, 1403636580063555583], dtype=np.int64)
    assert int(float(stamps[1])) != int(stamps[1])  # what a float parse would lose
    write_joint_angles_csv(tmp_path / "joint_angles.csv", stamps, np.array([[0.1, -0.2], [0.3, 0.4], [0.5, 0.6]]))
    t, th = read_joint_angles_csv(tmp_path / "joint_angles.csv")
    assert t.dtype == np.int64 and np.array_equal(t, stamps) and th.shape == (3, 2)
    write_tum(tmp_path / "traj.tum", stamps, np.tile(np.eye(4), (3, 1, 1)))
    t_tum, _ = read_tum(tmp_path / "traj.tum")
    assert np.array_equal(t_tum, stamps)
    (tmp_path / "joints.csv").write_text("timestamp_ns,theta_1\n" + "".join(f"{s},0.5\n" for s in stamps))
    t_j, _ = read_joints_csv(tmp_path / "joints.csv")
    assert np.array_equal(t_j, stamps)


def test_joints_csv(tmp_path: Path) -> None:
    path = tmp_path / "joints.csv"
    path.write_text("timestamp_ns,theta_1,theta_2\n10,0.5,-1\n20,0.25,2e-3\n")
    ts, q = read_joints_csv(path)
    assert ts.tolist() == [10, 20] and q.shape == (2, 2) and q[1, 1] == pytest.approx(0.002)
    path.write_text("time,theta_1\n10,0.5\n")
    with pytest.raises(ValueError, match="joints.csv: header"):
        read_joints_csv(path)
    path.write_text("timestamp_ns,theta_1\n10,abc\n")
    with pytest.raises(ValueError, match=r"joints.csv:2: not a number"):
        read_joints_csv(path)


# ---------------------------------------------------------------------------------------------
# Bags
# ---------------------------------------------------------------------------------------------


def _write(kind: str, path: Path, data: list[FramePair], compressed: bool = False) -> Path:
    if kind == "ros1":
        return write_ros1_bag(path.with_suffix(".bag"), data, compressed=compressed)
    return write_ros2_bag(path, data, compressed=compressed, storage="mcap" if kind == "mcap" else "sqlite3")


@pytest.mark.parametrize(("kind", "compressed"), [("ros1", False), ("ros2", False), ("mcap", True), ("ros1", True)])
def test_bag_round_trip(tmp_path: Path, kind: str, compressed: bool) -> None:
    src = frames(3)
    src[0] = FramePair(
        src[0].timestamp_ns,
        src[0].static.astype(np.uint16) * 200,
        src[0].dynamic,
        src[0].joints,
        dynamic_timestamp_ns=src[0].dynamic_timestamp_ns,
    )
    src[2] = FramePair(
        src[2].timestamp_ns,
        src[2].static,
        cv2.cvtColor(src[2].dynamic, cv2.COLOR_GRAY2BGRA),
        src[2].joints,
        dynamic_timestamp_ns=src[2].dynamic_timestamp_ns,
    )
    bag = _write(kind, tmp_path / "rec", src, compressed)
    pairs = read_bag_pairs(bag, "/cam0/image_raw", "/cam1/image_raw", joint_topic="auto", tolerance_ns=2_000_000)
    assert pairs.joint_topic == "/gimbal/joint_states"
    assert len(pairs) == 3 and not pairs.pairing.unpaired_static and not pairs.pairing.unpaired_dynamic
    got = list(pairs)
    for g, s in zip(got, src, strict=True):
        assert g.timestamp_ns == s.timestamp_ns and g.dynamic_timestamp_ns == s.dynamic_timestamp_ns
        for a, b in ((g.static, s.static), (g.dynamic, s.dynamic)):
            assert a.dtype == b.dtype and np.array_equal(a, b)
        assert g.joints is not None and np.allclose(g.joints, s.joints)
        assert "/cam0/image_raw" in g.static_source
    # Where each pair's messages are (for detection workers that read the bag themselves): same order,
    # stamps, joints and, fetched by record time, the same images.
    refs = pairs.references()
    assert [r.static.stamp_ns for r in refs] == [g.timestamp_ns for g in got]
    assert [r.dynamic.stamp_ns for r in refs] == [g.dynamic_timestamp_ns for g in got]
    with open_bag(Path(bag)) as reader:
        for r, g in zip(refs, got, strict=True):
            assert r.joints is not None and g.joints is not None and np.array_equal(r.joints, g.joints)
            assert r.static.where(Path(bag)) == g.static_source and r.dynamic.where(Path(bag)) == g.dynamic_source
            for ref, image in ((r.static, g.static), (r.dynamic, g.dynamic)):
                fetched = fetch_image(reader, Path(bag), ref)
                assert fetched.dtype == image.dtype and np.array_equal(fetched, image)
        gone = MessageReference("/cam0/image_raw", refs[0].static.record_ns + 1, refs[0].static.stamp_ns)
        with pytest.raises(ValueError, match=r"topic /cam0/image_raw at .* no such message recorded"):
            fetch_image(reader, Path(bag), gone)
    # The pairing report lists frames without a partner.
    more = [*src, FramePair(T0 + 50 * PERIOD, src[1].static, src[1].dynamic, dynamic_timestamp_ns=T0 + 60 * PERIOD)]
    bag2 = _write(kind, tmp_path / "rec2", more, compressed)
    pairs = read_bag_pairs(bag2, "/cam0/image_raw", "/cam1/image_raw", tolerance_ns=2_000_000)
    assert len(list(pairs)) == 3 and pairs.joints is None
    assert pairs.pairing.unpaired_static == [T0 + 50 * PERIOD]
    assert pairs.pairing.unpaired_dynamic == [T0 + 60 * PERIOD]


def test_header_stamp_from_the_first_bytes() -> None:
    """ROS 1 and ROS 2 (little- and big-endian CDR) headers; a zero stamp falls back to the record time."""
    sec, nsec = 1_700_000_123, 456_789_012
    ros1 = (7).to_bytes(4, "little") + sec.to_bytes(4, "little") + nsec.to_bytes(4, "little") + b"rest"
    le = b"\x00\x01\x00\x00" + sec.to_bytes(4, "little") + nsec.to_bytes(4, "little") + b"rest"
    be = b"\x00\x00\x00\x00" + sec.to_bytes(4, "big") + nsec.to_bytes(4, "big") + b"rest"
    assert raw_stamp_ns(ros1, ros2=False) == raw_stamp_ns(le, ros2=True) == raw_stamp_ns(be, ros2=True)
    assert raw_stamp_ns(le, ros2=True) == sec * 1_000_000_000 + nsec
    assert raw_stamp_ns(b"\x00\x01\x00\x00" + bytes(8), ros2=True, fallback_ns=5) == 5
    with pytest.raises(ValueError, match="too short"):
        raw_stamp_ns(b"\x00\x01", ros2=True)


def test_decode_image_encodings() -> None:
    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)

    def msg(enc: str, data: np.ndarray, step: int, big: int = 0) -> SimpleNamespace:
        return SimpleNamespace(encoding=enc, height=2, width=3, step=step, is_bigendian=big, data=data.reshape(-1))

    out = decode_image(msg("rgb8", rgb, 9), "sensor_msgs/msg/Image", "here")
    assert np.array_equal(out, rgb[:, :, ::-1])  # BGR like cv2.imread
    rgba = np.dstack([rgb, np.full((2, 3), 7, np.uint8)])
    assert np.array_equal(
        decode_image(msg("rgba8", rgba, 12), "sensor_msgs/msg/Image", "here"), rgba[:, :, [2, 1, 0, 3]]
    )
    mono16 = np.array([[1, 2, 3], [256, 1000, 65535]], np.uint16)
    big = mono16.astype(">u2").view(np.uint8)
    assert np.array_equal(decode_image(msg("mono16", big, 6, big=1), "sensor_msgs/msg/Image", "here"), mono16)
    padded = np.zeros((2, 8), np.uint8)
    padded[:, :3] = [[1, 2, 3], [4, 5, 6]]
    assert decode_image(msg("mono8", padded, 8), "sensor_msgs/msg/Image", "here").tolist() == [[1, 2, 3], [4, 5, 6]]
    with pytest.raises(ValueError, match="here: image encoding 'yuv422'"):
        decode_image(msg("yuv422", rgb, 9), "sensor_msgs/msg/Image", "here")
    with pytest.raises(ValueError, match="here: image does not decode"):
        decode_image(msg("mono8", np.zeros(4, np.uint8), 3), "sensor_msgs/msg/Image", "here")
    bad = SimpleNamespace(format="png", data=np.frombuffer(b"garbage", np.uint8))
    with pytest.raises(ValueError, match=r"here: compressed image \(format 'png'\) does not decode"):
        decode_image(bad, "sensor_msgs/msg/CompressedImage", "here")


def test_bag_missing_topic(tmp_path: Path) -> None:
    bag = write_ros2_bag(tmp_path / "rec", frames(2))
    with pytest.raises(
        ValueError, match=r"rec: topic /left/image not found \(image topics in the bag: /cam0/image_raw"
    ):
        BagImagePairs(bag, "/left/image", "/cam1/image_raw")
    with pytest.raises(
        ValueError, match="topic /gimbal/joint_states has type sensor_msgs/msg/JointState, not sensor_msgs/Image"
    ):
        BagImagePairs(bag, "/gimbal/joint_states", "/cam1/image_raw")
    with pytest.raises(ValueError, match="topic /joints not found"):
        BagImagePairs(bag, "/cam0/image_raw", "/cam1/image_raw", joint_topic="/joints")


def test_bag_undecodable_image_names_topic(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    real_message = bag_writer.image_message

    def broken(typestore, img, stamp, frame_id, compressed=False):  # type: ignore[no-untyped-def]
        msgtype, msg = real_message(typestore, img, stamp, frame_id, compressed)
        if frame_id == "cam1" and stamp > T0 + PERIOD:
            msg.data = np.frombuffer(b"\x89PNG broken", np.uint8)
        return msgtype, msg

    monkeypatch.setattr(bag_writer, "image_message", broken)
    bag = write_ros1_bag(tmp_path / "rec.bag", frames(3), compressed=True)
    monkeypatch.undo()
    pairs = BagImagePairs(bag, "/cam0/image_raw", "/cam1/image_raw", tolerance_ns=2_000_000)
    with pytest.raises(
        ValueError, match=r"rec.bag: topic /cam1/image_raw at \d+ ns: compressed image .* does not decode"
    ):
        list(pairs)


@pytest.mark.parametrize("kind", ["ros1", "ros2", "mcap"])
def test_truncated_bag(tmp_path: Path, kind: str) -> None:
    bag = _write(kind, tmp_path / "rec", frames(3))
    files = [bag] if bag.is_file() else [p for p in bag.iterdir() if p.suffix in (".db3", ".mcap")]
    for f in files:
        data = f.read_bytes()
        f.write_bytes(data[: int(0.7 * len(data))])
    with pytest.raises(ValueError, match=f"{bag.name}: truncated or corrupt bag"):
        list(BagImagePairs(bag, "/cam0/image_raw", "/cam1/image_raw"))


def test_rosbags_structural_assert_is_reported_as_corrupt(tmp_path: Path) -> None:
    """rosbags checks a ROS1 index record's fields with ``assert``: that counts as a corrupt bag."""
    from rosbags.highlevel import AnyReader

    bag = write_ros1_bag(tmp_path / "rec.bag", frames(2))
    data = bytearray(bag.read_bytes())
    k = data.index(b"count=", data.index(b"op=\x04"))  # first index-data record's 'count' field
    data[k + 2] = ord("x")  # 'count' -> 'coxnt': an unknown field name
    bad = tmp_path / "bad.bag"
    bad.write_bytes(bytes(data))
    with pytest.raises(AssertionError), AnyReader([bad]):  # what rosbags itself raises
        pass
    with pytest.raises(ValueError, match="bad.bag: truncated or corrupt bag, cannot open it"):
        BagImagePairs(bad, "/cam0/image_raw", "/cam1/image_raw")


def test_a_bug_is_not_reported_as_a_corrupt_bag(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Only what rosbags raises for bad files becomes "corrupt bag"; a KeyError or an
    AssertionError of a bug keeps its type and traceback."""
    from rosbags.highlevel import AnyReader

    bag = write_ros1_bag(tmp_path / "rec.bag", frames(2))

    def broken_deserialize(self, raw, msgtype):  # type: ignore[no-untyped-def]
        raise KeyError("a bug: no such field")

    monkeypatch.setattr(AnyReader, "deserialize", broken_deserialize)
    with pytest.raises(KeyError, match="a bug"):  # the images are deserialized when the pairs are read
        list(BagImagePairs(bag, "/cam0/image_raw", "/cam1/image_raw"))

    def failed_assert(self):  # type: ignore[no-untyped-def]
        raise AssertionError("a bug: an assumption of ours")

    monkeypatch.setattr(AnyReader, "open", failed_assert)
    with pytest.raises(AssertionError, match="a bug"):
        BagImagePairs(bag, "/cam0/image_raw", "/cam1/image_raw")


def test_bag_timestamps_that_never_pair(tmp_path: Path) -> None:
    bag = write_ros1_bag(tmp_path / "rec.bag", frames(3, jitter_ns=20_000_000))
    with pytest.raises(
        ValueError, match=r"never pair within 5000000 ns: .*rec.bag: topic /cam0/image_raw.*topic /cam1/image_raw"
    ):
        BagImagePairs(bag, "/cam0/image_raw", "/cam1/image_raw")


# ---------------------------------------------------------------------------------------------
# Detection folders (yac)
# ---------------------------------------------------------------------------------------------


def test_detection_folder_real_yac_files() -> None:
    root = real("euroc_aprilgrid/calib/cam_april")
    snaps, target, pairing = read_detection_folder(root)
    assert target == TargetGeometry.aprilgrid(6, 6, 0.088, 0.3)
    assert len(snaps) == 30 and not pairing.unpaired_static and not pairing.unpaired_dynamic
    first = sorted((root / "cam0").glob("*.csv"))[0]
    rows = np.loadtxt(first, delimiter=",", skiprows=1)
    assert snaps[0].timestamp_ns == int(first.stem)
    ids = (4 * rows[:, 10] + rows[:, 11]).astype(int)
    order = np.argsort(ids)
    assert np.array_equal(snaps[0].static.ids, ids[order])
    assert np.allclose(snaps[0].static.pixels, rows[order, 5:7])
    assert all(len(s.static) >= 100 and len(s.dynamic) >= 100 for s in snaps)


def test_detection_folder_round_trip_and_bad_points(tmp_path: Path) -> None:
    target = TargetGeometry.aprilgrid(3, 2, 0.05, 0.25)
    root = tmp_path / "det"
    (root / "cam0").mkdir(parents=True)
    (root / "cam1").mkdir()
    rng = np.random.default_rng(3)
    for k in range(3):
        ts = T0 + k * PERIOD
        ids = np.sort(rng.choice(24, 10, replace=False))
        write_detection_csv(root / "cam0" / f"{ts}.csv", ts, Observation(ids, rng.uniform(0, 500, (10, 2))), target)
        write_detection_csv(
            root / "cam1" / f"{ts + 999}.csv", ts + 999, Observation(ids[:6], rng.uniform(0, 500, (6, 2))), target
        )
    (root / "joints.csv").write_text(
        "timestamp_ns,theta_1\n" + "".join(f"{T0 + k * PERIOD},{0.1 * k}\n" for k in range(3))
    )
    empty = root / "cam0" / f"{T0 + 7 * PERIOD}.csv"
    empty.write_text("#ts,tag_rows,tag_cols,tag_size,tag_spacing,kp_x,kp_y,p_x,p_y,p_z,tag_id,corner_idx\n")
    snaps, got, pairing = read_detection_folder(root)
    assert got == target and len(snaps) == 3 and pairing.unpaired_static == [T0 + 7 * PERIOD]
    assert [len(s.dynamic) for s in snaps] == [6, 6, 6]
    assert snaps[2].joints is not None and snaps[2].joints.tolist() == [pytest.approx(0.2)]
    # A point that disagrees with the target geometry: the error names the file and line.
    bad = root / "cam1" / f"{T0 + 999}.csv"
    lines = bad.read_text().splitlines()
    fields = lines[3].split(",")
    fields[7] = "0.123456"
    lines[3] = ",".join(fields)
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=rf"{bad.name}:4: p_x,p_y,p_z .* disagree with the target geometry"):
        read_detection_folder(root)
    with pytest.raises(ValueError, match=r"cam0/\d+\.csv: target in the file .* differs from the expected"):
        read_detection_csv(root / "cam0" / f"{T0}.csv", TargetGeometry.aprilgrid(6, 6, 0.05, 0.25))


# ---------------------------------------------------------------------------------------------
# load_dataset
# ---------------------------------------------------------------------------------------------


def test_detect_layout(tmp_path: Path) -> None:
    assert detect_layout(write_image_folder(tmp_path / "imgs", frames(1))) == "image_folder"
    assert detect_layout(write_ros1_bag(tmp_path / "a.bag", frames(1))) == "ros1_bag"
    assert detect_layout(write_ros2_bag(tmp_path / "b", frames(1))) == "ros2_bag"
    renamed = tmp_path / "recording.dat"
    (tmp_path / "a.bag").rename(renamed)  # recognised by content, not by name
    assert detect_layout(renamed) == "ros1_bag"
    (tmp_path / "other.txt").write_text("hello")
    with pytest.raises(ValueError, match="other.txt: not a ROS1 bag"):
        detect_layout(tmp_path / "other.txt")
    with pytest.raises(ValueError, match="no cam0/ and cam1/ subfolders"):
        detect_layout(tmp_path)


@pytest.mark.parametrize("layout", ["image_folder", "ros1_bag", "ros2_bag"])
def test_load_dataset_from_images(tmp_path: Path, layout: str) -> None:
    data = frames(3)
    data[1] = FramePair(
        data[1].timestamp_ns,
        data[1].static,
        np.full_like(data[1].dynamic, 200),
        data[1].joints,
        dynamic_timestamp_ns=data[1].dynamic_timestamp_ns,
    )
    if layout == "image_folder":
        path = write_image_folder(tmp_path / "imgs", data)
    elif layout == "ros1_bag":
        path = write_ros1_bag(tmp_path / "rec.bag", data)
    else:
        path = write_ros2_bag(tmp_path / "rec", data, storage="mcap")
    ds = load_dataset(path, camchain(), BOARD, tolerance_ns=2_000_000, progress=False)
    assert ds.source == str(path)
    assert [s.timestamp_ns for s in ds.snapshots] == [T0, T0 + 2 * PERIOD]  # frame 1: dynamic sees no board
    for snap, k in zip(ds.snapshots, (0, 2), strict=True):
        assert np.array_equal(snap.static.ids, np.arange(54)) and len(snap.dynamic) == 54
        assert snap.static.pixels[0] == pytest.approx([30 + 2 * k - 0.5, 30 + k - 0.5], abs=0.3)
        assert snap.joints is not None and snap.joints[0] == pytest.approx(0.1 * k)
    assert ds.target_points.shape == (54, 3)


def test_load_dataset_errors(tmp_path: Path) -> None:
    blank = [
        FramePair(
            f.timestamp_ns,
            np.full_like(f.static, 255),
            np.full_like(f.dynamic, 255),
            dynamic_timestamp_ns=f.dynamic_timestamp_ns,
        )
        for f in frames(2)
    ]
    root = write_image_folder(tmp_path / "blank", blank)
    with pytest.raises(ValueError, match=r"target \(checkerboard 9x6\) never detected in 2 image pairs"):
        load_dataset(root, camchain(), BOARD, tolerance_ns=2_000_000, progress=False)
    bag = write_ros1_bag(tmp_path / "rec.bag", frames(2))
    with pytest.raises(ValueError, match=r"rec.bag: topic /left not found"):
        load_dataset(bag, camchain(), BOARD, static_topic="/left", progress=False)
    chain = camchain()
    chain["cam1"] = CamchainEntry(chain["cam1"].camera, None)
    with pytest.raises(ValueError, match="cam1 has no 'rostopic'"):
        load_dataset(bag, chain, BOARD, progress=False)
    chain = camchain()
    chain["cam0"] = CamchainEntry(CameraModel((200.0, 200.0, 320.0, 240.0), resolution=(640, 480)), "/cam0/image_raw")
    with pytest.raises(
        ValueError,
        match=r"topic /cam0/image_raw at \d+ ns: image is 240x180 but the camchain's cam0 resolution is 640x480",
    ):
        load_dataset(bag, chain, BOARD, tolerance_ns=2_000_000, progress=False)
    with pytest.raises(ValueError, match="no entry 'cam2'"):
        load_dataset(bag, camchain(), BOARD, dynamic_cam="cam2", progress=False)
    with pytest.raises(ValueError, match="at least 60 common target points"):
        load_dataset(bag, camchain(), BOARD, tolerance_ns=2_000_000, min_common_points=60, progress=False)


def test_load_dataset_detection_folder_real() -> None:
    root = real("euroc_aprilgrid/calib/cam_april")
    cam = CameraModel((458.654, 457.296, 367.215, 248.375), "radtan", (-0.28, 0.07, 0.0002, 0.00002), (752, 480))
    chain = {"cam0": CamchainEntry(cam), "cam1": CamchainEntry(cam)}
    ds = load_dataset(root, chain, progress=False)
    assert len(ds.snapshots) == 30 and ds.target_points.shape == (144, 3)
    with pytest.raises(ValueError, match="differs from the expected"):
        load_dataset(root, chain, TargetGeometry.aprilgrid(6, 6, 0.05, 0.3), progress=False)


def test_stamp_jitter_from_regular_skipped_and_drifting_streams() -> None:
    """1-sigma of header stamps around their grid: 0 for exact 30 Hz stamps; the drawn jitter for a
    jittered stream, also when only every static frame's nearest image is kept (30 Hz paired with
    20 Hz: intervals of one and two periods) and when the camera clock runs 100 ppm fast."""
    rng = np.random.default_rng(3)
    k = np.arange(600)
    exact = np.round(k * 1e9 / 30.0).astype(np.int64)
    assert stamp_jitter_s(exact) < 1e-9
    for sigma in (1e-4, 5e-4):
        jittered = exact + np.round(rng.normal(0, sigma * 1e9, k.size)).astype(np.int64)
        assert stamp_jitter_s(jittered) == pytest.approx(sigma, rel=0.15)
        paired = jittered[np.unique(np.round(np.arange(400) * 1.5).astype(int))]  # every 20 Hz frame's nearest
        assert stamp_jitter_s(paired) == pytest.approx(sigma, rel=0.2)
        drift = (jittered * (1 + 1e-4)).astype(np.int64)
        assert stamp_jitter_s(drift) == pytest.approx(sigma, rel=0.15)
    assert stamp_jitter_s([0, 1, 2]) == 0.0
