"""EuRoC / ASL folder datasets as a dcc-fg dataset and calibration.

The files are read by :mod:`dcc_fg.io.euroc` (which also packs them into bags).  For dcc-fg, cam0
is the static camera ``s`` and cam1 is treated as a gimbal camera on a one-joint mechanism locked
at the published extrinsics (:func:`euroc_calibration`): ``tau_s = 0``, one DH link ``[0, 0, 0]``
(its joint axis is cam0's optical axis), ``tau_d`` = the pose of cam0 in cam1, so
``T_ds(theta = 0) = T_c1c0`` and the true joint angle is 0 by construction.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from numpy.typing import NDArray

from dcc_fg.data.vio import ImuConfig, ImuSamples
from dcc_fg.io import validate
from dcc_fg.io.euroc import asl_root, read_image_list, read_imu_csv, read_sensor_yaml, sensor_camera, sensor_T_BS
from dcc_fg.io.outputs import write_text_atomic
from dcc_fg.model import GimbalCalibration
from factors.camera import CameraModel
from factors.chain import inv_se3, tau_from_se3

FloatArray = NDArray[np.float64]


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


def load_euroc(root: str | Path) -> EurocDataset:
    """Read an ASL folder (``root`` is the ``mav0`` folder or its parent)."""
    root = asl_root(root)
    s0, s1, si = (read_sensor_yaml(root / c / "sensor.yaml") for c in ("cam0", "cam1", "imu0"))
    imu_yaml = root / "imu0/sensor.yaml"

    def noise(key: str, default: float) -> float:
        return validate.number(si.get(key, default), f"{imu_yaml}: {key}", positive=True)

    imu_cfg = ImuConfig(
        T_sI=inv_se3(sensor_T_BS(s0, root / "cam0/sensor.yaml")) @ sensor_T_BS(si, imu_yaml),
        accelerometer_noise_density=noise("accelerometer_noise_density", 2.0e-3),
        accelerometer_random_walk=noise("accelerometer_random_walk", 3.0e-3),
        gyroscope_noise_density=noise("gyroscope_noise_density", 1.6968e-4),
        gyroscope_random_walk=noise("gyroscope_random_walk", 1.9393e-5),
        rate_hz=noise("rate_hz", 200.0),
    )
    t, acc, gyro = read_imu_csv(root / "imu0/data.csv")
    return EurocDataset(
        root=root,
        cam0=sensor_camera(s0, root / "cam0/sensor.yaml"),
        cam1=sensor_camera(s1, root / "cam1/sensor.yaml"),
        T_B_c0=sensor_T_BS(s0, root / "cam0/sensor.yaml"),
        T_B_c1=sensor_T_BS(s1, root / "cam1/sensor.yaml"),
        imu=ImuSamples(t_ns=t, acc=acc, gyro=gyro),
        imu_config=imu_cfg,
        images0=read_image_list(root / "cam0"),
        images1=read_image_list(root / "cam1"),
    )


def euroc_calibration(ds: EurocDataset, rigid: bool = False) -> GimbalCalibration:
    """cam0 static, cam1 on a one-joint mechanism locked at the published extrinsics (theta = 0); with
    ``rigid`` cam1 sits on a chain without joints (L = 0) at those extrinsics: a static stereo pair, which
    ``dcc-fg vio --mode mono`` uses as two static cameras."""
    links = np.zeros((0 if rigid else 1, 3))
    return GimbalCalibration.from_parts(
        np.zeros(6), tau_from_se3(ds.T_c1c0), links, static_camera=ds.cam0, dynamic_camera=ds.cam1
    )


def write_euroc_calibration(ds: EurocDataset, path: str | Path, rigid: bool = False) -> Path:
    """``calibration.yaml`` of :func:`euroc_calibration` with an ``imu:`` section (T_sI = T_c0_I)."""
    d = euroc_calibration(ds, rigid).to_dict()
    d["imu"] = ds.imu_config.to_dict()
    write_text_atomic(Path(path), yaml.safe_dump(d, sort_keys=False))
    return Path(path)
