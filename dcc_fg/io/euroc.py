"""EuRoC / ASL folder datasets (``mav0/cam0``, ``mav0/cam1``, ``mav0/imu0``) and packing them into bags.

Layout (ETH ASL): ``cam{0,1}/data.csv`` (``#timestamp [ns],filename``) with ``cam{0,1}/data/*.png``;
``imu0/data.csv`` (``#timestamp [ns], w_RS_S_x, w_RS_S_y, w_RS_S_z [rad/s], a_RS_S_x, a_RS_S_y,
a_RS_S_z [m/s^2]``); ``*/sensor.yaml`` with ``T_BS`` (sensor -> body, 4x4 row-major), camera
``intrinsics`` ``[fu, fv, cu, cv]``, ``distortion_model`` (``radial-tangential`` or
``equidistant``), ``distortion_coefficients`` and ``resolution``, IMU noise figures.  In EuRoC
the body frame is the IMU frame.

For dcc-fg, cam0 is the static camera ``s`` and cam1 is treated as a gimbal camera on a one-joint
mechanism locked at the published extrinsics (:func:`euroc_calibration`): ``tau_s = 0``, one DH
link ``[0, 0, 0]`` (its joint axis is cam0's optical axis), ``tau_d`` = the pose of cam0 in cam1,
so ``T_ds(theta = 0) = T_c1c0`` and the true joint angle is 0 by construction.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from dcc_fg.io.bag_writer import BagWriter
from dcc_fg.model import GimbalCalibration, write_text_atomic
from dcc_fg.data.vio import ImuConfig, ImuSamples
from factors.camera import CameraModel
from factors.chain import inv_se3, tau_from_se3

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
_DISTORTION = {"radial-tangential": "radtan", "radtan": "radtan", "equidistant": "equidistant"}


@dataclass(frozen=True)
class EurocDataset:
    """An ASL folder: camera models, extrinsics (``T_B_c0``, ``T_B_c1``: camera -> body/IMU), IMU
    samples and noise, and the (timestamp_ns, png path) lists of both cameras."""

    root: Path
    cam0: CameraModel
    cam1: CameraModel
    T_B_c0: FloatArray
    T_B_c1: FloatArray
    imu: ImuSamples
    imu_config: ImuConfig
    images0: list[tuple[int, Path]]
    images1: list[tuple[int, Path]]

    @property
    def T_c1c0(self) -> FloatArray:
        """cam0 -> cam1 (static -> dynamic camera), 4x4."""
        return inv_se3(self.T_B_c1) @ self.T_B_c0


def read_sensor_yaml(path: Path) -> dict[str, Any]:
    """Parse an ASL ``sensor.yaml`` (OpenCV's ``%YAML:1.0`` header is skipped)."""
    if not path.is_file():
        raise ValueError(f"{path}: sensor.yaml not found")
    lines = path.read_text().splitlines()
    text = "\n".join(ln for ln in lines if not ln.startswith("%YAML"))
    d = yaml.safe_load(text) or {}
    if not isinstance(d, dict):
        raise ValueError(f"{path}: not a YAML mapping")
    return d


def _T_BS(d: dict[str, Any], where: Path) -> FloatArray:
    try:
        T = np.asarray(d["T_BS"]["data"], dtype=float).reshape(4, 4)
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{where}: 'T_BS' must be a 4x4 matrix ({exc})") from None
    if not np.allclose(T[3], [0, 0, 0, 1]) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-5):
        raise ValueError(f"{where}: 'T_BS' is not a rigid transform")
    return T


def _camera(d: dict[str, Any], where: Path) -> CameraModel:
    try:
        model = _DISTORTION[str(d["distortion_model"])]
        return CameraModel(
            tuple(float(x) for x in d["intrinsics"]),  # type: ignore[arg-type]
            model,
            tuple(float(x) for x in d["distortion_coefficients"]),
            tuple(int(x) for x in d["resolution"]),  # type: ignore[arg-type]
        )
    except KeyError as exc:
        raise ValueError(f"{where}: missing or unsupported field {exc}") from None


def _image_list(cam_dir: Path) -> list[tuple[int, Path]]:
    csv = cam_dir / "data.csv"
    if not csv.is_file():
        raise ValueError(f"{csv}: image list not found")
    out = []
    for n, line in enumerate(csv.read_text().splitlines()):
        if not line.strip() or line.startswith("#"):
            continue
        parts = [p.strip() for p in line.split(",")]
        if len(parts) < 2:
            raise ValueError(f"{csv}:{n + 1}: expected 'timestamp,filename'")
        out.append((int(parts[0]), cam_dir / "data" / parts[1]))
    present = [(t, p) for t, p in out if p.is_file()]
    if not present:
        raise ValueError(f"{csv}: none of the {len(out)} listed images exists in {cam_dir / 'data'}")
    if len(present) < len(out):
        log.warning("%s: %d of %d listed images are missing; using the others", csv, len(out) - len(present), len(out))
    return sorted(present)


