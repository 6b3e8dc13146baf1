"""The cameras of one VIO run: which cameras of a cluster it uses, and how each is mounted.

A run numbers its cameras:

* ``0``: cam0, the reference static camera s (its mount ``T_sI`` is the body frame's link to vision);
* ``1``: the primary gimbal camera d (:attr:`dcc_fg.cluster.CameraCluster.primary_gimbal_camera`), in
  ``scc`` / ``dcc`` mode; its chain's joint angles are the state the smoother estimates;
* ``2, 3, ...``: every further camera the run uses (:class:`RunCamera`), in cluster order.

A further camera is either *rigid* to the body (``T_cs`` constant: a static camera, a camera on a chain
without joints, or in ``scc`` mode any camera on the locked chain at the locked angles) or on a chain
with joints (``kin`` = its chain parameters ``[tau_s, tau_d, dh]`` of :mod:`factors.chain`): the primary
chain (``slot`` 0, sharing the primary camera's joint angles) or, in ``dcc``, a further chain (``slot``
1, 2, ... in cluster order, :func:`run_chains`), whose joint angles are a state of their own. ``scc``
locks the primary chain only: cameras on further chains with joints are left out (listed by
:func:`ignored_cameras`, for the log and the summary) and refused when asked for by name. ``mono`` mode
uses cam0 and the rigid cameras only (a static stereo pair is ``mono`` with two static cameras).

Frames: ``T_cs`` maps points of s into camera c (the paper's T^{c:s}); angles in rad.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from dcc_fg.cluster import CameraCluster
from dcc_fg.model import GimbalCalibration
from factors import chain
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]

#: Run index of cam0 (the reference static camera s) and of the primary gimbal camera d.
STATIC_INDEX = 0
GIMBAL_INDEX = 1
VIO_MODES = ("mono", "scc", "dcc")


def default_topic(name: str) -> str:
    """EuRoC / Kalibr's image topic of camera ``name``: ``/camN/image_raw``."""
    return f"/{name}/image_raw"


@dataclass(frozen=True, eq=False)
class RunCamera:
    """A further camera of a VIO run (run index >= 2).

    Attributes:
        index: run index (2, 3, ...).
        name: the cluster's camera name (``cam1``, ``cam2``, ...).
        model: intrinsics.
        topic: image topic in a bag.
        T_cs: rigid cameras: s -> c (4x4); None on a chain.
        kin: cameras on a chain with joints: ``[tau_s (6), tau_d (6), dh (3L)]``; None when rigid.
        n_joints: L of that chain (0 for a rigid camera).
        chain: the chain's name (None when rigid).
        slot: which joint-angle state the camera follows: 0 the primary chain's, 1, 2, ... further chains'
            (:func:`run_chains`).
    """

    index: int
    name: str
    model: CameraModel
    topic: str
    T_cs: FloatArray | None = None
    kin: FloatArray | None = None
    n_joints: int = 0
    chain: str | None = None
    slot: int = 0

    def __post_init__(self) -> None:
        if self.index < 2:
            raise ValueError(f"{self.name}: run indices 0 and 1 are cam0 and the primary gimbal camera")
        if (self.T_cs is None) == (self.kin is None):
            raise ValueError(f"{self.name}: a run camera is either rigid (T_cs) or on a chain (kin)")

    @property
    def on_gimbal(self) -> bool:
        """True when the camera moves with joint angles (of the chain in :attr:`slot`)."""
        return self.kin is not None

    def T_cs_at(self, theta: ArrayLike | None = None) -> FloatArray:
        """s -> this camera (4x4) at its chain's joint angles ``theta`` (rad; ignored when rigid)."""
        if self.kin is None:
            assert self.T_cs is not None
            return self.T_cs
        return chain.T_ds(self.kin, np.asarray(theta, float), self.n_joints)

    def T_cI(self, T_sI: FloatArray, theta: ArrayLike | None = None) -> FloatArray:
        """IMU/body I -> this camera (4x4) for the static mount ``T_sI`` and joint angles ``theta``."""
        return self.T_cs_at(theta) @ T_sI


def _rigid(cluster: CameraCluster, name: str, theta: FloatArray | None) -> FloatArray | None:
    """``T_cs`` of camera ``name`` if it is rigid to the body (static, an L = 0 chain, or locked at
    ``theta`` on the primary chain), else None."""
    mount = cluster.camera(name)
    if mount.is_static:
        return cluster.T_cs(name)
    assert mount.chain is not None
    ch = cluster.chain(mount.chain)
    if ch.n_joints == 0:
        return cluster.T_cs(name, {mount.chain: np.zeros(0)})
    primary = cluster.camera(cluster.primary_gimbal_camera).chain
    if theta is not None and mount.chain == primary:
        return cluster.T_cs(name, {mount.chain: theta})
    return None


