"""Target detection on every core: image pairs or single images in a process pool, results in input order.

The images are decoded here (reading a bag is sequential) and sent to ``jobs`` workers that run the
detector (:func:`dcc_fg.util.parallel.ordered_map`: bounded memory, input order kept, so the results
are those of the serial loop bit for bit). The detector must be a module-level function to run in a
pool (it is pickled by reference); any other callable (a lambda, a closure) runs serially, with a
logged note. Pixels are those of the distorted images, as everywhere in detection.
"""

from __future__ import annotations

import logging
import pickle
from collections.abc import Callable, Iterable, Iterator

import numpy as np
from numpy.typing import NDArray

from dcc_fg.data import Observation
from dcc_fg.targets import TargetGeometry
from dcc_fg.util.parallel import ordered_map

log = logging.getLogger(__name__)

Detector = Callable[[NDArray[np.generic], TargetGeometry], Observation]
PairTask = tuple[NDArray[np.generic], NDArray[np.generic], TargetGeometry, Detector]
ImageTask = tuple[NDArray[np.generic], TargetGeometry, Detector]
#: Modules the pool's fork server imports once for every worker.
PRELOAD = ("dcc_fg.detection",)


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
    return ordered_map(detect_pair, tasks, pool_jobs(detector, jobs), preload=PRELOAD)


def detect_images(
    images: Iterable[NDArray[np.generic]], target: TargetGeometry, detector: Detector, jobs: int = 1
) -> Iterator[Observation]:
    """Detections of single images, in input order, on ``jobs`` processes."""
    tasks = ((img, target, detector) for img in images)
    return ordered_map(detect_image, tasks, pool_jobs(detector, jobs), preload=PRELOAD)
