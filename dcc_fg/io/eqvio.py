"""Parser of the gtsam wheel's ``eqvio_processed_30s.csv`` (EuRoC V1_01_easy, first 30 s), as raw arrays.

The file has one header row ``row_type,t_abs,t_rel,seq,frame_idx,landmark_id,gx,gy,gz,ax,ay,az,
bgx,...,u_norm,v_norm,key,value`` and three kinds of rows:

* ``meta``: ``key,value`` pairs, among them ``measurement_space`` (must be ``normalized``),
  ``camera_fx/fy/cx/cy`` and the camera-IMU extrinsic ``T_ci_{tx,ty,tz,qw,qx,qy,qz}``;
* ``imu``: ``t_abs`` (s, absolute), gyroscope ``gx,gy,gz`` (rad/s), accelerometer ``ax,ay,az`` (m/s^2);
* ``vision_feature``: ``t_abs``, ``frame_idx``, ``landmark_id`` and the undistorted normalized
  coordinates ``u_norm, v_norm`` of cam0.

Times are parsed from the decimal text to integer ns (never through a float).
:mod:`dcc_fg.sources.eqvio` turns the arrays into IMU samples and track frames.
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path

import gtsam
import numpy as np
from numpy.typing import NDArray

from dcc_fg.io import validate
from dcc_fg.io.tum import text_to_ns


@dataclass(frozen=True)
class EqvioRows:
    """The rows of the file.

    Attributes:
        meta: the ``meta`` rows, key -> value text.
        imu_t_ns: (N,) IMU stamps, ns; imu_gyro, imu_acc: (N, 3) rad/s and m/s^2.
        features: per feature stamp (ns, ascending), the (M,) landmark ids and (M, 2)
            normalized coordinates ``u_norm, v_norm``.
    """

    meta: dict[str, str]
    imu_t_ns: NDArray[np.int64]
    imu_gyro: NDArray[np.float64]
    imu_acc: NDArray[np.float64]
    features: list[tuple[int, NDArray[np.int64], NDArray[np.float64]]]


def default_eqvio_path() -> Path:
    """The wheel's copy of the file."""
    return Path(gtsam.findExampleDataFile("eqvio_processed_30s.csv"))


def read_eqvio_rows(path: str | Path | None = None) -> EqvioRows:
    """Parse the file (see module docstring); ValueError names the row at fault."""
    path = Path(path) if path is not None else default_eqvio_path()
    meta: dict[str, str] = {}
    imu_t: list[int] = []
    imu_rows: list[list[float]] = []
    feats: dict[int, list[tuple[int, float, float]]] = {}
    text = validate.read_text(path, "eqvio CSV", "header row_type,t_abs,...")
    reader = csv.reader(io.StringIO(text, newline=""))
    header = next(reader, None)
    if header is None or header[0] != "row_type":
        raise ValueError(f"{path}: expected a header starting with 'row_type'")
    col = {name: i for i, name in enumerate(header)}
    for name in ("t_abs", "gx", "ax", "landmark_id", "u_norm", "v_norm", "key", "value"):
        if name not in col:
            raise ValueError(f"{path}: header lacks column '{name}'")
    for line, row in enumerate(reader, start=2):
        if not row:
            continue
        kind = row[0]
        try:
            if kind == "meta":
                meta[row[col["key"]]] = row[col["value"]]
            elif kind == "imu":
                imu_t.append(text_to_ns(row[col["t_abs"]]))
                g, a = col["gx"], col["ax"]
                imu_rows.append([float(x) for x in row[g : g + 3] + row[a : a + 3]])
            elif kind == "vision_feature":
                t = text_to_ns(row[col["t_abs"]])
                u, v = float(row[col["u_norm"]]), float(row[col["v_norm"]])
                if not (np.isfinite(u) and np.isfinite(v)):
                    raise ValueError(f"u_norm, v_norm must be finite numbers, got {u:g}, {v:g}")
                feats.setdefault(t, []).append((int(row[col["landmark_id"]]), u, v))
            else:
                raise ValueError(f"unknown row_type '{kind}'")
        except (ValueError, IndexError) as err:
            raise ValueError(f"{path}:{line}: {err}") from None
    if not imu_t:
        raise ValueError(f"{path}: no imu rows")
    data = np.array(imu_rows)
    features = []
    for t_ns in sorted(feats):
        rows = feats[t_ns]
        ids = np.array([r[0] for r in rows], dtype=np.int64)
        xy = np.array([[r[1], r[2]] for r in rows], dtype=float)
        features.append((t_ns, ids, xy))
    return EqvioRows(meta, np.array(imu_t, dtype=np.int64), data[:, 0:3].copy(), data[:, 3:6].copy(), features)
