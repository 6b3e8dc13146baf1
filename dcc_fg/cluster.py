"""A dynamic camera cluster of N cameras: static cameras and cameras on one or more gimbal chains.

Frames (docs/architecture.md): ``s`` is the *reference* static camera, always ``cam0``; every other
camera ``c`` is either

* **static**: rigid to ``s``, ``T_cs`` a constant 4x4 (maps points of ``s`` into ``c``; metres), or
* **on a chain**: mounted on the end effector ``e`` of a gimbal chain, ``T_ce = T_de(tau_d)``, so
  ``T_cs(theta) = T_de(tau_d) @ inv(A_1(theta_1) ... A_L(theta_L)) @ T_bs(tau_s)`` (paper eq. 5;
  :func:`factors.chain.T_ds` with ``kin = [tau_s, tau_d, dh]``). Each chain has its own base ``b``
  (``T_bs(tau_s)``: reference static camera -> that chain's base), its DH links ``dh`` (L, 3) rows
  ``[d, a, alpha]`` (m, m, rad) and its joint count L; several cameras may sit on the same chain end,
  each with its own ``tau_d``.

``tau = [rx, ry, rz, tx, ty, tz]``: 3-2-1 Euler angles (R = Rz Ry Rx, rad), then metres.

Joint angles ``theta`` are given per chain (a mapping chain name -> (L,) angles, rad) or as one flat
vector of :attr:`CameraCluster.joint_count` angles: the chains in the order of ``chains`` (the order
of the ``chains:`` section of the file), each chain's ``theta_1 .. theta_L`` in turn.

YAML (the ``cameras:`` / ``chains:`` form of ``gimbal.yaml`` / ``calibration.yaml``)::

    cameras:                       # cam0, cam1, ... camN-1 (Kalibr names, no gaps); cam0 is s
      cam0: {mount: static}        # + optional Kalibr intrinsics fields, rostopic
      cam1: {mount: static, T_cs: [[r11, r12, r13, tx], ..., [0, 0, 0, 1]]}   # s -> cam1 (4x4, m)
      cam2: {mount: gimbal, tau_d: [rx, ry, rz, tx, ty, tz]}                   # T_ce: e -> cam2
    chains:
      gimbal: {joints: 2, tau_s: [rx, ry, rz, tx, ty, tz], dh: [[d, a, alpha], [d, a, alpha]]}

Optional 1-sigma values: ``chains.<name>.tau_s_std`` (6), ``chains.<name>.dh_std`` (L rows of 3),
``cameras.<name>.tau_d_std`` (6); ``null`` where a value is unknown. Camera entries may carry the
Kalibr camchain fields (``camera_model``, ``intrinsics``, ``distortion_model``, ``distortion_coeffs``,
``resolution``: all or none; ``rostopic``). The static ``T_cs`` is a 4x4 in Kalibr's row layout
(like Kalibr's ``T_cn_cnm1``, but always from the reference camera ``cam0``); a rotation block off
orthonormal by rounding (up to :data:`dcc_fg.io.validate.ROTATION_TOLERANCE`) is projected onto the
nearest rotation when read. :func:`cluster_from_camchain` builds a cluster from a Kalibr camchain.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray

from dcc_fg.io import validate
from dcc_fg.io.camchain import REQUIRED, CamchainEntry, camchain_transforms, camera_from_dict, camera_to_dict
from dcc_fg.io.camchain import load_camchain as read_camchain
from factors import chain
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]

log = logging.getLogger(__name__)

TAU_NAMES = ("rx", "ry", "rz", "tx", "ty", "tz")
DH_NAMES = ("d", "a", "alpha")
TAU_FORM = "[rx, ry, rz, tx, ty, tz] (rad, m)"
DH_FORM = "[d, a, alpha] (m, m, rad)"

#: The mount of a static camera (a chain may not have this name).
STATIC = "static"
#: The reference static camera s.
REFERENCE = "cam0"
#: The chain of a two-camera ``gimbal.yaml`` (``joints``, ``tau_s``, ``tau_d``, ``dh`` at the top level).
LEGACY_CHAIN = "gimbal"

CAMERA_NAME = re.compile(r"^cam(0|[1-9][0-9]*)$")
CHAIN_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
CAMERA_KEYS = ("mount", "T_cs", "tau_d", "tau_d_std", "rostopic", *REQUIRED)
CHAIN_KEYS = ("joints", "tau_s", "dh", "tau_s_std", "dh_std")

#: Theta of a cluster: chain name -> (L,) angles (rad), or one flat vector of all joints (rad).
Theta = Mapping[str, ArrayLike] | ArrayLike | None


CHAIN_NAME_RULE = "letters, digits and '_', starting with a letter; not 'static' and not a camera name (camN)"


def valid_chain_name(name: object) -> bool:
    """A usable chain name (:data:`CHAIN_NAME_RULE`)."""
    return isinstance(name, str) and bool(CHAIN_NAME.match(name)) and name != STATIC and not CAMERA_NAME.match(name)


def warn_degrees(source: str, tau: Mapping[str, Sequence[float]], dh: FloatArray, prefix: str = "") -> None:
    """Log a warning for angles beyond one turn (rad): probably written in degrees.

    Args:
        source: the file, for the message.
        tau: field name -> tau (6,), whose first three entries are angles (rad).
        dh: (L, 3) rows ``[d, a, alpha]``; alpha is an angle (rad).
        prefix: prepended to the ``dh`` field name (``chains.gimbal.``).
    """
    angles = {f"{k}[{i}]": float(v[i]) for k, v in tau.items() for i in range(3)}
    angles.update({f"{prefix}dh[{i}][2] (alpha)": float(row[2]) for i, row in enumerate(dh)})
    big = {k: v for k, v in angles.items() if abs(v) > validate.MAX_JOINT_ANGLE_RAD}
    if big:
        log.warning(
            "%s: angle(s) beyond one turn: %s; angles are radians (degrees written by mistake?)",
            source, ", ".join(f"{k} = {v:g}" for k, v in big.items()),
        )  # fmt: skip


def _std_vector(value: FloatArray | None, shape: tuple[int, ...], what: str) -> FloatArray | None:
    """``value`` as a float array of ``shape`` (NaN allowed: unknown), or None."""
    if value is None:
        return None
    arr = np.asarray(value, dtype=float).reshape(shape)
    if np.any(arr[np.isfinite(arr)] < 0) or np.any(np.isinf(arr)):
        raise ValueError(f"{what}: 1-sigma values must be non-negative (NaN where unknown)")
    return arr


def _nullable(values: FloatArray) -> list[float | None]:
    return [float(x) if np.isfinite(x) else None for x in np.asarray(values, dtype=float).ravel()]


@dataclass(frozen=True, eq=False)
class ChainSpec:
    """One gimbal chain: base pose, DH links and joint count.

    Attributes:
        name: the chain's name (``gimbal``; letters, digits, ``_``; not ``static``).
        tau_s: (6,) ``T_bs``: reference static camera s -> this chain's base b (rad, m).
        dh: (L, 3) DH rows ``[d, a, alpha]`` (m, m, rad), link 1 first.
        tau_s_std, dh_std: optional 1-sigma values of ``tau_s`` (6,) and ``dh`` (L, 3); NaN where unknown.
    """

    name: str
    tau_s: FloatArray
    dh: FloatArray
    tau_s_std: FloatArray | None = None
    dh_std: FloatArray | None = None

    def __post_init__(self) -> None:
        if not valid_chain_name(self.name):
            raise ValueError(f"chain name {self.name!r}: {CHAIN_NAME_RULE}")
        object.__setattr__(self, "tau_s", np.asarray(self.tau_s, dtype=float).reshape(6))
        object.__setattr__(self, "dh", np.asarray(self.dh, dtype=float).reshape(-1, 3))
        if not (np.all(np.isfinite(self.tau_s)) and np.all(np.isfinite(self.dh))):
            raise ValueError(f"chain {self.name}: tau_s and dh must be finite")
        object.__setattr__(self, "tau_s_std", _std_vector(self.tau_s_std, (6,), f"chain {self.name}: tau_s_std"))
        object.__setattr__(self, "dh_std", _std_vector(self.dh_std, (self.n_joints, 3), f"chain {self.name}: dh_std"))

    @property
    def n_joints(self) -> int:
        """L, the number of revolute joints (DH links)."""
        return int(self.dh.shape[0])

    def T_bs(self) -> FloatArray:
        """Reference static camera s -> this chain's base b (4x4)."""
        return chain.se3_from_tau(self.tau_s)

    def T_eb(self, theta: ArrayLike) -> FloatArray:
        """Base b -> end effector e at joint angles ``theta`` (L,) rad: ``inv(A_1 ... A_L)`` (4x4)."""
        return chain.T_eb(self.dh, np.asarray(theta, dtype=float).reshape(self.n_joints))


