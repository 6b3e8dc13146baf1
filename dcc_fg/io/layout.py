"""Which input layout a path holds, judged by content: a bag, an image folder or a detection folder.

Layouts:

* ``ros1_bag``: a ROS1 ``.bag`` file; ``ros2_bag``: a ROS2 bag folder (``metadata.yaml``,
  ``*.db3`` or ``*.mcap``);
* ``image_folder``: ``cam0/<timestamp_ns>.png``, ``cam1/<timestamp_ns>.png``, optional ``joints.csv``;
* ``detection_folder``: ``cam0/<timestamp_ns>.csv``, ``cam1/<timestamp_ns>.csv`` in yac's layout,
  optional ``joints.csv``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from dcc_fg.io.bags import is_bag
from dcc_fg.io.detections import is_detection_csv
from dcc_fg.io.folders import DYNAMIC_DIR, IMAGE_SUFFIXES, STATIC_DIR

Layout = Literal["ros1_bag", "ros2_bag", "image_folder", "detection_folder"]


def detect_layout(path: str | Path) -> Layout:
    """Which input layout ``path`` holds, judged by content (not by name alone).

    Raises:
        ValueError: naming ``path`` if it does not exist or matches no layout.
    """
    path = Path(path)
    if not path.exists():
        raise ValueError(f"{path}: no such file or folder")
    if is_bag(path):
        return "ros1_bag" if path.is_file() else "ros2_bag"
    if path.is_file():
        raise ValueError(f"{path}: not a ROS1 bag (no '#ROSBAG V2.0' magic); expected a bag or a data folder")
    static = path / STATIC_DIR
    if not static.is_dir() or not (path / DYNAMIC_DIR).is_dir():
        raise ValueError(
            f"{path}: not a ROS2 bag folder (no metadata.yaml, *.db3, *.mcap) and no {STATIC_DIR}/ and "
            f"{DYNAMIC_DIR}/ subfolders (image or detection folder layout)"
        )
    files = sorted(p for p in static.iterdir() if p.is_file())
    csvs = [p for p in files if p.suffix.lower() == ".csv"]
    images = [p for p in files if p.suffix.lower() in IMAGE_SUFFIXES]
    if csvs and not images:
        if not is_detection_csv(csvs[0]):
            raise ValueError(f"{csvs[0]}: CSV without yac's detection header (#ts,tag_rows,...,tag_id,corner_idx)")
        return "detection_folder"
    if images and not csvs:
        return "image_folder"
    if images and csvs:
        raise ValueError(f"{static}: holds both images and CSV files; cannot tell the layout")
    raise ValueError(f"{static}: no images (*.png, *.jpg, ...) and no detection CSV files")
