"""Reader for the gtsam wheel's ``eqvio_processed_30s.csv`` (EuRoC V1_01_easy, first 30 s).

The file has one header row ``row_type,t_abs,t_rel,seq,frame_idx,landmark_id,gx,gy,gz,ax,ay,az,
bgx,...,u_norm,v_norm,key,value`` and three kinds of rows:

* ``meta``: ``key,value`` pairs, among them ``measurement_space`` (must be ``normalized``),
  ``camera_fx/fy/cx/cy`` and the camera-IMU extrinsic ``T_ci_{tx,ty,tz,qw,qx,qy,qz}``. Despite its
  name, ``T_ci`` equals EuRoC's ``T_BS`` of cam0: it maps camera points into the IMU frame
  (``T_Ic``), so the static-camera mount is ``T_sI = inv(T_ci)``;
* ``imu``: ``t_abs`` (s, absolute), gyroscope ``gx,gy,gz`` (rad/s), accelerometer ``ax,ay,az`` (m/s^2);
* ``vision_feature``: ``t_abs``, ``frame_idx``, ``landmark_id`` and the undistorted normalized
  coordinates ``u_norm, v_norm`` of cam0.

The IMU noise figures are EuRoC's ADIS16448 values (:class:`~dcc_fg.data.vio.ImuConfig` defaults).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import gtsam
import numpy as np

from dcc_fg.data.vio import ImuConfig, ImuSamples, TrackFrame
from factors import chain

NS = 1_000_000_000


@dataclass(frozen=True)
class EqvioData:
    """IMU, cam0 tracks (as static-camera frames), the IMU config with ``T_sI``, and the meta rows."""

    imu: ImuSamples
    frames: list[TrackFrame]
    imu_config: ImuConfig
    meta: dict[str, str]
    focal_length: float


def default_eqvio_path() -> Path:
    """The wheel's copy of the file."""
    return Path(gtsam.findExampleDataFile("eqvio_processed_30s.csv"))


def _ns(t: str) -> int:
    whole, _, frac = t.partition(".")
    return int(whole) * NS + int((frac + "000000000")[:9])


def load_eqvio_csv(path: str | Path | None = None) -> EqvioData:
    """Parse the file (see module docstring); ValueError names the row at fault."""
    path = Path(path) if path is not None else default_eqvio_path()
    meta: dict[str, str] = {}
    imu_t: list[int] = []
    imu_rows: list[list[float]] = []
    feats: dict[int, list[tuple[int, float, float]]] = {}
    with path.open(newline="") as f:
        reader = csv.reader(f)
        header = next(reader, None)
        if header is None or header[0] != "row_type":
            raise ValueError(f"{path}: expected a header starting with 'row_type'")
        col = {name: i for i, name in enumerate(header)}
        for name in ("t_abs", "gx", "ax", "landmark_id", "u_norm", "v_norm", "key", "value"):
            if name not in col:
                raise ValueError(f"{path}: header lacks column '{name}'")
        for line, row in enumerate(reader, start=2):
            kind = row[0]
            try:
                if kind == "meta":
                    meta[row[col["key"]]] = row[col["value"]]
                elif kind == "imu":
                    imu_t.append(_ns(row[col["t_abs"]]))
                    g, a = col["gx"], col["ax"]
                    imu_rows.append([float(x) for x in row[g : g + 3] + row[a : a + 3]])
                elif kind == "vision_feature":
                    t = _ns(row[col["t_abs"]])
                    feats.setdefault(t, []).append(
                        (int(row[col["landmark_id"]]), float(row[col["u_norm"]]), float(row[col["v_norm"]]))
                    )
                else:
                    raise ValueError(f"unknown row_type '{kind}'")
            except (ValueError, IndexError) as err:
                raise ValueError(f"{path}:{line}: {err}") from None
    if meta.get("measurement_space", "normalized") != "normalized":
        raise ValueError(f"{path}: measurement_space is '{meta['measurement_space']}', expected 'normalized'")
    try:
        t = [float(meta[f"T_ci_t{c}"]) for c in "xyz"]
        q = [float(meta[f"T_ci_q{c}"]) for c in "wxyz"]
    except KeyError as err:
        raise ValueError(f"{path}: meta row {err} (camera-IMU extrinsic) missing") from None
    T_Ic = gtsam.Pose3(gtsam.Rot3.Quaternion(*q), np.array(t)).matrix()
    if not imu_t:
        raise ValueError(f"{path}: no imu rows")
    data = np.array(imu_rows)
    imu = ImuSamples(np.array(imu_t, dtype=np.int64), data[:, 3:6].copy(), data[:, 0:3].copy())
    frames = []
    for t_ns in sorted(feats):
        rows = feats[t_ns]
        ids = np.array([r[0] for r in rows], dtype=np.int64)
        xy = np.array([[r[1], r[2]] for r in rows], dtype=float)
        frames.append(TrackFrame(t_ns, ids, xy))
    fx = float(meta.get("camera_fx", "nan"))
    return EqvioData(imu, frames, ImuConfig(T_sI=chain.inv_se3(T_Ic)), meta, fx)