@dataclass(frozen=True, eq=False)
class CameraMount:
    """One camera of the cluster and where it sits.

    Attributes:
        name: ``cam0``, ``cam1``, ... (Kalibr's names); ``cam0`` is the reference static camera s.
        chain: the chain whose end effector carries the camera; None for a static camera.
        tau_d: (6,) ``T_ce = T_de(tau_d)``: end effector e -> this camera (rad, m); chain cameras only.
        T_cs: (4, 4) reference static camera s -> this camera (m); static cameras only (identity for cam0).
        camera: intrinsics (optional).
        rostopic: the image topic (optional, Kalibr's ``rostopic``).
        tau_d_std: optional 1-sigma of ``tau_d`` (6,), NaN where unknown.
    """

    name: str
    chain: str | None = None
    tau_d: FloatArray | None = None
    T_cs: FloatArray | None = None
    camera: CameraModel | None = None
    rostopic: str | None = None
    tau_d_std: FloatArray | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not CAMERA_NAME.match(self.name):
            raise ValueError(f"camera name {self.name!r}: cameras are named cam0, cam1, ... (Kalibr's names)")
        if self.chain is None:
            if self.tau_d is not None or self.tau_d_std is not None:
                raise ValueError(f"camera {self.name}: a static camera has T_cs, not tau_d")
            T = np.eye(4) if self.T_cs is None and self.name == REFERENCE else self.T_cs
            if T is None:
                raise ValueError(f"camera {self.name}: a static camera needs T_cs (reference static camera -> it)")
            T = np.array(T, dtype=float).reshape(4, 4)
            if not np.all(np.isfinite(T)):
                raise ValueError(f"camera {self.name}: T_cs must be finite")
            object.__setattr__(self, "T_cs", T)
        else:
            if self.T_cs is not None:
                raise ValueError(f"camera {self.name}: a camera on chain {self.chain} has tau_d, not T_cs")
            if self.tau_d is None:
                raise ValueError(f"camera {self.name}: a camera on chain {self.chain} needs tau_d (end effector -> it)")
            tau_d = np.asarray(self.tau_d, dtype=float).reshape(6)
            if not np.all(np.isfinite(tau_d)):
                raise ValueError(f"camera {self.name}: tau_d must be finite")
            object.__setattr__(self, "tau_d", tau_d)
            object.__setattr__(self, "tau_d_std", _std_vector(self.tau_d_std, (6,), f"camera {self.name}: tau_d_std"))

    @property
    def is_static(self) -> bool:
        """Rigid to the reference static camera."""
        return self.chain is None

    @property
    def mount(self) -> str:
        """``static`` or the chain's name (the ``mount:`` field of the file)."""
        return STATIC if self.chain is None else self.chain

    def T_de(self) -> FloatArray:
        """End effector e -> this camera (4x4); chain cameras only."""
        if self.tau_d is None:
            raise ValueError(f"camera {self.name} is static: it has no end-effector mount T_de")
        return chain.se3_from_tau(self.tau_d)


