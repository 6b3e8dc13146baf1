"""Load any supported input into a :class:`~dcc_fg.data.CalibrationDataset` (detecting the target in images).

Layouts, recognised by their content (:func:`dcc_fg.io.layout.detect_layout`):

* ``ros1_bag``: a ROS1 ``.bag`` file; ``ros2_bag``: a ROS2 bag folder (``metadata.yaml``,
  ``*.db3`` or ``*.mcap``).  Image topics are the camchain's ``rostopic`` entries (or the
  ``static_topic`` / ``dynamic_topic`` arguments); joints from a ``sensor_msgs/JointState``
  topic.
* ``image_folder``: ``cam0/<timestamp_ns>.png``, ``cam1/<timestamp_ns>.png``, optional
  ``joints.csv``.
* ``detection_folder``: ``cam0/<timestamp_ns>.csv``, ``cam1/<timestamp_ns>.csv`` in yac's
  layout, optional ``joints.csv``; the target comes from the CSV headers.

``cam0`` is the static camera s, ``cam1`` the dynamic (gimbal) camera d.  Snapshot timestamps
are the static frame's, in ns; pixels are in the distorted images; joint angles in radians.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from dcc_fg.data import CalibrationDataset, Observation, Snapshot
from dcc_fg.detection import detect_target
from dcc_fg.io.bags import BagImagePairs, BagTopicImages
from dcc_fg.io.camchain import CamchainEntry, load_camchain
from dcc_fg.io.folders import (
    DYNAMIC_DIR,
    IMAGE_SUFFIXES,
    STATIC_DIR,
    FramePair,
    ImageFolder,
    list_timestamped,
    read_image,
)
from dcc_fg.io.layout import Layout, detect_layout
from dcc_fg.io.pairing import DEFAULT_TOLERANCE_NS, Pairing
from dcc_fg.sources.detections import read_detection_folder
from dcc_fg.sources.parallel_detection import (
    CameraSize,
    Detector,
    ImageReference,
    check_resolution,
    detect_images,
    detect_pairs,
    detect_referenced_pairs,
    pool_jobs,
)
from dcc_fg.sync import CameraStream
from dcc_fg.targets import TargetGeometry, load_target

log = logging.getLogger(__name__)

__all__ = ["Detector", "Layout", "detect_layout", "load_dataset", "load_streams"]


def _common(snap: Snapshot) -> int:
    return int(np.intersect1d(snap.static.ids, snap.dynamic.ids).size)


def _size(entry: CamchainEntry, cam: str) -> CameraSize:
    """The camera's name and its camchain resolution (width, height), px."""
    w, h = entry.camera.resolution
    return cam, (int(w), int(h))


#: Detections of image files by (path, size in bytes, modification time in ns): a file whose key is
#: known is neither read nor detected again (:func:`load_dataset` ``file_cache``).
FileDetections = dict[tuple[str, int, int], Observation]


def _file_key(path: Path) -> tuple[str, int, int]:
    st = path.stat()
    return str(path), int(st.st_size), int(st.st_mtime_ns)


def _detect_folder_cached(
    folder: ImageFolder, sizes: tuple[CameraSize, CameraSize], target: TargetGeometry, detector: Detector,
    cache: FileDetections,
) -> list[Snapshot]:  # fmt: skip
    """Every pair of an image folder, each file read and detected only when ``cache`` does not hold it."""
    snapshots = []
    for ref in folder.references():
        obs = []
        for path, size in ((ref.static, sizes[0]), (ref.dynamic, sizes[1])):
            key = _file_key(path)
            if key not in cache:
                image = read_image(path)
                check_resolution(image, size, str(path))
                cache[key] = detector(image, target)
            obs.append(cache[key])
        snapshots.append(Snapshot(ref.timestamp_ns, obs[0], obs[1], ref.joints))
    return snapshots