def run_cameras(
    calibration: GimbalCalibration,
    mode: str,
    theta_fixed: ArrayLike | None = None,
    use: Sequence[str] | None = None,
) -> tuple[RunCamera, ...]:
    """The further cameras (run index >= 2) a run in ``mode`` uses, in cluster order.

    ``use``: camera names to use (None: every camera the mode can use). cam0 is always used; the
    primary gimbal camera is used in ``scc`` / ``dcc`` and is not listed here. ``theta_fixed``: the
    locked angles of ``scc`` mode (rad). Raises ValueError naming the camera: unknown or unusable names
    in ``use`` (a camera on a chain with joints in ``mono``, on a further chain in ``scc``) and a camera
    without intrinsics.
    """
    if mode not in VIO_MODES:
        raise ValueError(f"unknown VIO mode {mode!r} (modes: {', '.join(VIO_MODES)})")
    cluster = calibration.cluster()
    where = calibration.source or "the calibration"
    names = cluster.camera_names
    if use is not None:
        unknown = [n for n in use if n not in names]
        if unknown:
            raise ValueError(f"{where}: no camera {', '.join(unknown)} in the cluster (cameras: {', '.join(names)})")
    primary = cluster.primary_gimbal_camera
    primary_chain = cluster.camera(primary).chain
    theta = None if theta_fixed is None else np.asarray(theta_fixed, float).reshape(-1)
    chains = run_chains(calibration, mode, use)
    out: list[RunCamera] = []
    index = 2
    for name in names[1:]:
        if mode != "mono" and name == primary:
            continue
        wanted = use is None or name in use
        if not wanted:
            continue
        mount = cluster.camera(name)
        T_cs = _rigid(cluster, name, theta if mode == "scc" else None)
        kin = None
        if T_cs is None:
            if mode != "dcc":
                if use is None:
                    continue  # not usable in this mode: only an explicit request is an error
                why = (
                    "mono mode uses rigid cameras only (static, or on a chain without joints)"
                    if mode == "mono"
                    else f"it is on chain {mount.chain!r}, which scc does not lock (only {primary_chain!r})"
                )
                raise ValueError(f"{where}: camera {name} cannot be used in {mode} mode: {why}")
            kin = cluster.kin_of(name)
        if mount.camera is None:
            raise ValueError(f"{where}: cameras.{name}: no intrinsics (the VIO needs every camera's model)")
        out.append(
            RunCamera(
                index=index,
                name=name,
                model=mount.camera,
                topic=mount.rostopic or default_topic(name),
                T_cs=None if T_cs is None else np.asarray(T_cs, float),
                kin=kin,
                n_joints=cluster.chain(mount.chain).n_joints if kin is not None and mount.chain else 0,
                chain=mount.chain if kin is not None else None,
                slot=chains.index(mount.chain) if kin is not None and mount.chain in chains else 0,
            )
        )
        index += 1
    return tuple(out)


def run_chains(calibration: GimbalCalibration, mode: str, use: Sequence[str] | None = None) -> tuple[str, ...]:
    """The chains whose joint angles a run in ``mode`` estimates or holds, slot order: the primary chain
    first (``scc`` / ``dcc``), then in ``dcc`` every further chain with joints that carries a camera the
    run uses (``use``: the further cameras asked for, None: all)."""
    if mode == "mono":
        return ()
    cluster = calibration.cluster()
    primary = cluster.camera(cluster.primary_gimbal_camera).chain
    assert primary is not None
    out = [primary]
    if mode == "dcc":
        for mount in cluster.cameras:
            ch = mount.chain
            if ch is None or ch in out or cluster.chain(ch).n_joints == 0:
                continue
            if use is None or mount.name in use:
                out.append(ch)
    return tuple(out)


def ignored_cameras(calibration: GimbalCalibration, mode: str, used: Sequence[RunCamera]) -> list[str]:
    """Cameras of the cluster a run in ``mode`` leaves out (for the log and the summary)."""
    cluster = calibration.cluster()
    taken = {"cam0", *(c.name for c in used)}
    if mode != "mono":
        taken.add(cluster.primary_gimbal_camera)
    return [n for n in cluster.camera_names if n not in taken]