def _camera_number(name: str) -> int:
    return int(name[3:])


def check_structure(cameras: Sequence[CameraMount], chains: Sequence[ChainSpec], source: str) -> None:
    """The cluster's structure; ValueError naming ``source`` and the field.

    Refused: no cameras; duplicate camera or chain names; cameras other than ``cam0 .. camN-1``
    in that order; ``cam0`` not static or with ``T_cs`` other than the identity; a camera on an unknown
    chain; a chain carrying no camera; no chain at all.
    """
    names = [c.name for c in cameras]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"{source}: cameras: duplicate camera name(s) {', '.join(dup)}")
    chain_names = [c.name for c in chains]
    dup = sorted({n for n in chain_names if chain_names.count(n) > 1})
    if dup:
        raise ValueError(f"{source}: chains: duplicate chain name(s) {', '.join(dup)}")
    if not names or names[0] != REFERENCE:
        raise ValueError(f"{source}: cameras: the reference static camera cam0 is missing (got {', '.join(names)})")
    expected = [f"cam{k}" for k in range(len(names))]
    if names != expected:
        raise ValueError(
            f"{source}: cameras must be named {', '.join(expected)} in order, without gaps (Kalibr's names); "
            f"got {', '.join(names)}"
        )
    ref = cameras[0]
    if not ref.is_static:
        raise ValueError(
            f"{source}: cameras.cam0.mount must be 'static': cam0 is the reference static camera s, got {ref.mount!r}"
        )
    if ref.T_cs is not None and not np.allclose(ref.T_cs, np.eye(4), rtol=0.0, atol=1e-12):
        raise ValueError(f"{source}: cameras.cam0.T_cs must be the identity (cam0 is the reference s) or omitted")
    known = set(chain_names)
    for cam in cameras:
        if cam.chain is not None and cam.chain not in known:
            listed = ", ".join(chain_names) or "none"
            raise ValueError(
                f"{source}: cameras.{cam.name}.mount: unknown chain {cam.chain!r} (chains: {listed}; or 'static')"
            )
    if not chains:
        raise ValueError(f"{source}: chains: a cluster needs at least one chain carrying a camera (none given)")
    for ch in chains:
        if not any(c.chain == ch.name for c in cameras):
            raise ValueError(
                f"{source}: chains.{ch.name}: no camera is mounted on it (give a camera 'mount: {ch.name}' or "
                "remove the chain)"
            )