def _detect_frames(
    frames: Iterable[FramePair],
    total: int,
    target: TargetGeometry,
    entries: tuple[CamchainEntry, CamchainEntry],
    names: tuple[str, str],
    detector: Detector,
    progress: bool,
    desc: str,
    jobs: int = 1,
    file_cache: FileDetections | None = None,
) -> list[Snapshot]:
    """Detect the target in every pair (read here, detected on ``jobs`` processes), in input order; an
    image folder with ``file_cache``: in this process, each file only once (:data:`FileDetections`)."""
    meta: deque[tuple[int, NDArray[np.float64] | None]] = deque()  # stamp and joints of the pairs in flight
    sizes = (_size(entries[0], names[0]), _size(entries[1], names[1]))
    if file_cache is not None and isinstance(frames, ImageFolder):
        return _detect_folder_cached(frames, sizes, target, detector, file_cache)

    def images() -> Iterator[tuple[NDArray[np.generic], NDArray[np.generic]]]:
        for fr in frames:
            check_resolution(fr.static, sizes[0], fr.static_source)
            check_resolution(fr.dynamic, sizes[1], fr.dynamic_source)
            meta.append((fr.timestamp_ns, fr.joints))
            yield fr.static, fr.dynamic

    def references() -> Iterator[tuple[ImageReference, ImageReference]]:
        if isinstance(frames, BagImagePairs):
            for ref in frames.references():
                meta.append((ref.static.stamp_ns, ref.joints))
                yield ref.static, ref.dynamic
        elif isinstance(frames, ImageFolder):
            for pair in frames.references():
                meta.append((pair.timestamp_ns, pair.joints))
                yield pair.static, pair.dynamic

    snapshots = []
    if isinstance(frames, BagImagePairs | ImageFolder) and pool_jobs(detector, jobs) > 1:  # workers read
        bag = frames.path if isinstance(frames, BagImagePairs) else None
        results = detect_referenced_pairs(bag, references(), sizes, target, detector, jobs)
    else:
        results = detect_pairs(images(), target, detector, jobs)
    for obs_s, obs_d in tqdm(results, total=total, desc=desc, unit="pair", disable=not progress, leave=False):
        stamp, joints = meta.popleft()
        snapshots.append(Snapshot(stamp, obs_s, obs_d, joints))
    return snapshots


def _keep(
    snapshots: list[Snapshot], min_common_points: int, where: tuple[str, str], target: TargetGeometry
) -> list[Snapshot]:
    """Snapshots where both cameras see >= ``min_common_points`` common points; clear errors if none."""
    n_s = sum(1 for s in snapshots if len(s.static) > 0)
    n_d = sum(1 for s in snapshots if len(s.dynamic) > 0)
    kind = f"{target.target_type} {target.cols}x{target.rows}"
    if n_s == 0 and n_d == 0:
        raise ValueError(
            f"target ({kind}) never detected in {len(snapshots)} image pairs of {where[0]} and {where[1]} "
            "(check target.yaml: targetCols/targetRows count inner corners, tagCols/tagRows count tags)"
        )
    for n, w in ((n_s, where[0]), (n_d, where[1])):
        if n == 0:
            raise ValueError(f"{w}: target ({kind}) never detected in {len(snapshots)} images")
    kept = [s for s in snapshots if _common(s) >= min_common_points]
    log.info(
        "%d of %d snapshots kept (both cameras see >= %d common target points; target found in %d static, "
        "%d dynamic images)",
        len(kept),
        len(snapshots),
        min_common_points,
        n_s,
        n_d,
    )
    if not kept:
        best = max((_common(s) for s in snapshots), default=0)
        raise ValueError(
            f"{where[0]} / {where[1]}: no image pair where both cameras see at least {min_common_points} common "
            f"target points (best pair: {best}); the target was found in {n_s} static and {n_d} dynamic images"
        )
    return kept


@dataclass(frozen=True)
class _CameraPair:
    """The static and dynamic cameras' camchain entries and names, and how to name the camchain in errors."""

    entries: tuple[CamchainEntry, CamchainEntry]
    names: tuple[str, str]
    source: str


def _camera_pair(camchain: str | Path | Mapping[str, CamchainEntry], static_cam: str, dynamic_cam: str) -> _CameraPair:
    entries = dict(load_camchain(camchain) if isinstance(camchain, str | Path) else camchain)
    source = str(camchain) if isinstance(camchain, str | Path) else "camchain"
    for cam in (static_cam, dynamic_cam):
        if cam not in entries:
            raise ValueError(f"{source}: no entry '{cam}'")
    return _CameraPair((entries[static_cam], entries[dynamic_cam]), (static_cam, dynamic_cam), source)


def _bag_topics(cams: _CameraPair, static_topic: str | None, dynamic_topic: str | None) -> tuple[str, str]:
    """The image topics of the two cameras: the overrides, else the camchain's ``rostopic``."""
    topics = []
    for entry, cam, override in zip(cams.entries, cams.names, (static_topic, dynamic_topic), strict=True):
        topic = override or entry.rostopic
        if not topic:
            raise ValueError(f"{cams.source}: {cam} has no 'rostopic' field; needed to read a bag")
        topics.append(topic)
    return topics[0], topics[1]


def _image_pairs(
    path: Path,
    layout: Layout,
    cams: _CameraPair,
    topics: tuple[str | None, str | None, str | None],
    tolerance_ns: int,
    joint_names: list[str] | None,
) -> tuple[ImageFolder | BagImagePairs, tuple[str, str]]:
    """The paired images of an image folder or bag, and how to name the two streams in errors.

    ``topics``: static and dynamic image topic overrides and the joint topic (bags only).
    """
    if layout == "image_folder":
        return ImageFolder(path, tolerance_ns), (str(path / STATIC_DIR), str(path / DYNAMIC_DIR))
    static_topic, dynamic_topic = _bag_topics(cams, topics[0], topics[1])
    frames = BagImagePairs(path, static_topic, dynamic_topic, topics[2], tolerance_ns, joint_names)
    return frames, (f"{path}: topic {static_topic}", f"{path}: topic {dynamic_topic}")


