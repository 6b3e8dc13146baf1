"""The camera images behind a calibration's snapshots, read again from the data for display.

A :class:`~dcc_fg.data.CalibrationDataset` keeps only the detected corners. For the interactive view
(:mod:`dcc_fg.viz.rerun_log`) the images are looked up again by stamp: for each snapshot and camera, the
frame whose stamp (integer ns, the camera's own clock) is nearest to the wanted stamp within a tolerance.
Image folders (``cam0/<ns>.png``, ``cam1/<ns>.png``) read only the files needed; bags decode only the
messages needed (the camchain's ``rostopic`` of ``cam0`` and ``cam1``). Detection folders hold no
images, so nothing is found there and the view shows the corners alone.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from dcc_fg.io.bags import bag_messages, decode_image, image_topic_connections, open_bag, stamp_ns
from dcc_fg.io.camchain import CamchainEntry, load_camchain
from dcc_fg.io.folders import DYNAMIC_DIR, IMAGE_SUFFIXES, STATIC_DIR, list_timestamped, read_image
from dcc_fg.io.layout import detect_layout
from dcc_fg.io.pairing import nearest_within

log = logging.getLogger(__name__)

Image = NDArray[np.generic]
#: Camera names of the calibration data: ``cam0`` static, ``cam1`` gimbal.
CAMERAS = (STATIC_DIR, DYNAMIC_DIR)


@dataclass(frozen=True)
class ImageRequest:
    """Which images to find: per camera (``cam0``, ``cam1``) the wanted stamps (ns) and the largest
    stamp difference accepted (ns)."""

    stamps_ns: Mapping[str, NDArray[np.int64]]
    tolerance_ns: Mapping[str, int]


@dataclass(frozen=True)
class ImageSource:
    """Where a calibration's images are and how its snapshot stamps relate to them.

    ``data``: the calibration data (bag, image folder, detection folder); ``camchain``: its camchain
    (path or entries; a bag's image topics come from ``rostopic``); ``tolerance_ns``: largest stamp
    difference of a shown image, per camera (``cam0``, ``cam1``); ``dynamic_shift_ns``: added to a
    snapshot stamp (static clock) to get the gimbal frame's own stamp (``-(t_d - t_s)`` with
    ``--sync interpolate``, else 0)."""

    data: str | Path
    camchain: str | Path | Mapping[str, CamchainEntry] | None
    tolerance_ns: Mapping[str, int]
    dynamic_shift_ns: int = 0

    def request(self, stamps_ns: NDArray[np.int64]) -> ImageRequest:
        """The images of snapshots stamped ``stamps_ns`` (static clock, ns)."""
        t = np.asarray(stamps_ns, dtype=np.int64)
        return ImageRequest({STATIC_DIR: t, DYNAMIC_DIR: t + int(self.dynamic_shift_ns)}, self.tolerance_ns)


def _folder_images(root: Path, request: ImageRequest) -> dict[str, list[Image | None]]:
    """Per camera, the image of each wanted stamp (None: none near it) from an image folder; only the
    files needed are read."""
    out: dict[str, list[Image | None]] = {}
    for cam in CAMERAS:
        files = list_timestamped(root / cam, IMAGE_SUFFIXES)
        stamps = np.array(sorted(files), dtype=np.int64)
        idx = nearest_within(request.stamps_ns[cam], stamps, request.tolerance_ns[cam])
        out[cam] = [read_image(files[int(stamps[i])]) if i >= 0 else None for i in idx]
    return out


def _topics(camchain: str | Path | Mapping[str, CamchainEntry] | None) -> dict[str, str]:
    """The image topic of each camera from the camchain's ``rostopic`` (cameras without one left out)."""
    if camchain is None:
        return {}
    entries = load_camchain(camchain) if isinstance(camchain, str | Path) else camchain
    return {cam: entries[cam].rostopic for cam in CAMERAS if cam in entries and entries[cam].rostopic}  # type: ignore[misc]