@dataclass(frozen=True, eq=False)
class CameraCluster:
    """N cameras: the reference static camera cam0, other static cameras, cameras on gimbal chains.

    Attributes:
        cameras: ``cam0 .. camN-1`` in order; ``cam0`` static (the reference s).
        chains: the gimbal chains; their order is the order of the flat joint-angle vector.
    """

    cameras: tuple[CameraMount, ...]
    chains: tuple[ChainSpec, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "cameras", tuple(self.cameras))
        object.__setattr__(self, "chains", tuple(self.chains))
        check_structure(self.cameras, self.chains, "CameraCluster")

    # ------------------------------------------------------------------------ structure
    @property
    def camera_names(self) -> list[str]:
        """``['cam0', 'cam1', ...]``."""
        return [c.name for c in self.cameras]

    @property
    def chain_names(self) -> list[str]:
        """The chains, in the order of the flat joint-angle vector."""
        return [c.name for c in self.chains]

    def camera(self, name: str) -> CameraMount:
        """The camera ``name``; KeyError listing the cameras."""
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(f"no camera {name!r} in the cluster (cameras: {', '.join(self.camera_names)})")

    def chain(self, name: str) -> ChainSpec:
        """The chain ``name``; KeyError listing the chains."""
        for c in self.chains:
            if c.name == name:
                return c
        raise KeyError(f"no chain {name!r} in the cluster (chains: {', '.join(self.chain_names)})")

    def cameras_on(self, chain_name: str) -> list[str]:
        """The cameras on the end effector of chain ``chain_name``, in camera order."""
        return [c.name for c in self.cameras if c.chain == chain_name]

    @property
    def static_cameras(self) -> list[str]:
        """The static cameras (cam0 first)."""
        return [c.name for c in self.cameras if c.is_static]

    @property
    def primary_gimbal_camera(self) -> str:
        """The first camera on a chain (in camera order): the gimbal camera d of :meth:`T_ds`."""
        return next(c.name for c in self.cameras if not c.is_static)

    @property
    def is_two_camera(self) -> bool:
        """Exactly today's two-camera cluster: static cam0 and cam1 on the only chain."""
        return len(self.cameras) == 2 and not self.cameras[1].is_static

    @property
    def joint_count(self) -> int:
        """Total number of joints, the length of the flat joint-angle vector."""
        return sum(c.n_joints for c in self.chains)

    def joint_slices(self) -> dict[str, slice]:
        """Chain name -> its slice of the flat joint-angle vector (chains in order, theta_1..theta_L each)."""
        out, k = {}, 0
        for c in self.chains:
            out[c.name] = slice(k, k + c.n_joints)
            k += c.n_joints
        return out

    def split_theta(self, theta: Theta) -> dict[str, FloatArray]:
        """Chain name -> (L,) joint angles (rad) from a mapping or a flat vector (see the module docstring).

        Raises:
            ValueError: a flat vector of the wrong length, or a mapping missing a chain / with the wrong count.
        """
        return {c.name: self.chain_theta(c.name, theta) for c in self.chains}

    def chain_theta(self, chain_name: str, theta: Theta) -> FloatArray:
        """The (L,) joint angles (rad) of chain ``chain_name`` out of ``theta`` (a mapping or a flat vector)."""
        ch = self.chain(chain_name)
        if isinstance(theta, Mapping):
            if chain_name not in theta:
                if ch.n_joints == 0:
                    return np.zeros(0)
                raise ValueError(f"theta has no joint angles for chain {chain_name!r} (given: {', '.join(theta)})")
            th = np.atleast_1d(np.asarray(theta[chain_name], dtype=float)).reshape(-1)
            if th.shape != (ch.n_joints,):
                raise ValueError(f"theta[{chain_name!r}] must have {ch.n_joints} joint angles, got {th.shape[0]}")
            return th
        flat = np.atleast_1d(np.asarray((), dtype=float) if theta is None else np.asarray(theta, dtype=float))
        flat = flat.reshape(-1)
        if flat.shape != (self.joint_count,):
            order = ", ".join(f"{c.name} ({c.n_joints})" for c in self.chains)
            raise ValueError(
                f"theta must have {self.joint_count} joint angles (chains in order: {order}) or be a mapping chain "
                f"-> angles, got {flat.shape[0]}"
            )
        return flat[self.joint_slices()[chain_name]]

    # ------------------------------------------------------------------------ kinematics
    def kin_of(self, camera: str) -> FloatArray:
        """``[tau_s (6), tau_d (6), dh (3L)]`` of ``camera``'s chain and mount, the ``kin`` vector of
        :mod:`factors.chain` for the pair (cam0, camera); chain cameras only."""
        mount = self.camera(camera)
        if mount.chain is None or mount.tau_d is None:
            raise ValueError(f"camera {camera} is static: it has no chain parameters")
        ch = self.chain(mount.chain)
        return np.concatenate([ch.tau_s, mount.tau_d, ch.dh.ravel()])

    def T_cs(self, camera: str, theta: Theta = None) -> FloatArray:
        """Reference static camera s (cam0) -> ``camera`` (4x4; maps points of s into the camera).

        Static cameras ignore ``theta`` (cam0: the identity). A camera on a chain: ``T_de(tau_d) @
        inv(A_1 ... A_L) @ T_bs(tau_s)`` (:func:`factors.chain.T_ds`) at that chain's joint angles out
        of ``theta`` (a mapping chain -> (L,) rad, or the flat vector of all joints, rad).
        """
        mount = self.camera(camera)
        if mount.chain is None:
            assert mount.T_cs is not None
            return mount.T_cs.copy()
        ch = self.chain(mount.chain)
        th = self.chain_theta(ch.name, theta)
        return chain.T_ds(self.kin_of(camera), th, ch.n_joints)

    def T_ds(self, theta: Theta = None) -> FloatArray:
        """``T_cs`` of the first camera on a chain (:attr:`primary_gimbal_camera`), the single-gimbal case."""
        return self.T_cs(self.primary_gimbal_camera, theta)

    # ------------------------------------------------------------------------ YAML
    def to_dict(self) -> dict[str, Any]:
        """The ``cameras:`` / ``chains:`` mapping (module docstring); reads back with :meth:`from_dict`."""
        cameras: dict[str, Any] = {}
        for c in self.cameras:
            item: dict[str, Any] = {"mount": c.mount}
            if c.chain is None and c.name != REFERENCE:
                assert c.T_cs is not None
                item["T_cs"] = [[float(x) for x in row] for row in c.T_cs]
            if c.tau_d is not None:
                item["tau_d"] = [float(x) for x in c.tau_d]
            if c.tau_d_std is not None:
                item["tau_d_std"] = _nullable(c.tau_d_std)
            if c.camera is not None:
                item.update(camera_to_dict(c.camera))
            if c.rostopic is not None:
                item["rostopic"] = c.rostopic
            cameras[c.name] = item
        chains: dict[str, Any] = {}
        for ch in self.chains:
            entry: dict[str, Any] = {
                "joints": ch.n_joints,
                "tau_s": [float(x) for x in ch.tau_s],
                "dh": [[float(x) for x in row] for row in ch.dh],
            }
            if ch.tau_s_std is not None:
                entry["tau_s_std"] = _nullable(ch.tau_s_std)
            if ch.dh_std is not None:
                entry["dh_std"] = [_nullable(row) for row in ch.dh_std]
            chains[ch.name] = entry
        return {"cameras": cameras, "chains": chains}

    @staticmethod
    def from_dict(d: Mapping[str, Any], source: str = "<cluster>") -> CameraCluster:
        """Parse the ``cameras:`` and ``chains:`` sections of ``d``, checking every field.

        Raises:
            ValueError: naming ``source`` and the field (``cameras.cam2.tau_d[3] (tx)``): a missing or
                unknown field; a camera on an unknown chain; a chain without a camera; camera names other
                than cam0..camN-1; cam0 not static; ``joints`` that is not a non-negative integer; ``tau_s``
                / ``tau_d`` that are not 6 finite numbers; ``dh`` without one row of 3 finite numbers per
                joint; a ``T_cs`` that is not a rigid 4x4; bad 1-sigma values or Kalibr fields.
        """
        for key in ("cameras", "chains"):
            if key not in d:
                raise ValueError(f"{source}: missing field '{key}' (a cluster file has both cameras: and chains:)")
            if not isinstance(d[key], dict) or not d[key]:
                raise ValueError(f"{source}: {key} must be a non-empty mapping name -> entry, got {d[key]!r}")
        chains = [_chain_from_dict(str(name), entry, source) for name, entry in d["chains"].items()]
        cameras = [_camera_from_dict(str(name), entry, source) for name, entry in d["cameras"].items()]
        cameras.sort(key=lambda c: _camera_number(c.name))
        check_structure(cameras, chains, source)
        return CameraCluster(tuple(cameras), tuple(chains))


