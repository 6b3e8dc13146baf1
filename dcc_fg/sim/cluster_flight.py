"""N-camera clusters for simulated VIO flights, and their feature tracks (no images).

The flight simulator (:mod:`dcc_fg.sim.flight_bag`) flies a static camera cam0 and one 2-joint gimbal
camera (:func:`dcc_fg.sim.trajectory.flight_calibration`). A *flight cluster* adds cameras to that
rig while keeping its primary chain, the primary gimbal camera's mount and intrinsics and hence the
joint motion exactly, so a run with and a run without the extra camera see the same flight.
Presets (:data:`FLIGHT_PRESETS`):

* ``stereo+gimbal``: cam0 static (the flight's static camera); cam1 static, cam0's stereo partner
  ~11 cm to its right (along s's x axis), rotated by ~3 deg, with cam0's intrinsics; cam2 the
  flight's gimbal camera on chain ``gimbal`` (the primary gimbal camera, run index 1);
* ``gimbal-pair``: cam0 static; cam1 the flight's gimbal camera on chain ``gimbal``; cam2 on the same
  chain end, 4 cm beside cam1 (along cam1's x axis), rotated by ~3 deg, a thermal-like 640x480
  pinhole with a shorter focal length (fx ~ 400 px, wider view) and its own distortion;
* ``two-gimbals``: cam0 static; cam1 the flight's gimbal camera on chain ``gimbal`` (the primary
  chain); cam2 the thermal-like camera on a second gimbal ``gimbal2``: the same 2-joint mechanism
  with its base 20 cm to the left of the first one's (along -x of s), its camera rotated by a few
  degrees from where cam1 would sit, so at the mid angles (90, 0) deg it looks ahead like cam1 and
  overlaps cam0's view. Chain ``gimbal2`` moves on its own
  (:func:`~dcc_fg.sim.trajectory.chain_motion_variant` of the flight's joint motion,
  :func:`further_chain_motions`).

Every camera model is scaled by ``scale`` (:func:`scale_camera`), like the flight's two cameras.
:func:`load_flight_cluster` takes a preset name or a cluster calibration file (``cameras:`` /
``chains:``) instead.

Synthetic tracks of such a cluster: :func:`dcc_fg.sim.trajectory.simulate_camera_tracks` (every further
camera of a run, :class:`~dcc_fg.data.cameras.RunCamera`, observed as well, in ``TrackFrame.extra``; a
camera on a further chain at that chain's true angles, ``FlightTruth.extra_theta``).

Frames: ``s`` = cam0; ``T_cs`` maps points of s into camera c; ``e`` the gimbal's end effector.
Units: metres, radians, pixels.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from dcc_fg.cluster import LEGACY_CHAIN, CameraCluster, CameraMount, ChainSpec
from dcc_fg.data.cameras import RunCamera, ignored_cameras, run_cameras, run_chains
from dcc_fg.model import GimbalCalibration, load_calibration
from dcc_fg.sim.trajectory import DEG, JointMotion, chain_motion_variant
from dcc_fg.sim.trajectory import flight_calibration as two_camera_flight_calibration
from factors import chain
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]

#: The flight cluster presets of ``simulate flight --cluster``.
FLIGHT_PRESETS = ("stereo+gimbal", "gimbal-pair", "two-gimbals")
#: Number of joints of the flight's gimbal (its joint motion, :class:`dcc_fg.sim.trajectory.JointMotion`).
FLIGHT_JOINTS = 2

#: Stereo partner of cam0 (``stereo+gimbal``): its optical centre in s (m) and rotation (rx, ry, rz, rad).
STEREO_CENTRE_S = (0.11, 0.0, 0.0)
STEREO_ANGLES = (1.0 * DEG, -2.0 * DEG, 1.5 * DEG)
#: Second gimbal camera (``gimbal-pair``): its optical centre in the primary gimbal camera's frame (m)
#: and rotation relative to it (rx, ry, rz, rad).
PAIR_CENTRE_D = (0.04, 0.0, 0.0)
PAIR_ANGLES = (-1.0 * DEG, 2.0 * DEG, -1.5 * DEG)
#: The thermal-like camera of ``gimbal-pair`` at scale 1 (640x480, fx ~ 400 px).
#: Second gimbal (``two-gimbals``): its base's displacement from the first gimbal's base, in s (m), and
#: its camera's rotation relative to the first gimbal's camera mount (rx, ry, rz, rad).
GIMBAL2_NAME = "gimbal2"
GIMBAL2_OFFSET_S = (-0.20, 0.0, 0.0)
GIMBAL2_ANGLES = (1.0 * DEG, -2.0 * DEG, 1.0 * DEG)
THERMAL = CameraModel((400.0, 401.0, 322.0, 238.0), "radtan", (-0.03, 0.004, 0.0002, -0.0001), (640, 480))


def scale_camera(cam: CameraModel, scale: float) -> CameraModel:
    """The same lens at ``scale`` times the resolution (pixel centres at integer coordinates)."""
    if scale == 1.0:
        return cam
    fx, fy, cx, cy = cam.intrinsics
    w, h = cam.resolution
    return dataclasses.replace(
        cam,
        intrinsics=(fx * scale, fy * scale, (cx + 0.5) * scale - 0.5, (cy + 0.5) * scale - 0.5),
        resolution=(int(round(w * scale)), int(round(h * scale))),
    )


def _rigid(angles: Sequence[float], centre: Sequence[float]) -> FloatArray:
    """``T_ca`` (4x4) of a camera c with rotation ``R_ca = Rz Ry Rx`` of ``angles`` (rad) whose optical
    centre is ``centre`` (m) in frame a."""
    rx, ry, rz = angles
    R = chain.rot_z(rz) @ chain.rot_y(ry) @ chain.rot_x(rx)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ np.asarray(centre, float)
    return T


def flight_cluster(preset: str, scale: float = 1.0) -> GimbalCalibration:
    """The true cluster of flight preset ``preset`` (module docstring) with every camera model at
    ``scale`` times its resolution, as a :class:`GimbalCalibration` (``layout`` set).

    Its primary chain (``gimbal``: ``tau_s``, ``dh``) and primary gimbal camera (``tau_d``, intrinsics)
    are :func:`~dcc_fg.sim.trajectory.flight_calibration`'s, so ``T_ds(theta)`` is the two-camera
    flight's to the bit. ``two-gimbals`` adds the chain ``gimbal2`` (:data:`GIMBAL2_OFFSET_S`).
    """
    if preset not in FLIGHT_PRESETS:
        raise ValueError(f"unknown flight cluster preset {preset!r} (presets: {', '.join(FLIGHT_PRESETS)})")
    base = two_camera_flight_calibration()
    assert base.static_camera is not None and base.dynamic_camera is not None
    cam_s, cam_d = scale_camera(base.static_camera, scale), scale_camera(base.dynamic_camera, scale)
    gimbal = ChainSpec(LEGACY_CHAIN, base.tau_s, base.dh)
    static = CameraMount("cam0", camera=cam_s)
    if preset == "stereo+gimbal":
        stereo = CameraMount("cam1", T_cs=_rigid(STEREO_ANGLES, STEREO_CENTRE_S), camera=cam_s)
        primary = CameraMount("cam2", LEGACY_CHAIN, tau_d=base.tau_d, camera=cam_d)
        cameras = (static, stereo, primary)
    elif preset == "gimbal-pair":
        primary = CameraMount("cam1", LEGACY_CHAIN, tau_d=base.tau_d, camera=cam_d)
        T_ce = _rigid(PAIR_ANGLES, PAIR_CENTRE_D) @ base.T_de()  # e -> cam2 = (cam1 -> cam2) (e -> cam1)
        second = CameraMount("cam2", LEGACY_CHAIN, tau_d=chain.tau_from_se3(T_ce), camera=scale_camera(THERMAL, scale))
        cameras = (static, primary, second)
    else:
        primary = CameraMount("cam1", LEGACY_CHAIN, tau_d=base.tau_d, camera=cam_d)
        # base2 = base1 moved by the offset o in s: p_b2 = T_b1s (p_s - o)
        T_b2s = chain.se3_from_tau(base.tau_s) @ _rigid((0.0, 0.0, 0.0), GIMBAL2_OFFSET_S)
        gimbal2 = ChainSpec(GIMBAL2_NAME, chain.tau_from_se3(T_b2s), base.dh)
        T_ce = _rigid(GIMBAL2_ANGLES, (0.0, 0.0, 0.0)) @ base.T_de()  # rotated about its optical centre
        second = CameraMount("cam2", GIMBAL2_NAME, tau_d=chain.tau_from_se3(T_ce), camera=scale_camera(THERMAL, scale))
        return GimbalCalibration.from_cluster(CameraCluster((static, primary, second), (gimbal, gimbal2)))
    return GimbalCalibration.from_cluster(CameraCluster(cameras, (gimbal,)))


def check_flight_cluster(calibration: GimbalCalibration, n_joints: int = FLIGHT_JOINTS) -> tuple[RunCamera, ...]:
    """The further cameras (run index >= 2, :func:`~dcc_fg.data.cameras.run_cameras` in ``dcc`` mode)
    of a cluster the flight simulator can fly: every camera with intrinsics, a primary chain of
    ``n_joints`` joints (the flight's joint motion) and every further chain with joints that carries
    a camera of ``n_joints`` joints as well (each moves with a variant of that motion,
    :func:`further_chain_motions`). ValueError naming the calibration's source otherwise."""
    where = calibration.source or "the cluster"
    cluster = calibration.cluster()
    if calibration.n_joints != n_joints:
        raise ValueError(
            f"{where}: the primary chain {cluster.camera(cluster.primary_gimbal_camera).chain!r} has "
            f"{calibration.n_joints} joint(s); the flight's gimbal motion drives {n_joints}"
        )
    missing = [c.name for c in cluster.cameras if c.camera is None]
    if missing:
        raise ValueError(f"{where}: no intrinsics for {', '.join(missing)} (every camera of a flight is rendered)")
    extra = run_cameras(calibration, "dcc")
    left_out = ignored_cameras(calibration, "dcc", extra)
    if left_out:  # dcc uses every camera; kept as a guard should run_cameras change
        raise ValueError(f"{where}: {', '.join(left_out)} cannot be flown (not usable in a dcc run)")
    for name in run_chains(calibration, "dcc")[1:]:
        L = cluster.chain(name).n_joints
        if L != n_joints:
            raise ValueError(
                f"{where}: the second chain {name!r} ({', '.join(cluster.cameras_on(name))}) has {L} joint(s); "
                f"the flight's gimbal motion drives {n_joints} on every chain"
            )
    return extra


def further_chain_motions(calibration: GimbalCalibration, joints: JointMotion) -> dict[str, JointMotion]:
    """The joint motion of every further chain a flight of the cluster moves (chain name -> motion):
    the chains of slots 1, 2, ... of :func:`~dcc_fg.data.cameras.run_chains` in ``dcc`` mode, slot k
    moving with :func:`~dcc_fg.sim.trajectory.chain_motion_variant` ``(joints, k)`` (its own sinusoids
    and slews; locked if ``joints`` is). Empty for a cluster with one chain with joints."""
    further = run_chains(calibration, "dcc")[1:]
    return {name: chain_motion_variant(joints, k) for k, name in enumerate(further, start=1)}


def load_flight_cluster(spec: str | Path, scale: float = 1.0) -> GimbalCalibration:
    """The cluster of ``simulate flight --cluster SPEC``: a preset name (:func:`flight_cluster`) or a
    cluster calibration YAML file (``cameras:`` / ``chains:``, read with
    :func:`~dcc_fg.model.load_calibration`) whose every camera has intrinsics (scaled by ``scale``),
    whose primary chain and every further chain with joints have the flight gimbal's 2 joints
    (:func:`check_flight_cluster`). The file's geometry is taken as it is: its chain cameras should
    look ahead near the flight's mid joint angles (90, 0) deg like the flight's gimbal camera."""
    text = str(spec)
    if text in FLIGHT_PRESETS:
        return flight_cluster(text, scale)
    path = Path(spec)
    if not path.is_file():
        raise ValueError(
            f"unknown flight cluster {text!r}: neither a preset ({', '.join(FLIGHT_PRESETS)}) nor a cluster "
            "calibration YAML file"
        )
    cal = load_calibration(path)
    if cal.layout is None:
        raise ValueError(f"{path}: a two-camera calibration; a flight cluster file has cameras: and chains:")
    check_flight_cluster(cal)
    cluster = cal.cluster()
    mounts = tuple(
        dataclasses.replace(m, camera=scale_camera(m.camera, scale)) if m.camera is not None else m
        for m in cluster.cameras
    )
    return GimbalCalibration.from_cluster(CameraCluster(mounts, cluster.chains), source=str(path))
