"""Target detection on every core: image pairs or single images in a process pool, results in input order.

Two ways to feed the ``jobs`` workers (:func:`dcc_fg.util.parallel.ordered_map`: bounded memory, input
order kept, so the results are those of the serial loop bit for bit):

* :func:`detect_pairs` / :func:`detect_images`: the images are decoded here and sent to the workers;
* :func:`detect_referenced_pairs`: only where each pair's images are is sent (a bag's
  :class:`~dcc_fg.io.bags.MessageReference` or an image file's path); each worker reads (opening a bag
  once), decodes, checks and detects its pairs itself, so no image crosses a process boundary and this
  process only hands out references (reading and decoding were a fifth of the serial time for bags and
  more for PNG folders, and pickling the images to the workers cost as much again).

The detector must be a module-level function to run in a pool (it is pickled by reference); any other
callable (a lambda, a closure) runs serially, with a logged note. Pixels are those of the distorted
images, as everywhere in detection.
"""

from __future__ import annotations

import atexit
import logging
import pickle
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from dcc_fg.data import Observation
from dcc_fg.io.bags import MessageReference, bag_reader, fetch_image
from dcc_fg.io.folders import read_image
from dcc_fg.targets import TargetGeometry
from dcc_fg.util.parallel import ordered_map

log = logging.getLogger(__name__)

Detector = Callable[[NDArray[np.generic], TargetGeometry], Observation]
PairTask = tuple[NDArray[np.generic], NDArray[np.generic], TargetGeometry, Detector]
ImageTask = tuple[NDArray[np.generic], TargetGeometry, Detector]
#: Modules the pool's fork server imports once for every worker.
PRELOAD = ("dcc_fg.detection", "dcc_fg.io.bags", "dcc_fg.io.folders")
#: Pairs per pool task when the workers read the images themselves (a task is then a few hundred bytes:
#: one round trip through the pool per pair cost the main process ~0.75 ms, a quarter of a core).
REFERENCE_CHUNK = 8
#: A camera's name and its image size (width, height) in pixels, for :func:`check_resolution`.
CameraSize = tuple[str, tuple[int, int]]
#: Where an image is: a message of the task's bag, or an image file.
ImageReference = MessageReference | Path
ReferencedPairTask = tuple[
    str | None, ImageReference, ImageReference, tuple[CameraSize, CameraSize], TargetGeometry, Detector
]

#: The bags a worker process has open (opened at its first task, closed at its exit).
_OPEN_BAGS: dict[str, Any] = {}


def one_thread_per_worker() -> None:
    """Worker initializer: OpenCV on one thread, as many workers as cores (OpenCV's own threads would
    make each worker compete with the others for the same cores)."""
    cv2.setNumThreads(1)


def check_resolution(img: NDArray[np.generic], size: CameraSize, where: str) -> None:
    """Refuse an image whose size is not the camchain's ``resolution`` of its camera.

    Raises:
        ValueError: naming the image (``where``), its size, the camera and the camchain's size.
    """
    cam, (w, h) = size
    if img.shape[:2] != (h, w):
        raise ValueError(
            f"{where}: image is {img.shape[1]}x{img.shape[0]} but the camchain's {cam} resolution is {w}x{h}"
        )


def _close_bags() -> None:
    for reader in _OPEN_BAGS.values():
        reader.close()
    _OPEN_BAGS.clear()


def _open_bag(path: str) -> Any:
    """This process's opened reader of the bag ``path``."""
    reader = _OPEN_BAGS.get(path)
    if reader is None:
        reader = bag_reader(Path(path))
        reader.open()
        if not _OPEN_BAGS:
            atexit.register(_close_bags)
        _OPEN_BAGS[path] = reader
    return reader


def _read(bag: str | None, ref: ImageReference) -> tuple[NDArray[np.generic], str]:
    """The image ``ref`` (a message of ``bag`` or a file) and how errors name it."""
    if isinstance(ref, MessageReference):
        if bag is None:
            raise ValueError(f"{ref.topic}: a message reference needs its bag")
        return fetch_image(_open_bag(bag), Path(bag), ref), ref.where(Path(bag))
    return read_image(ref), str(ref)


def read_and_detect_pair(task: ReferencedPairTask) -> tuple[Observation, Observation]:
    """Worker: read the pair's two images (bag messages by record time, or files), check their sizes,
    detect."""
    bag, static, dynamic, sizes, target, detector = task
    out = []
    for ref, size in zip((static, dynamic), sizes, strict=True):
        image, where = _read(bag, ref)
        check_resolution(image, size, where)
        out.append(detector(image, target))
    return out[0], out[1]


def detect_pair(task: PairTask) -> tuple[Observation, Observation]:
    """Worker: the target in a static and a dynamic image."""
    static, dynamic, target, detector = task
    return detector(static, target), detector(dynamic, target)


def detect_image(task: ImageTask) -> Observation:
    """Worker: the target in one image."""
    image, target, detector = task
    return detector(image, target)


def pool_jobs(detector: Detector, jobs: int) -> int:
    """``jobs``, or 1 when ``detector`` cannot be sent to a worker process (not a module-level function)."""
    if jobs <= 1:
        return 1
    try:
        pickle.dumps(detector)
    except (pickle.PicklingError, AttributeError, TypeError):
        log.info("the detector %r is not a module-level function: detecting in this process only", detector)
        return 1
    return jobs


def detect_pairs(
    pairs: Iterable[tuple[NDArray[np.generic], NDArray[np.generic]]],
    target: TargetGeometry,
    detector: Detector,
    jobs: int = 1,
) -> Iterator[tuple[Observation, Observation]]:
    """Detections of (static, dynamic) image pairs, in input order, on ``jobs`` processes."""
    tasks = ((s, d, target, detector) for s, d in pairs)
    return ordered_map(
        detect_pair, tasks, pool_jobs(detector, jobs), preload=PRELOAD, initializer=one_thread_per_worker
    )


def detect_images(
    images: Iterable[NDArray[np.generic]], target: TargetGeometry, detector: Detector, jobs: int = 1
) -> Iterator[Observation]:
    """Detections of single images, in input order, on ``jobs`` processes."""
    tasks = ((img, target, detector) for img in images)
    return ordered_map(
        detect_image, tasks, pool_jobs(detector, jobs), preload=PRELOAD, initializer=one_thread_per_worker
    )


def detect_referenced_pairs(
    bag: Path | None,
    refs: Iterable[tuple[ImageReference, ImageReference]],
    sizes: tuple[CameraSize, CameraSize],
    target: TargetGeometry,
    detector: Detector,
    jobs: int,
) -> Iterator[tuple[Observation, Observation]]:
    """Detections of the (static, dynamic) image pairs ``refs`` (messages of ``bag`` or image files), in
    their order, each read, size-checked (``sizes`` of the static and the dynamic camera) and detected by
    one of ``jobs`` worker processes."""
    name = None if bag is None else str(bag)
    tasks = ((name, s, d, sizes, target, detector) for s, d in refs)
    return ordered_map(
        read_and_detect_pair,
        tasks,
        pool_jobs(detector, jobs),
        preload=PRELOAD,
        initializer=one_thread_per_worker,
        chunk=REFERENCE_CHUNK,
    )