def _strict_keys(entry: Mapping[str, Any], allowed: Sequence[str], where: str) -> None:
    unknown = [str(k) for k in entry if k not in allowed]
    if unknown:
        raise ValueError(f"{where}: unknown field(s) {', '.join(unknown)} (allowed: {', '.join(allowed)})")


def _std_rows(value: Any, n: int, where: str) -> FloatArray:
    if not isinstance(value, list) or len(value) != n:
        raise ValueError(f"{where} must have one row [d, a, alpha] per joint (joints = {n}), got {value!r}")
    rows = [validate.numbers(r, f"{where}[{i}]", 3, DH_NAMES, allow_null=True, nonnegative=True)
            for i, r in enumerate(value)]  # fmt: skip
    return np.array(rows, dtype=float).reshape(n, 3)


def _chain_from_dict(name: str, entry: Any, source: str) -> ChainSpec:
    where = f"{source}: chains.{name}"
    if not valid_chain_name(name):
        raise ValueError(f"{where}: chain name {name!r}: {CHAIN_NAME_RULE}")
    if not isinstance(entry, dict):
        raise ValueError(f"{where} must be a mapping with joints, tau_s, dh, got {entry!r}")
    _strict_keys(entry, CHAIN_KEYS, where)
    for key in ("joints", "tau_s", "dh"):
        if key not in entry:
            raise ValueError(f"{where}.{key}: missing field (a chain has joints, tau_s, dh)")
    n = validate.integer(entry["joints"], f"{where}.joints", unit="joints", minimum=0)
    tau_s = validate.numbers(entry["tau_s"], f"{where}.tau_s", 6, TAU_NAMES, form=TAU_FORM)
    rows = entry["dh"] if entry["dh"] is not None else []
    if not isinstance(rows, list) or len(rows) != n:
        got = f"{len(rows)} rows" if isinstance(rows, list) else repr(rows)
        raise ValueError(f"{where}.dh must have one row [d, a, alpha] per joint (joints = {n}), got {got}")
    dh = np.array([validate.numbers(r, f"{where}.dh[{i}]", 3, DH_NAMES, form=DH_FORM) for i, r in enumerate(rows)],
                  dtype=float).reshape(n, 3)  # fmt: skip
    warn_degrees(source, {f"chains.{name}.tau_s": tau_s}, dh, f"chains.{name}.")
    tau_s_std = None
    if entry.get("tau_s_std") is not None:
        tau_s_std = np.array(validate.numbers(entry["tau_s_std"], f"{where}.tau_s_std", 6, TAU_NAMES,
                                              allow_null=True, nonnegative=True), dtype=float)  # fmt: skip
    dh_std = _std_rows(entry["dh_std"], n, f"{where}.dh_std") if entry.get("dh_std") is not None else None
    return ChainSpec(name, np.array(tau_s), dh, tau_s_std, dh_std)


