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

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from dcc_fg.io import validate
from dcc_fg.io.camchain import camera_from_dict, camera_to_dict
from dcc_fg.io.outputs import plain, write_text_atomic
from factors import chain
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]

log = logging.getLogger(__name__)

TAU_NAMES = ("rx", "ry", "rz", "tx", "ty", "tz")
DH_NAMES = ("d", "a", "alpha")


def _warn_degrees(source: str, tau: dict[str, list[float]], dh: FloatArray) -> None:
    """Log a warning for angles beyond one turn (rad): probably written in degrees."""
    angles = {f"{k}[{i}]": v[i] for k, v in tau.items() for i in range(3)}
    angles.update({f"dh[{i}][2] (alpha)": float(row[2]) for i, row in enumerate(dh)})
    big = {k: v for k, v in angles.items() if abs(v) > validate.MAX_JOINT_ANGLE_RAD}
    if big:
        log.warning(
            "%s: angle(s) beyond one turn: %s; angles are radians (degrees written by mistake?)",
            source, ", ".join(f"{k} = {v:g}" for k, v in big.items()),
        )  # fmt: skip


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
        held_by_prior: directions the data did not determine, held by a weak prior
            (:meth:`dcc_fg.degeneracy.HeldDirections.report`: parameters, direction, held_at, prior_sigma).
        statistics: free-form results (reprojection errors, counts, ...).
    """

    kin: FloatArray
    n_joints: int
    static_camera: CameraModel | None = None
    dynamic_camera: CameraModel | None = None
    kin_std: FloatArray | None = None
    observable: NDArray[np.bool_] | None = None
    gauge_fixed: NDArray[np.bool_] | None = None
    held_by_prior: list[dict[str, Any]] = field(default_factory=list)
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
        if self.held_by_prior:
            out["held_by_prior"] = plain(self.held_by_prior)
        if self.static_camera is not None:
            out["cam0"] = camera_to_dict(self.static_camera)
        if self.dynamic_camera is not None:
            out["cam1"] = camera_to_dict(self.dynamic_camera)
        if self.statistics:
            out["statistics"] = plain(self.statistics)
        return out

    @staticmethod
    def from_dict(d: dict[str, Any], source: str = "<calibration>") -> GimbalCalibration:
        """Parse a ``gimbal.yaml`` / ``calibration.yaml`` mapping, checking every field.

        Raises:
            ValueError: naming ``source`` and the field: a missing field; ``joints`` that is not a
                non-negative integer; ``tau_s`` / ``tau_d`` that are not 6 finite numbers; ``dh``
                without one row of 3 finite numbers per joint; 1-sigma values (``*_std``) that
                are negative, non-finite or of the wrong length; a malformed ``observable`` /
                ``gauge_fixed``; a bad ``cam0`` / ``cam1`` entry (see
                :func:`dcc_fg.io.camchain.camera_from_dict`).
        """
        if not isinstance(d, dict):
            raise ValueError(f"{source}: expected a mapping with joints, tau_s, tau_d, dh")
        for key in ("joints", "tau_s", "tau_d", "dh"):
            if key not in d:
                raise ValueError(f"{source}: missing field '{key}' (a gimbal file has joints, tau_s, tau_d, dh)")
        n = validate.integer(d["joints"], f"{source}: joints", unit="joints", minimum=0)
        tau_form = "[rx, ry, rz, tx, ty, tz] (rad, m)"
        tau = {
            key: validate.numbers(d[key], f"{source}: {key}", 6, TAU_NAMES, form=tau_form) for key in ("tau_s", "tau_d")
        }
        dh_rows = d["dh"] if d["dh"] is not None else []
        if not isinstance(dh_rows, list) or len(dh_rows) != n:
            got = f"{len(dh_rows)} rows" if isinstance(dh_rows, list) else repr(dh_rows)
            raise ValueError(f"{source}: dh must have one row [d, a, alpha] per joint (joints = {n}), got {got}")
        dh = np.array(
            [validate.numbers(row, f"{source}: dh[{i}]", 3, DH_NAMES, form="[d, a, alpha] (m, m, rad)")
             for i, row in enumerate(dh_rows)],
            dtype=float,
        ).reshape(n, 3)  # fmt: skip
        _warn_degrees(source, tau, dh)
        cal = GimbalCalibration.from_parts(tau["tau_s"], tau["tau_d"], dh)
        if any(k in d for k in ("tau_s_std", "tau_d_std", "dh_std")):
            std = validate.numbers(d.get("tau_s_std"), f"{source}: tau_s_std", 6, TAU_NAMES, allow_null=True,
                                   nonnegative=True)  # fmt: skip
            std += validate.numbers(d.get("tau_d_std"), f"{source}: tau_d_std", 6, TAU_NAMES, allow_null=True,
                                    nonnegative=True)  # fmt: skip
            rows = d.get("dh_std") if n else (d.get("dh_std") or [])
            if not isinstance(rows, list) or len(rows) != n:
                raise ValueError(f"{source}: dh_std must have one row [d, a, alpha] per joint (joints = {n})")
            for i, row in enumerate(rows):
                std += validate.numbers(row, f"{source}: dh_std[{i}]", 3, DH_NAMES, allow_null=True, nonnegative=True)
            cal.kin_std = np.array(std, dtype=float)
        if "observable" in d:
            obs = d["observable"]
            if not isinstance(obs, dict) or not all(isinstance(v, bool) for v in obs.values()):
                raise ValueError(f"{source}: observable must be a mapping parameter name -> true/false")
            cal.observable = np.array([bool(obs.get(k, False)) for k in cal.names])
        if "gauge_fixed" in d:
            fixed = d["gauge_fixed"] or []
            unknown = [k for k in fixed if k not in cal.names] if isinstance(fixed, list) else None
            if unknown is None or unknown:
                raise ValueError(
                    f"{source}: gauge_fixed must be a list of parameter names ({', '.join(cal.names)}), got {fixed!r}"
                )
            cal.gauge_fixed = np.array([k in fixed for k in cal.names])
        if "held_by_prior" in d:
            held = d["held_by_prior"] or []
            if not isinstance(held, list) or not all(
                isinstance(h, dict) and isinstance(h.get("parameters"), list) for h in held
            ):
                raise ValueError(f"{source}: held_by_prior must be a list of mappings with a 'parameters' list")
            cal.held_by_prior = [dict(h) for h in held]
        if "cam0" in d:
            cal.static_camera = camera_from_dict(d["cam0"], source, "cam0")
        if "cam1" in d:
            cal.dynamic_camera = camera_from_dict(d["cam1"], source, "cam1")
        stats = d.get("statistics") or {}
        if not isinstance(stats, dict):
            raise ValueError(f"{source}: statistics must be a mapping, got {stats!r}")
        cal.statistics = dict(stats)
        return cal

    def save(self, path: str | Path) -> None:
        """Write ``calibration.yaml`` atomically."""
        write_text_atomic(Path(path), yaml.safe_dump(self.to_dict(), sort_keys=False))


def load_calibration(path: str | Path) -> GimbalCalibration:
    """Read a ``calibration.yaml`` or ``gimbal.yaml`` file (every field checked, see
    :meth:`GimbalCalibration.from_dict`; errors name the file and the field or YAML line)."""
    path = Path(path)
    d = validate.load_yaml(path, "calibration", "joints, tau_s, tau_d, dh")
    return GimbalCalibration.from_dict(d, str(path))
