"""The calibrated dynamic camera cluster: kinematics, intrinsics, statistics; YAML load/save.

``calibration.yaml`` schema (the ``gimbal.yaml`` schema plus results)::

    joints: 2                       # L
    tau_s: [rx, ry, rz, tx, ty, tz] # T_bs: static camera -> gimbal base (rad, m)
    tau_d: [rx, ry, rz, tx, ty, tz] # T_de: end effector -> dynamic camera (rad, m)
    dh: [[d, a, alpha], ...]        # one row per link (m, m, rad)
    # written by a calibration, optional on input:
    tau_s_std / tau_d_std / dh_std  # 1-sigma, null where the parameter is not observable
    observable: {name: bool}        # per kinematic parameter, from the information matrix
    gauge_fixed: [names]            # parameters held at their initial values to fix the gauge
    cam0 / cam1                     # Kalibr camchain entries of the static / dynamic camera
    statistics: {...}               # reprojection errors, counts, solver info
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from dcc_fg.io.camchain import camera_from_dict, camera_to_dict
from dcc_fg.io.outputs import plain, write_text_atomic
from factors import chain
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]


@dataclass
class GimbalCalibration:
    """Kinematic model of a DCC (paper eq. 5) with optional intrinsics and statistics.

    Attributes:
        kin: ``[tau_s (6), tau_d (6), d_1, a_1, alpha_1, ...]`` (rad, m), see :mod:`factors.chain`.
        n_joints: L.
        static_camera, dynamic_camera: intrinsics (optional).
        kin_std: 1-sigma of each entry of ``kin`` (NaN where not observable or gauge-fixed).
        observable: per entry of ``kin``, whether it is observable from images.
        gauge_fixed: per entry of ``kin``, whether it was held fixed to remove the gauge freedom.
        statistics: free-form results (reprojection errors, counts, ...).
    """

    kin: FloatArray
    n_joints: int
    static_camera: CameraModel | None = None
    dynamic_camera: CameraModel | None = None
    kin_std: FloatArray | None = None
    observable: NDArray[np.bool_] | None = None
    gauge_fixed: NDArray[np.bool_] | None = None
    statistics: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.kin = np.asarray(self.kin, dtype=float).reshape(-1)
        if self.kin.shape[0] != chain.n_kin(self.n_joints):
            raise ValueError(f"kin has {self.kin.shape[0]} entries, expected {chain.n_kin(self.n_joints)}")

    @staticmethod
    def from_parts(tau_s: FloatArray, tau_d: FloatArray, dh: FloatArray, **kwargs: Any) -> GimbalCalibration:
        """Build from ``tau_s`` (6), ``tau_d`` (6) and ``dh`` (L, 3) rows ``[d, a, alpha]``."""
        dh = np.asarray(dh, dtype=float).reshape(-1, 3)
        kin = np.concatenate([np.asarray(tau_s, float), np.asarray(tau_d, float), dh.ravel()])
        return GimbalCalibration(kin=kin, n_joints=dh.shape[0], **kwargs)

    @property
    def tau_s(self) -> FloatArray:
        return self.kin[0:6]

    @property
    def tau_d(self) -> FloatArray:
        return self.kin[6:12]

    @property
    def dh(self) -> FloatArray:
        return self.kin[12:].reshape(self.n_joints, 3)

    @property
    def names(self) -> list[str]:
        return chain.kin_names(self.n_joints)

    def T_bs(self) -> FloatArray:
        """Static camera -> gimbal base (4x4)."""
        return chain.se3_from_tau(self.tau_s)

    def T_de(self) -> FloatArray:
        """Gimbal end effector -> dynamic camera (4x4)."""
        return chain.se3_from_tau(self.tau_d)

    def T_ds(self, theta: FloatArray | list[float] | float = ()) -> FloatArray:
        """Static camera -> dynamic camera at joint angles ``theta`` (L,) radians, 4x4."""
        th = np.atleast_1d(np.asarray(theta, dtype=float))
        if th.shape != (self.n_joints,):
            raise ValueError(f"theta must have {self.n_joints} joint angles, got {th.shape[0]}")
        return chain.T_ds(self.kin, th, self.n_joints)

    # ---------------------------------------------------------------- YAML
    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "joints": self.n_joints,
            "tau_s": [float(x) for x in self.tau_s],
            "tau_d": [float(x) for x in self.tau_d],
            "dh": [[float(x) for x in row] for row in self.dh],
        }
        if self.kin_std is not None:
            std = [None if not np.isfinite(s) else float(s) for s in self.kin_std]
            out["tau_s_std"] = std[0:6]
            out["tau_d_std"] = std[6:12]
            out["dh_std"] = [std[12 + 3 * i : 15 + 3 * i] for i in range(self.n_joints)]
        if self.observable is not None:
            out["observable"] = {n: bool(o) for n, o in zip(self.names, self.observable, strict=True)}
        if self.gauge_fixed is not None:
            out["gauge_fixed"] = [n for n, g in zip(self.names, self.gauge_fixed, strict=True) if g]
        if self.static_camera is not None:
            out["cam0"] = camera_to_dict(self.static_camera)
        if self.dynamic_camera is not None:
            out["cam1"] = camera_to_dict(self.dynamic_camera)
        if self.statistics:
            out["statistics"] = plain(self.statistics)
        return out

    @staticmethod
    def from_dict(d: dict[str, Any], source: str = "<calibration>") -> GimbalCalibration:
        for key in ("joints", "tau_s", "tau_d", "dh"):
            if key not in d:
                raise ValueError(f"{source}: missing field '{key}'")
        n = int(d["joints"])
        dh = np.asarray(d["dh"] if n else np.zeros((0, 3)), dtype=float).reshape(-1, 3)
        if dh.shape[0] != n:
            raise ValueError(f"{source}: 'dh' has {dh.shape[0]} rows but joints = {n}")
        for key in ("tau_s", "tau_d"):
            if len(d[key]) != 6:
                raise ValueError(f"{source}: '{key}' must have 6 entries [rx, ry, rz, tx, ty, tz]")
        cal = GimbalCalibration.from_parts(d["tau_s"], d["tau_d"], dh)
        if "tau_s_std" in d:
            std = list(d["tau_s_std"]) + list(d["tau_d_std"]) + [x for row in d.get("dh_std", []) for x in row]
            cal.kin_std = np.array([np.nan if s is None else float(s) for s in std])
        if "observable" in d:
            cal.observable = np.array([bool(d["observable"].get(k, False)) for k in cal.names])
        if "gauge_fixed" in d:
            cal.gauge_fixed = np.array([k in d["gauge_fixed"] for k in cal.names])
        if "cam0" in d:
            cal.static_camera = camera_from_dict(d["cam0"], f"{source}: cam0")
        if "cam1" in d:
            cal.dynamic_camera = camera_from_dict(d["cam1"], f"{source}: cam1")
        cal.statistics = dict(d.get("statistics", {}))
        return cal

    def save(self, path: str | Path) -> None:
        """Write ``calibration.yaml`` atomically."""
        write_text_atomic(Path(path), yaml.safe_dump(self.to_dict(), sort_keys=False))


def load_calibration(path: str | Path) -> GimbalCalibration:
    """Read a ``calibration.yaml`` or ``gimbal.yaml`` file."""
    path = Path(path)
    try:
        with path.open() as f:
            d = yaml.safe_load(f)
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: calibration file not found") from None
    if not isinstance(d, dict):
        raise ValueError(f"{path}: not a YAML mapping")
    return GimbalCalibration.from_dict(d, str(path))