def _input_report(
    layout: Layout, pairing: Pairing, snapshots: list[Snapshot], kept: list[Snapshot]
) -> dict[str, object]:
    """Counts for a summary (see :func:`load_dataset`'s ``report``)."""
    return {
        "layout": layout,
        "pairs": len(snapshots),
        "unpaired_static": len(pairing.unpaired_static),
        "unpaired_dynamic": len(pairing.unpaired_dynamic),
        "detected_static": sum(1 for s in snapshots if len(s.static) > 0),
        "detected_dynamic": sum(1 for s in snapshots if len(s.dynamic) > 0),
        "kept": len(kept),
        "rejected": len(snapshots) - len(kept),
        "pairing": pairing.statistics(),
    }


def load_dataset(
    path: str | Path,
    camchain: str | Path | Mapping[str, CamchainEntry],
    target: str | Path | TargetGeometry | None = None,
    *,
    static_cam: str = "cam0",
    dynamic_cam: str = "cam1",
    static_topic: str | None = None,
    dynamic_topic: str | None = None,
    joint_topic: str | None = "auto",
    joint_names: list[str] | None = None,
    tolerance_ns: int = DEFAULT_TOLERANCE_NS,
    min_common_points: int = 8,
    detector: Detector | None = None,
    progress: bool = True,
    report: dict[str, object] | None = None,
    jobs: int = 1,
    file_cache: FileDetections | None = None,
) -> CalibrationDataset:
    """Read a bag, image folder or detection folder into a calibration dataset.

    Args:
        path: bag file / bag folder / image folder / detection folder (see :func:`detect_layout`).
        camchain: Kalibr camchain YAML path or its parsed entries; gives both cameras'
            intrinsics and (for bags) image topics.
        target: Kalibr target YAML path or geometry; optional for detection folders (inferred
            from the CSV headers, and checked against this if given).
        static_cam, dynamic_cam: camchain entries of the static and the dynamic camera.
        static_topic, dynamic_topic: override the camchain's ``rostopic`` (bags only).
        joint_topic: ``sensor_msgs/JointState`` topic (bags); ``"auto"`` uses the bag's only
            JointState topic if there is one; None ignores joints.
        joint_names: joint order for JointState messages (default: as recorded).
        tolerance_ns: timestamp pairing tolerance between the cameras (and joints), ns.
        min_common_points: keep a snapshot only if both cameras see at least this many of the
            same target points.
        detector: ``detector(image, target) -> Observation``; default
            :func:`dcc_fg.detection.detect_target`.
        progress: show a tqdm progress bar over the image pairs (on stderr).
        jobs: processes detecting the target (:mod:`dcc_fg.sources.parallel_detection`; the same
            corners in the same order for any value); 1: this process only.
        file_cache: image folders: detections by file (path, size, modification time), filled and
            used (this process): a file already in it is neither read nor detected again, e.g. when a
            growing folder is read again and again (``calibrate --incremental``).
        report: if given, filled with counts for a summary: ``layout``, ``pairs`` (image pairs
            after timestamp pairing), ``unpaired_static`` / ``unpaired_dynamic`` (frame counts
            without a partner), ``detected_static`` / ``detected_dynamic`` (pairs where the
            target was found), ``kept`` and ``rejected`` (pairs with / without
            ``min_common_points`` common points), and ``pairing``: the timestamp pairing's
            statistics (:meth:`dcc_fg.io.pairing.Pairing.statistics`: number of pairs, median and
            largest stamp gap of the pairs, each camera's median frame period, in ms, unpaired
            frames per camera) for a pairing health check.

    Returns:
        The dataset; ``source`` is ``path``.

    Raises:
        ValueError: naming the file, topic or field at fault: unknown layout, missing camchain
            entry or topic, image that does not decode or has the wrong size, truncated bag,
            timestamps that never pair, target never detected, no snapshot with enough
            common points, detection files that disagree with the target.
    """
    path = Path(path)
    layout = detect_layout(path)
    cams = _camera_pair(camchain, static_cam, dynamic_cam)
    geometry = load_target(target) if isinstance(target, str | Path) else target
    if layout == "detection_folder":
        snapshots, geometry, pairing = read_detection_folder(path, geometry, tolerance_ns)
        where = (str(path / STATIC_DIR), str(path / DYNAMIC_DIR))
    else:
        if geometry is None:
            raise ValueError(f"{path}: a target (Kalibr target.yaml) is needed to detect corners in images")
        frames, where = _image_pairs(
            path, layout, cams, (static_topic, dynamic_topic, joint_topic), tolerance_ns, joint_names
        )
        pairing = frames.pairing
        detector = detector or detect_target
        desc = f"detect {path.name}"
        snapshots = _detect_frames(
            frames, len(frames), geometry, cams.entries, cams.names, detector, progress, desc, jobs, file_cache
        )
    kept = _keep(snapshots, min_common_points, where, geometry)
    if report is not None:
        report.update(_input_report(layout, pairing, snapshots, kept))
    return CalibrationDataset(
        static_camera=cams.entries[0].camera,
        dynamic_camera=cams.entries[1].camera,
        target_points=geometry.points,
        snapshots=kept,
        source=str(path),
    )