def topic_images(path: Path, topic: str, wanted_ns: NDArray[np.int64], tolerance_ns: int) -> list[Image | None]:
    """The image of each wanted stamp (ns, the camera's clock) on one image ``topic`` of the bag
    ``path``: the frame whose stamp is nearest, None where none lies within ``tolerance_ns``. One pass
    over the topic; a message is decoded only when it is the nearest so far to a wanted stamp."""
    wanted = np.asarray(wanted_ns, dtype=np.int64)
    order = np.argsort(wanted, kind="stable")
    sorted_wanted = wanted[order]
    out: list[Image | None] = [None] * len(wanted)
    best = np.full(len(wanted), tolerance_ns + 1, dtype=np.int64)  # stamp distance of the image held
    if not len(wanted):
        return out
    with open_bag(path) as reader:
        conns = image_topic_connections(reader, path, topic)
        for conn, t, msg in bag_messages(path, reader, conns):
            stamp = stamp_ns(msg, t)
            lo = int(np.searchsorted(sorted_wanted, stamp - tolerance_ns, side="left"))
            hi = int(np.searchsorted(sorted_wanted, stamp + tolerance_ns, side="right"))
            targets = [int(k) for k in order[lo:hi] if abs(int(wanted[k]) - stamp) < best[k]]
            if not targets:
                continue
            image = decode_image(msg, conn.msgtype, f"{path}: topic {topic} at {stamp} ns")
            for k in targets:
                out[k], best[k] = image, abs(int(wanted[k]) - stamp)
    return out


def _bag_images(path: Path, topics: dict[str, str], request: ImageRequest) -> dict[str, list[Image | None]]:
    """Per camera, the image of each wanted stamp (None: none near it) from a bag (:func:`topic_images`)."""
    out: dict[str, list[Image | None]] = {cam: [None] * len(request.stamps_ns[cam]) for cam in CAMERAS}
    for cam, topic in topics.items():
        out[cam] = topic_images(path, topic, request.stamps_ns[cam], request.tolerance_ns[cam])
    return out


def calibration_images(source: ImageSource, stamps_ns: NDArray[np.int64]) -> dict[str, list[Image | None]]:
    """The images of ``source`` nearest to the snapshots stamped ``stamps_ns`` (static clock, ns), as
    ``{'cam0': [image of snapshot 0, ...], 'cam1': [...]}`` (images as read: grey or BGR, 8 or 16 bit;
    None where no frame lies within the camera's tolerance).

    Missing images are simply absent (a detection folder has none; a bag camera without a ``rostopic``
    in the camchain is skipped); the data were read once already, so errors here are not expected and
    are logged as a warning instead of failing the run."""
    request = source.request(stamps_ns)
    empty: dict[str, list[Image | None]] = {cam: [None] * len(stamps_ns) for cam in CAMERAS}
    try:
        path = Path(source.data)
        layout = detect_layout(path)
        if layout == "image_folder":
            return _folder_images(path, request)
        if layout in ("ros1_bag", "ros2_bag"):
            return _bag_images(path, _topics(source.camchain), request)
    except (ValueError, OSError) as exc:
        log.warning("rerun: the images of %s are not shown (%s); the corners are", source.data, exc)
    return empty


def display_image(image: Any) -> NDArray[np.uint8]:
    """An image as 8 bit for display: 16-bit images scaled by their largest value, BGRA reduced to BGR."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        top = float(img.max()) if img.size else 0.0
        img = (np.clip(img.astype(float) * (255.0 / top if top > 0 else 0.0), 0, 255)).astype(np.uint8)
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, :3]
    return np.ascontiguousarray(img)


def jpeg_bytes(image: Any, quality: int = 90) -> bytes:
    """The image (grey or BGR, any depth; :func:`display_image`) encoded as JPEG."""
    ok, buf = cv2.imencode(".jpg", display_image(image), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("image does not encode as JPEG")
    return buf.tobytes()
