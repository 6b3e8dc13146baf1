"""EuRoC / ASL folder datasets (``mav0/cam0``, ``mav0/cam1``, ``mav0/imu0``): the files, and packing them into bags.

Layout (ETH ASL): ``cam{0,1}/data.csv`` (``#timestamp [ns],filename``) with ``cam{0,1}/data/*.png``;
``imu0/data.csv`` (``#timestamp [ns], w_RS_S_x, w_RS_S_y, w_RS_S_z [rad/s], a_RS_S_x, a_RS_S_y,
a_RS_S_z [m/s^2]``); ``*/sensor.yaml`` with ``T_BS`` (sensor -> body, 4x4 row-major), camera
``intrinsics`` ``[fu, fv, cu, cv]``, ``distortion_model`` (``radial-tangential`` or
``equidistant``), ``distortion_coefficients`` and ``resolution``, IMU noise figures.  In EuRoC
the body frame is the IMU frame.  :mod:`dcc_fg.sources.euroc` assembles a dataset and its
calibration from these readers.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from dcc_fg.io import validate
from dcc_fg.io.bag_writer import BagWriter
from dcc_fg.io.camchain import camera_from_dict
from factors.camera import CameraModel

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
_DISTORTION = {"radial-tangential": "radtan", "radtan": "radtan", "equidistant": "equidistant"}


def asl_root(root: str | Path) -> Path:
    """The ``mav0`` folder of an ASL dataset given it or its parent."""
    root = Path(root)
    return root / "mav0" if (root / "mav0").is_dir() else root


def read_sensor_yaml(path: Path) -> dict[str, Any]:
    """Parse an ASL ``sensor.yaml`` (OpenCV's ``%YAML:1.0`` header is skipped); errors name the file."""
    if not path.exists():
        raise ValueError(f"{path}: sensor.yaml not found")
    text = validate.read_text(path, "ASL sensor.yaml")
    lines = text.splitlines()
    # keep the line count so YAML errors point at the file's own line numbers
    d = validate.parse_yaml("\n".join("" if ln.startswith("%YAML") else ln for ln in lines), str(path), "sensor.yaml")
    if not isinstance(d, dict):
        raise ValueError(f"{path}: not a YAML mapping; expected an ASL sensor.yaml")
    return d


def sensor_T_BS(d: dict[str, Any], where: Path) -> FloatArray:
    """``T_BS`` of a parsed ``sensor.yaml``: sensor -> body (IMU), 4x4, checked to be rigid."""
    T_BS = d.get("T_BS")
    data = T_BS.get("data") if isinstance(T_BS, dict) else None
    if not isinstance(data, list) or len(data) != 16:
        raise ValueError(f"{where}: T_BS.data must be the 16 entries of a 4x4 matrix (row-major), got {data!r}")
    return validate.rigid_transform([data[4 * i : 4 * i + 4] for i in range(4)], f"{where}: T_BS")


def sensor_camera(d: dict[str, Any], where: Path) -> CameraModel:
    """The camera model of a parsed camera ``sensor.yaml`` (every field checked, errors name the field)."""
    for key in ("intrinsics", "distortion_model", "distortion_coefficients", "resolution"):
        if key not in d:
            raise ValueError(f"{where}: missing field '{key}'")
    model = str(d["distortion_model"])
    if model not in _DISTORTION:
        raise ValueError(f"{where}: distortion_model must be one of {', '.join(_DISTORTION)}, got {model!r}")
    entry = {
        "camera_model": d.get("camera_model", "pinhole"),
        "intrinsics": d["intrinsics"],
        "distortion_model": _DISTORTION[model],
        "distortion_coeffs": d["distortion_coefficients"],
        "resolution": d["resolution"],
    }
    return camera_from_dict(entry, str(where))


def read_image_list(cam_dir: Path) -> list[tuple[int, Path]]:
    """``(timestamp_ns, png path)`` of the images listed in ``cam_dir/data.csv`` that exist, sorted.

    Raises:
        ValueError: naming the file and line for a row that is not ``timestamp,filename`` with a
            positive integer timestamp (ns), or a timestamp listed twice.
    """
    csv = cam_dir / "data.csv"
    if not csv.is_file():
        raise ValueError(f"{csv}: image list not found")
    out = []
    seen: dict[int, int] = {}
    for n, line in enumerate(validate.read_text(csv, "ASL image list").splitlines(), start=1):
        if not line.strip() or line.startswith("#"):
            continue
        parts = [p.strip() for p in line.split(",")]
        if len(parts) < 2:
            raise ValueError(f"{csv}:{n}: expected 'timestamp,filename'")
        try:
            stamp = int(parts[0])
        except ValueError:
            raise ValueError(f"{csv}:{n}: timestamp must be an integer in ns, got {parts[0]!r}") from None
        if stamp <= 0:
            raise ValueError(f"{csv}:{n}: timestamp must be a positive integer in ns, got {stamp}")
        if stamp in seen:
            raise ValueError(f"{csv}:{n}: timestamp {stamp} is listed twice (also line {seen[stamp]})")
        seen[stamp] = n
        out.append((stamp, cam_dir / "data" / parts[1]))
    present = [(t, p) for t, p in out if p.is_file()]
    if not present:
        raise ValueError(f"{csv}: none of the {len(out)} listed images exists in {cam_dir / 'data'}")
    if len(present) < len(out):
        log.warning("%s: %d of %d listed images are missing; using the others", csv, len(out) - len(present), len(out))
    return sorted(present)


def read_imu_csv(path: Path) -> tuple[NDArray[np.int64], FloatArray, FloatArray]:
    """``imu0/data.csv``: stamps (N,) int64 ns (read as integers), accelerometer (N, 3) m/s^2 and
    gyroscope (N, 3) rad/s."""
    if not path.is_file():
        raise ValueError(f"{path}: IMU data not found")
    validate.read_text(path, "ASL IMU CSV")  # a folder, non-UTF-8 bytes, an empty file: named errors
    try:
        raw = np.loadtxt(path, delimiter=",", comments="#", dtype=np.float64, ndmin=2)
        t = np.loadtxt(path, delimiter=",", comments="#", dtype=np.int64, usecols=0, ndmin=1)
    except ValueError as exc:
        raise ValueError(f"{path}: cannot parse the IMU CSV ({exc})") from None
    if raw.shape[1] != 7:
        raise ValueError(f"{path}: expected 7 columns (timestamp, w xyz, a xyz), got {raw.shape[1]}")
    return t, raw[:, 4:7].copy(), raw[:, 1:4].copy()


def _events(
    imu_t_ns: NDArray[np.int64], images: dict[str, list[tuple[int, Path]]], t0: int, t1: int
) -> Iterator[tuple[int, int, str, Any]]:
    """(time, order, kind, payload) of IMU samples (payload: row index) within [t0, t1] and of
    images (payload: path), time-sorted."""
    ev: list[tuple[int, int, str, Any]] = []
    keep = (imu_t_ns >= t0) & (imu_t_ns <= t1)
    for i in np.flatnonzero(keep):
        ev.append((int(imu_t_ns[i]), 0, "imu", int(i)))
    for kind, lst in images.items():
        for t, p in lst:
            ev.append((t, 1, kind, p))
    ev.sort(key=lambda e: (e[0], e[1], e[2]))
    return iter(ev)


def pack_euroc_bag(
    root: str | Path,
    out: str | Path,
    ros: Literal[1, 2] = 2,
    imu_margin_s: float = 1.0,
    imu_topic: str = "/imu0",
    static_topic: str = "/cam0/image_raw",
    dynamic_topic: str = "/cam1/image_raw",
) -> Path:
    """Pack an ASL folder's images and IMU into a ROS1 bag file or ROS2 bag folder (streaming).

    IMU samples within ``imu_margin_s`` of the image span are kept (EuRoC's IMU stream may be much
    longer than the images).  Images are ``mono8`` ``sensor_msgs/Image``; IMU ``sensor_msgs/Imu``.
    """
    root = asl_root(root)
    for sensor in ("cam0", "cam1", "imu0"):  # the dataset must be complete and valid, as for load_euroc
        where = root / sensor / "sensor.yaml"
        d = read_sensor_yaml(where)
        sensor_T_BS(d, where)
        if sensor != "imu0":
            sensor_camera(d, where)
    imu_t, acc, gyro = read_imu_csv(root / "imu0/data.csv")
    images = {cam: read_image_list(root / cam) for cam in ("cam0", "cam1")}
    t_img = [t for t, _ in images["cam0"] + images["cam1"]]
    margin = int(imu_margin_s * 1e9)
    t0, t1 = min(t_img) - margin, max(t_img) + margin
    with BagWriter(out, ros) as bag:
        for t, _, kind, payload in _events(imu_t, images, t0, t1):
            if kind == "imu":
                bag.imu(imu_topic, t, acc[payload], gyro[payload], "imu0")
                continue
            img = cv2.imread(str(payload), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise ValueError(f"{payload}: image does not load")
            bag.image(static_topic if kind == "cam0" else dynamic_topic, t, img, kind)
    return Path(out)