@dataclass(frozen=True)
class CameraStreams:
    """Both cameras' frames detected on their own (:func:`load_streams`), with their intrinsics."""

    static: CameraStream
    dynamic: CameraStream
    entries: tuple[CamchainEntry, CamchainEntry]
    target: TargetGeometry


def _stream_frames(path: Path, layout: Layout, cams: _CameraPair, topics: tuple[str | None, str | None]) -> list[Any]:
    """Per camera: a sized iterable of ``(stamp ns, image, where)`` and its name for messages."""
    if layout == "image_folder":
        out = []
        for sub in (STATIC_DIR, DYNAMIC_DIR):
            files = list_timestamped(path / sub, IMAGE_SUFFIXES)
            out.append(([(t, f) for t, f in sorted(files.items())], str(path / sub)))
        return out
    static_topic, dynamic_topic = _bag_topics(cams, topics[0], topics[1])
    return [(BagTopicImages(path, t), f"{path}: topic {t}") for t in (static_topic, dynamic_topic)]


def _stream_images(
    frames: Iterable[Any], from_files: bool, entry: CamchainEntry, name: str, stamps: list[int]
) -> Iterator[NDArray[np.generic]]:
    """The images of one camera's frames (``(stamp, file)`` or ``(stamp, image, where)``), size-checked;
    their stamps are appended to ``stamps`` as they are read."""
    for item in frames:
        if from_files:
            stamp, file = item
            image, source = read_image(file), str(file)
        else:
            stamp, image, source = item
        check_resolution(image, _size(entry, name), source)
        stamps.append(int(stamp))
        yield image


def load_streams(
    path: str | Path,
    camchain: str | Path | Mapping[str, CamchainEntry],
    target: str | Path | TargetGeometry,
    *,
    static_cam: str = "cam0",
    dynamic_cam: str = "cam1",
    static_topic: str | None = None,
    dynamic_topic: str | None = None,
    detector: Detector | None = None,
    progress: bool = True,
    jobs: int = 1,
) -> CameraStreams:
    """Detect the target in every frame of each camera on its own (no pairing): the input of the
    calibration from unsynchronized or continuously moving recordings (:mod:`dcc_fg.sync`).

    Args: as :func:`load_dataset` (image folders and bags; a detection folder is already paired;
    ``jobs`` processes detect each camera's frames).

    Raises:
        ValueError: naming the file or topic at fault (layout, topic, image size, stamps that go
            backwards or repeat, a camera without frames).
    """
    path = Path(path)
    layout = detect_layout(path)
    if layout == "detection_folder":
        raise ValueError(f"{path}: a detection folder holds paired snapshots; --sync interpolate needs the images")
    cams = _camera_pair(camchain, static_cam, dynamic_cam)
    geometry = load_target(target) if isinstance(target, str | Path) else target
    detector = detector or detect_target
    streams = []
    for (frames, where), entry, name in zip(_stream_frames(path, layout, cams, (static_topic, dynamic_topic)),
                                            cams.entries, cams.names, strict=True):  # fmt: skip
        stamps: list[int] = []
        images = _stream_images(frames, layout == "image_folder", entry, name, stamps)
        results = detect_images(images, geometry, detector, jobs)
        observations = list(
            tqdm(results, total=len(frames), desc=f"detect {name}", unit="frame", disable=not progress, leave=False)
        )
        if not stamps:
            raise ValueError(f"{where}: no frames")
        order = np.argsort(np.asarray(stamps, dtype=np.int64), kind="stable")
        if layout != "image_folder" and np.any(np.diff(np.asarray(stamps)) <= 0):
            log.warning("%s: header stamps are not increasing in record order; frames sorted by stamp", where)
        streams.append(CameraStream(np.asarray(stamps, dtype=np.int64)[order], [observations[i] for i in order], where))
    return CameraStreams(streams[0], streams[1], cams.entries, geometry)
