"""The gtsam wheel's ``eqvio_processed_30s.csv`` (EuRoC V1_01_easy, first 30 s) as VIO measurements.

The file is parsed by :mod:`dcc_fg.io.eqvio`.  Its ``meta`` rows hold the camera-IMU extrinsic
``T_ci_{tx,ty,tz,qw,qx,qy,qz}``: despite its name, ``T_ci`` equals EuRoC's ``T_BS`` of cam0, it
maps camera points into the IMU frame (``T_Ic``), so the static-camera mount is
``T_sI = inv(T_ci)``.  The cam0 tracks become static-camera :class:`~dcc_fg.data.vio.TrackFrame`
objects; the IMU noise figures are EuRoC's ADIS16448 values (:class:`~dcc_fg.data.vio.ImuConfig`
defaults).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import gtsam
import numpy as np

from dcc_fg.data.vio import ImuConfig, ImuSamples, TrackFrame
from dcc_fg.io import validate
from dcc_fg.io.eqvio import default_eqvio_path, read_eqvio_rows
from dcc_fg.io.tum import QUATERNION_NORM_TOLERANCE
from factors import chain

__all__ = ["EqvioData", "default_eqvio_path", "load_eqvio_csv"]


@dataclass(frozen=True)
class EqvioData:
    """IMU, cam0 tracks (as static-camera frames), the IMU config with ``T_sI``, and the meta rows."""

    imu: ImuSamples
    frames: list[TrackFrame]
    imu_config: ImuConfig
    meta: dict[str, str]
    focal_length: float


def load_eqvio_csv(path: str | Path | None = None) -> EqvioData:
    """Read the file (default: the wheel's copy); ValueError names the row or meta entry at fault."""
    path = Path(path) if path is not None else default_eqvio_path()
    rows = read_eqvio_rows(path)
    meta = rows.meta
    if meta.get("measurement_space", "normalized") != "normalized":
        raise ValueError(f"{path}: measurement_space is '{meta['measurement_space']}', expected 'normalized'")
    try:
        t = [validate.number(meta[f"T_ci_t{c}"], f"{path}: meta T_ci_t{c}", unit="metres") for c in "xyz"]
        q = [validate.number(meta[f"T_ci_q{c}"], f"{path}: meta T_ci_q{c}") for c in "wxyz"]
    except KeyError as err:
        raise ValueError(f"{path}: meta row {err} (camera-IMU extrinsic) missing") from None
    if abs(float(np.linalg.norm(q)) - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise ValueError(f"{path}: meta T_ci_q{{w,x,y,z}} has norm {np.linalg.norm(q):.4g}, expected a unit quaternion")
    T_Ic = gtsam.Pose3(gtsam.Rot3.Quaternion(*q), np.array(t)).matrix()
    imu = ImuSamples(rows.imu_t_ns, rows.imu_acc, rows.imu_gyro)
    frames = [TrackFrame(t_ns, ids, xy) for t_ns, ids, xy in rows.features]
    fx = float(meta.get("camera_fx", "nan"))
    return EqvioData(imu, frames, ImuConfig(T_sI=chain.inv_se3(T_Ic)), meta, fx)
