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

N-camera clusters use the ``cameras:`` / ``chains:`` form instead of the top-level ``joints``,
``tau_s``, ``tau_d``, ``dh`` (schema in :mod:`dcc_fg.cluster`). A two-camera file is the cluster
``cam0`` (static, the reference s) + ``cam1`` on chain ``gimbal``: ``T_cs('cam1', theta) == T_ds(theta)``.
Either form loads into a :class:`GimbalCalibration` whose kinematics and intrinsics are those of
cam0 and the cluster's first camera on a chain (the pair the two-camera estimators use); its
:meth:`GimbalCalibration.cluster` / :meth:`GimbalCalibration.T_cs` give every camera, and code that
handles two cameras only calls :meth:`GimbalCalibration.require_two_cameras` first.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from dcc_fg.cluster import (
    DH_NAMES,
    LEGACY_CHAIN,
    TAU_NAMES,
    CameraCluster,
    CameraMount,
    ChainSpec,
    Theta,
    check_unique_keys,
    warn_degrees,
)
from dcc_fg.io import validate
from dcc_fg.io.camchain import camera_from_dict, camera_to_dict
from dcc_fg.io.outputs import plain, write_text_atomic
from factors import chain
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]

log = logging.getLogger(__name__)

#: Fields of the two-camera form that the ``cameras:`` / ``chains:`` form does not have.
LEGACY_FIELDS = ("joints", "tau_s", "tau_d", "dh", "tau_s_std", "tau_d_std", "dh_std", "observable", "gauge_fixed",
                 "held_by_prior", "cam0", "cam1")  # fmt: skip


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
        layout: the N-camera cluster of a ``cameras:`` / ``chains:`` file (every camera and chain but
            the primary pair, which :meth:`cluster` takes from the fields above); None for a two-camera
            calibration (cam0 static, cam1 on chain ``gimbal``).
        source: the file it was read from (for messages), None when built in code.
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
    layout: CameraCluster | None = None
    source: str | None = None

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

    # ---------------------------------------------------------------- N cameras
    @staticmethod
    def from_cluster(cluster: CameraCluster, **kwargs: Any) -> GimbalCalibration:
        """The calibration of an N-camera ``cluster``: kinematics and intrinsics of cam0 and the first
        camera on a chain (:attr:`CameraCluster.primary_gimbal_camera`), ``layout`` = the cluster."""
        primary = cluster.camera(cluster.primary_gimbal_camera)
        assert primary.chain is not None and primary.tau_d is not None
        ch = cluster.chain(primary.chain)
        kin_std = None
        if ch.tau_s_std is not None or primary.tau_d_std is not None or ch.dh_std is not None:
            nan6 = np.full(6, np.nan)
            kin_std = np.concatenate([
                nan6 if ch.tau_s_std is None else ch.tau_s_std,
                nan6 if primary.tau_d_std is None else primary.tau_d_std,
                np.full(3 * ch.n_joints, np.nan) if ch.dh_std is None else ch.dh_std.ravel(),
            ])  # fmt: skip
        kwargs.setdefault("kin_std", kin_std)
        return GimbalCalibration.from_parts(
            ch.tau_s, primary.tau_d, ch.dh, static_camera=cluster.cameras[0].camera, dynamic_camera=primary.camera,
            layout=cluster, **kwargs,
        )  # fmt: skip

    def _std_part(self, part: slice, shape: tuple[int, ...]) -> FloatArray | None:
        """``kin_std[part]`` reshaped, None where there is none or every entry is unknown (NaN)."""
        if self.kin_std is None:
            return None
        values = np.asarray(self.kin_std, dtype=float)[part]
        return None if values.size == 0 or not np.any(np.isfinite(values)) else values.reshape(shape)

    def cluster(self) -> CameraCluster:
        """Every camera and chain (:class:`dcc_fg.cluster.CameraCluster`); the primary pair (cam0 and the
        first camera on a chain) from this calibration's ``kin``, ``kin_std`` and intrinsics.

        A two-camera calibration is the cluster cam0 (static, the reference s) + cam1 on chain ``gimbal``.
        """
        L = self.n_joints
        tau_s_std, tau_d_std = self._std_part(slice(0, 6), (6,)), self._std_part(slice(6, 12), (6,))
        dh_std = self._std_part(slice(12, None), (L, 3))
        if self.layout is None:
            cameras = (
                CameraMount("cam0", camera=self.static_camera),
                CameraMount("cam1", LEGACY_CHAIN, tau_d=self.tau_d, camera=self.dynamic_camera, tau_d_std=tau_d_std),
            )
            return CameraCluster(cameras, (ChainSpec(LEGACY_CHAIN, self.tau_s, self.dh, tau_s_std, dh_std),))
        primary = self.layout.camera(self.layout.primary_gimbal_camera)
        mounts = []
        for m in self.layout.cameras:
            if m.name == "cam0":
                m = dataclasses.replace(m, camera=self.static_camera)
            elif m.name == primary.name:
                m = dataclasses.replace(m, tau_d=self.tau_d, camera=self.dynamic_camera, tau_d_std=tau_d_std)
            mounts.append(m)
        chains = [
            dataclasses.replace(c, tau_s=self.tau_s, dh=self.dh, tau_s_std=tau_s_std, dh_std=dh_std)
            if c.name == primary.chain else c
            for c in self.layout.chains
        ]  # fmt: skip
        return CameraCluster(tuple(mounts), tuple(chains))

    @property
    def camera_names(self) -> list[str]:
        """``['cam0', 'cam1', ...]``: every camera of the cluster."""
        return ["cam0", "cam1"] if self.layout is None else self.layout.camera_names

    @property
    def is_two_camera(self) -> bool:
        """A static camera cam0 and one gimbal camera cam1 on one chain, nothing else."""
        return self.layout is None or self.layout.is_two_camera

    def T_cs(self, camera: str, theta: Theta = None) -> FloatArray:
        """Reference static camera s (cam0) -> ``camera`` (4x4) at joint angles ``theta`` (rad).

        ``theta``: a mapping chain name -> (L,) angles, or the flat vector of all joints (chains in
        file order; for a two-camera calibration the usual (L,) ``theta``). Static cameras ignore it
        (cam0: the identity); a two-camera calibration's ``T_cs('cam1', theta)`` is ``T_ds(theta)``
        to the bit. See :meth:`dcc_fg.cluster.CameraCluster.T_cs`.
        """
        return self.cluster().T_cs(camera, theta)

    def require_two_cameras(self, purpose: str, allow_subset: bool = False) -> GimbalCalibration:
        """``self`` if ``purpose`` (``dcc-fg vio``, ``calibration``...) can use it: a two-camera cluster,
        or with ``allow_subset`` a larger one whose cam1 is on a chain (then only cam0 and cam1 are used,
        logged); else ValueError naming the file and saying that N-camera ``purpose`` is not supported yet.
        """
        if self.is_two_camera:
            return self
        assert self.layout is not None
        layout = self.layout
        where = self.source or "the calibration"
        desc = ", ".join(f"{c.name} ({'static' if c.is_static else 'chain ' + c.mount})" for c in layout.cameras)
        if allow_subset and not layout.cameras[1].is_static:
            rest = [c.name for c in layout.cameras[2:]]
            log.info(
                "%s: %s uses cam0 (static) and cam1 (chain %s) only; %s not used (N-camera %s is not supported yet)",
                where, purpose, layout.cameras[1].mount, ", ".join(rest), purpose,
            )  # fmt: skip
            return self
        hint = (
            " (a larger cluster can be used when its cam1 is on a chain; here cam1 is static)" if allow_subset else ""
        )
        if purpose == "calibration":
            hint += (
                "; give the file as dcc-fg calibrate --cluster FILE "
                "(or use dcc_fg.cluster_calibration.calibrate_cluster)"
            )
        raise ValueError(
            f"{where}: a {len(layout.cameras)}-camera cluster ({desc}); {purpose} handles a static camera cam0 and one "
            f"gimbal camera cam1 only: N-camera {purpose} is not supported yet{hint}"
        )

    # ---------------------------------------------------------------- YAML
    def to_dict(self) -> dict[str, Any]:
        """The file's mapping: the two-camera form, or the ``cameras:`` / ``chains:`` form of a cluster
        read from one (with ``statistics``)."""
        if self.layout is not None:
            dropped = [k for k, v in (("observable", self.observable), ("gauge_fixed", self.gauge_fixed),
                                      ("held_by_prior", self.held_by_prior or None)) if v is not None]  # fmt: skip
            if dropped:
                log.warning("%s: %s not written: the cameras/chains form has no such fields", self.source, dropped)
            out_cluster = self.cluster().to_dict()
            if self.statistics:
                out_cluster["statistics"] = plain(self.statistics)
            return out_cluster
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
        if "cameras" in d or "chains" in d:
            mixed = [k for k in LEGACY_FIELDS if k in d]
            if mixed:
                raise ValueError(
                    f"{source}: {', '.join(mixed)}: not fields of the cameras:/chains: form (give either the "
                    "two-camera fields joints, tau_s, tau_d, dh, cam0, cam1 or cameras: and chains:; per-chain values "
                    "go under chains.NAME, per-camera ones under cameras.camN)"
                )
            cal = GimbalCalibration.from_cluster(CameraCluster.from_dict(d, source), source=source)
            cal.statistics = _statistics(d, source)
            return cal
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
        warn_degrees(source, tau, dh)
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
        cal.statistics = _statistics(d, source)
        cal.source = source
        return cal

    def save(self, path: str | Path) -> None:
        """Write ``calibration.yaml`` atomically."""
        write_text_atomic(Path(path), yaml.safe_dump(self.to_dict(), sort_keys=False))


def _statistics(d: dict[str, Any], source: str) -> dict[str, Any]:
    stats = d.get("statistics") or {}
    if not isinstance(stats, dict):
        raise ValueError(f"{source}: statistics must be a mapping, got {stats!r}")
    return dict(stats)


def load_calibration(path: str | Path) -> GimbalCalibration:
    """Read a ``calibration.yaml`` or ``gimbal.yaml`` file, two-camera or ``cameras:`` / ``chains:`` form
    (every field checked, see :meth:`GimbalCalibration.from_dict`; errors name the file and the field or
    YAML line; in the cluster form a key given twice is refused too)."""
    path = Path(path)
    d = validate.load_yaml(path, "calibration", "joints, tau_s, tau_d, dh; or cameras:, chains:")
    if isinstance(d, dict) and ("cameras" in d or "chains" in d):
        check_unique_keys(validate.read_text(path, "calibration"), str(path))
    return GimbalCalibration.from_dict(d, str(path))