def _imu_csv(path: Path) -> ImuSamples:
    if not path.is_file():
        raise ValueError(f"{path}: IMU data not found")
    try:
        raw = np.loadtxt(path, delimiter=",", comments="#", dtype=np.float64, ndmin=2)
        t = np.loadtxt(path, delimiter=",", comments="#", dtype=np.int64, usecols=0, ndmin=1)
    except ValueError as exc:
        raise ValueError(f"{path}: cannot parse the IMU CSV ({exc})") from None
    if raw.shape[1] != 7:
        raise ValueError(f"{path}: expected 7 columns (timestamp, w xyz, a xyz), got {raw.shape[1]}")
    return ImuSamples(t_ns=t, acc=raw[:, 4:7].copy(), gyro=raw[:, 1:4].copy())


def load_euroc(root: str | Path) -> EurocDataset:
    """Read an ASL folder (``root`` is the ``mav0`` folder or its parent)."""
    root = Path(root)
    if (root / "mav0").is_dir():
        root = root / "mav0"
    s0, s1, si = (read_sensor_yaml(root / c / "sensor.yaml") for c in ("cam0", "cam1", "imu0"))
    imu_cfg = ImuConfig(
        T_sI=inv_se3(_T_BS(s0, root / "cam0/sensor.yaml")) @ _T_BS(si, root / "imu0/sensor.yaml"),
        accelerometer_noise_density=float(si.get("accelerometer_noise_density", 2.0e-3)),
        accelerometer_random_walk=float(si.get("accelerometer_random_walk", 3.0e-3)),
        gyroscope_noise_density=float(si.get("gyroscope_noise_density", 1.6968e-4)),
        gyroscope_random_walk=float(si.get("gyroscope_random_walk", 1.9393e-5)),
        rate_hz=float(si.get("rate_hz", 200.0)),
    )
    return EurocDataset(
        root=root,
        cam0=_camera(s0, root / "cam0/sensor.yaml"),
        cam1=_camera(s1, root / "cam1/sensor.yaml"),
        T_B_c0=_T_BS(s0, root / "cam0/sensor.yaml"),
        T_B_c1=_T_BS(s1, root / "cam1/sensor.yaml"),
        imu=_imu_csv(root / "imu0/data.csv"),
        imu_config=imu_cfg,
        images0=_image_list(root / "cam0"),
        images1=_image_list(root / "cam1"),
    )


def euroc_calibration(ds: EurocDataset) -> GimbalCalibration:
    """cam0 static, cam1 on a one-joint mechanism locked at the published extrinsics (theta = 0)."""
    return GimbalCalibration.from_parts(
        np.zeros(6), tau_from_se3(ds.T_c1c0), np.zeros((1, 3)), static_camera=ds.cam0, dynamic_camera=ds.cam1
    )


def write_euroc_calibration(ds: EurocDataset, path: str | Path) -> Path:
    """``calibration.yaml`` of :func:`euroc_calibration` with an ``imu:`` section (T_sI = T_c0_I)."""
    d = euroc_calibration(ds).to_dict()
    d["imu"] = ds.imu_config.to_dict()
    write_text_atomic(Path(path), yaml.safe_dump(d, sort_keys=False))
    return Path(path)


def _events(ds: EurocDataset, t0: int, t1: int) -> Iterator[tuple[int, int, str, Any]]:
    """(time, order, kind, payload) of IMU samples and images within [t0, t1], time-sorted."""
    ev: list[tuple[int, int, str, Any]] = []
    keep = (ds.imu.t_ns >= t0) & (ds.imu.t_ns <= t1)
    for i in np.flatnonzero(keep):
        ev.append((int(ds.imu.t_ns[i]), 0, "imu", int(i)))
    for kind, lst in (("cam0", ds.images0), ("cam1", ds.images1)):
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
    ds = load_euroc(root)
    t_img = [t for t, _ in ds.images0 + ds.images1]
    margin = int(imu_margin_s * 1e9)
    t0, t1 = min(t_img) - margin, max(t_img) + margin
    with BagWriter(out, ros) as bag:
        for t, _, kind, payload in _events(ds, t0, t1):
            if kind == "imu":
                bag.imu(imu_topic, t, ds.imu.acc[payload], ds.imu.gyro[payload], "imu0")
                continue
            img = cv2.imread(str(payload), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise ValueError(f"{payload}: image does not load")
            bag.image(static_topic if kind == "cam0" else dynamic_topic, t, img, kind)
    return Path(out)