def nearest_rigid(T: FloatArray) -> FloatArray:
    """``T`` with its rotation block projected onto the nearest rotation (SVD) when it is off
    orthonormal by more than rounding (``||R^T R - I|| > 1e-12``); unchanged otherwise."""
    T = np.array(T, dtype=float)
    R = T[:3, :3]
    if float(np.linalg.norm(R.T @ R - np.eye(3))) <= 1e-12:
        return T
    U, _, Vt = np.linalg.svd(R)
    T[:3, :3] = U @ Vt
    return T


def _camera_from_dict(name: str, entry: Any, source: str) -> CameraMount:
    where = f"{source}: cameras.{name}"
    if not CAMERA_NAME.match(name):
        raise ValueError(f"{where}: cameras are named cam0, cam1, ... camN-1 (Kalibr's names)")
    if not isinstance(entry, dict):
        raise ValueError(f"{where} must be a mapping with mount: static or mount: CHAIN, got {entry!r}")
    _strict_keys(entry, CAMERA_KEYS, where)
    if "mount" not in entry:
        raise ValueError(f"{where}.mount: missing field ('static', or the name of the chain carrying the camera)")
    mount = entry["mount"]
    if not isinstance(mount, str) or not mount:
        raise ValueError(f"{where}.mount must be 'static' or a chain name, got {mount!r}")
    camera = None
    if any(k in entry for k in REQUIRED):
        camera = camera_from_dict({k: entry[k] for k in entry if k in REQUIRED}, source, f"cameras.{name}")
    rostopic = entry.get("rostopic")
    if rostopic is not None and not isinstance(rostopic, str):
        raise ValueError(f"{where}.rostopic must be a topic name (text), got {rostopic!r}")
    if mount == STATIC:
        for key in ("tau_d", "tau_d_std"):
            if key in entry:
                raise ValueError(f"{where}.{key}: a static camera has no end-effector mount (give T_cs, or a chain)")
        if "T_cs" not in entry and name != REFERENCE:
            raise ValueError(
                f"{where}.T_cs: missing field (a static camera needs T_cs: the 4x4 from the reference static "
                "camera cam0 into it, metres)"
            )
        T_cs = nearest_rigid(validate.rigid_transform(entry["T_cs"], f"{where}.T_cs")) if "T_cs" in entry else None
        if name == REFERENCE and T_cs is not None and not np.allclose(T_cs, np.eye(4), rtol=0.0, atol=1e-12):
            raise ValueError(f"{where}.T_cs must be the identity (cam0 is the reference static camera s) or omitted")
        return CameraMount(name, None, T_cs=T_cs, camera=camera, rostopic=rostopic)
    if name == REFERENCE:
        raise ValueError(f"{where}.mount must be 'static': cam0 is the reference static camera s, got {mount!r}")
    if "T_cs" in entry:
        raise ValueError(f"{where}.T_cs: a camera on chain {mount} moves with it; give tau_d (end effector -> camera)")
    if "tau_d" not in entry:
        raise ValueError(f"{where}.tau_d: missing field (a camera on a chain needs tau_d: end effector -> camera)")
    tau_d = validate.numbers(entry["tau_d"], f"{where}.tau_d", 6, TAU_NAMES, form=TAU_FORM)
    warn_degrees(source, {f"cameras.{name}.tau_d": tau_d}, np.zeros((0, 3)))
    tau_d_std = None
    if entry.get("tau_d_std") is not None:
        tau_d_std = np.array(validate.numbers(entry["tau_d_std"], f"{where}.tau_d_std", 6, TAU_NAMES,
                                              allow_null=True, nonnegative=True), dtype=float)  # fmt: skip
    return CameraMount(name, mount, tau_d=np.array(tau_d), camera=camera, rostopic=rostopic, tau_d_std=tau_d_std)


class _UniqueKeyLoader(yaml.SafeLoader):
    """A SafeLoader refusing a mapping key given twice (PyYAML keeps the last one silently)."""


def _construct_unique(loader: yaml.SafeLoader, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
    seen: set[Any] = set()
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if isinstance(key, list | dict):
            continue
        if key in seen:
            raise ValueError(f"duplicate key {key!r} (line {key_node.start_mark.line + 1})")
        seen.add(key)
    return loader.construct_mapping(node, deep)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_unique)


def check_unique_keys(text: str, source: str) -> None:
    """ValueError naming ``source``, the line and the key where a YAML mapping gives a key twice."""
    try:
        yaml.load(text, Loader=_UniqueKeyLoader)  # a SafeLoader subclass: safe
    except ValueError as exc:
        raise ValueError(f"{source}: {exc}; every camera and chain name must be given once") from None


# ---------------------------------------------------------------------------------------- Kalibr


def cluster_from_camchain(
    camchain: str | Path | Mapping[str, CamchainEntry],
    chains: Sequence[ChainSpec],
    mounts: Mapping[str, tuple[str, ArrayLike]],
    source: str | None = None,
) -> CameraCluster:
    """A cluster from a Kalibr camchain (``cam0 .. camN-1``, ``T_cn_cnm1``) and the gimbal mounts.

    Static cameras get ``T_cs`` by chaining the camchain's ``T_cn_cnm1`` from cam0
    (:func:`dcc_fg.io.camchain.camchain_transforms`; with the gimbal held still while Kalibr calibrated, a
    chain through a gimbal camera is valid too); the cameras in ``mounts`` sit on a chain instead.

    Args:
        camchain: the camchain file, or its entries (:func:`dcc_fg.io.camchain.load_camchain`).
        chains: the gimbal chains (``tau_s``, ``dh``; e.g. hand-measured initial values).
        mounts: camera name -> (chain name, ``tau_d`` (6,): end effector -> camera, rad and m).
        source: the camchain's name in messages (default: the path).

    Raises:
        ValueError: naming the camchain: a mount for a camera not in it, an unknown chain, a chain
            without a camera, cam0 on a chain, a missing ``T_cn_cnm1`` on the path of a static camera.
    """
    if isinstance(camchain, Mapping):
        entries, where = dict(camchain), source or "<camchain>"
    else:
        entries, where = read_camchain(camchain), source or str(camchain)
    missing = [c for c in mounts if c not in entries]
    if missing:
        raise ValueError(f"{where}: gimbal camera(s) {', '.join(missing)} not in the camchain ({', '.join(entries)})")
    bad = [c for c in entries if not CAMERA_NAME.match(c)]
    if bad:
        raise ValueError(
            f"{where}: camera entries must be named cam0, cam1, ... (Kalibr's names), got {', '.join(bad)}"
        )
    transforms = camchain_transforms(entries, where, [c for c in entries if c not in mounts])
    cameras = []
    for name in sorted(entries, key=_camera_number):
        e = entries[name]
        if name in mounts:
            chain_name, tau_d = mounts[name]
            if name == REFERENCE:
                raise ValueError(f"{where}: cam0 is the reference static camera s; it cannot sit on chain {chain_name}")
            cameras.append(CameraMount(name, chain_name, tau_d=np.asarray(tau_d, dtype=float), camera=e.camera,
                                       rostopic=e.rostopic))  # fmt: skip
        else:
            T = None if name == REFERENCE else nearest_rigid(transforms[name])
            cameras.append(CameraMount(name, None, T_cs=T, camera=e.camera, rostopic=e.rostopic))
    check_structure(cameras, list(chains), where)
    return CameraCluster(tuple(cameras), tuple(chains))
