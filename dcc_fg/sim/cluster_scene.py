"""Corner-level simulator of N-camera clusters: static cameras and cameras on gimbal chains.

Frames (docs/architecture.md): ``s`` = cam0, the reference static camera; ``T_cs`` maps points of s
into camera c; target t. Presets (:data:`PRESETS`):

* ``stereo+gimbal``: cam0 + cam1 a static stereo pair (baseline ~11 cm to the right), cam2 on a
  2-DOF gimbal (the pinned roll-pitch mechanism of :mod:`dcc_fg.sim.calibration_scene`) ~9 cm below
  between them;
* ``gimbal-pair``: cam0 static; cam1 and cam2 side by side (4 cm apart, e.g. visible + thermal,
  different intrinsics) on one 2-DOF gimbal;
* ``two-gimbals``: cam0 static; cam1 on gimbal ``gimbal`` (right), cam2 on gimbal ``gimbal2`` (left).

Geometry: the pinned layout with ``random_geometry=False``; with it, every chain's base rotation,
DH links and joint ranges are drawn like :func:`dcc_fg.sim.calibration_scene.random_mechanism`
(any joint-1 axis direction, random links and twists) and the camera positions (+-2 cm) and
orientations (+-4 deg) are jittered. Each chain camera looks along cam0's optical axis at the centre
of its chain's joint ranges.

Snapshots: joint angles on a jittered grid of each chain's ranges; per snapshot a board pose
0.6-1.3 m ahead, aimed at the cameras' common view with a lateral jitter; a camera sees the target
when every corner projects inside its image with a margin (the others do not observe it), and a draw
is kept when at least two rigid groups (each static camera, each chain) see the board, so that some
snapshots hold only a subset of the cameras. Zero-mean Gaussian pixel noise; initial values
perturbed (translations N(0, 3 cm), angles and joint guesses N(0, 10 deg)). Everything is seeded;
the ground truth travels along.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from numpy.typing import NDArray

from dcc_fg.cluster import CameraCluster, CameraMount, ChainSpec
from dcc_fg.cluster_data import ClusterDataset, ClusterSnapshot
from dcc_fg.data import Observation
from dcc_fg.io.detections import write_detection_table
from dcc_fg.io.outputs import plain, write_text_atomic
from dcc_fg.sim.calibration_scene import (
    DEG,
    default_cameras,
    grid_joint_samples,
    joint_ranges,
    random_mechanism,
    true_kinematics,
)
from dcc_fg.targets import TargetGeometry
from factors import chain
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]
PRESETS = ("stereo+gimbal", "gimbal-pair", "two-gimbals")
BOARD_TRIES = 4000


@dataclass(frozen=True)
class ClusterSceneConfig:
    """Parameters of a simulated cluster data set."""

    n_snapshots: int = 60
    pixel_sigma: float = 0.4
    init_translation_sigma: float = 0.03
    init_rotation_sigma: float = 10.0 * DEG
    init_joint_sigma: float = 10.0 * DEG
    distance_range: tuple[float, float] = (0.6, 1.3)
    lateral_jitter: float = 0.12
    board_tilt: float = 20.0 * DEG
    margin_px: float = 5.0
    random_geometry: bool = False
    target: TargetGeometry = field(default_factory=lambda: TargetGeometry.checkerboard(9, 7, 0.06))


@dataclass
class SimulatedCluster:
    """A simulated cluster data set with its ground truth.

    Attributes:
        data: the snapshots (``joints`` = true angles + N(0, init_joint_sigma) per chain).
        truth / initial: the true and the perturbed cluster (``initial``: hand-measured start).
        joints: chain -> (K, L) true joint angles (rad), every snapshot (also where unseen).
        T_st: (K, 4, 4) true target poses in s.
        ranges: chain -> (L, 2) joint ranges (rad).
        preset, seed, config: how it was made.
    """

    data: ClusterDataset
    truth: CameraCluster
    initial: CameraCluster
    joints: dict[str, FloatArray]
    T_st: FloatArray
    ranges: dict[str, FloatArray]
    preset: str
    seed: int
    config: ClusterSceneConfig


def _pose(R: FloatArray, centre_s: FloatArray) -> FloatArray:
    """T_cs of a camera with rotation R (= R_cs) and optical centre ``centre_s`` in s (m)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ centre_s
    return T


def _small_rotation(rng: np.random.Generator | None, deg: float, fixed: FloatArray) -> FloatArray:
    """Rz Ry Rx of the angles ``fixed`` (rad), plus random angles up to ``deg`` when ``rng`` is given."""
    a = np.asarray(fixed, float) + (0.0 if rng is None else rng.uniform(-deg, deg, size=3) * DEG)
    return chain.rot_z(a[2]) @ chain.rot_y(a[1]) @ chain.rot_x(a[0])


def _chain_for(
    rng: np.random.Generator | None, name: str, T_cs_mid: list[FloatArray]
) -> tuple[ChainSpec, list[FloatArray], FloatArray]:
    """A 2-DOF chain whose end effector puts cameras at ``T_cs_mid`` at the centre of its ranges:
    (chain, tau_d per camera, ranges (2, 2) rad). Pinned mechanism when ``rng`` is None."""
    if rng is None:
        cal = true_kinematics(2)
        tau_s, dh, ranges = cal.tau_s, cal.dh, joint_ranges(2)
    else:
        cal, ranges = random_mechanism(rng, 2)
        tau_s, dh = cal.tau_s, cal.dh
    mid = ranges.mean(axis=1)
    T_eb_s = chain.T_eb(dh, mid) @ chain.se3_from_tau(tau_s)  # s -> e at mid-range
    taus = [chain.tau_from_se3(T @ chain.inv_se3(T_eb_s)) for T in T_cs_mid]
    return ChainSpec(name, tau_s, dh), taus, ranges


def preset_cluster(preset: str, rng: np.random.Generator | None = None) -> tuple[CameraCluster, dict[str, FloatArray]]:
    """The true cluster of ``preset`` and its chains' joint ranges (rad); random geometry with ``rng``."""
    if preset not in PRESETS:
        raise ValueError(f"unknown cluster preset {preset!r} (presets: {', '.join(PRESETS)})")
    cam_s, cam_d = default_cameras()
    thermal = CameraModel((400.0, 401.0, 322.0, 238.0), "radtan", (-0.03, 0.004, 0.0002, -0.0001), (640, 480))

    def jit(v: FloatArray) -> FloatArray:
        return np.asarray(v, float) + (0.0 if rng is None else rng.uniform(-0.02, 0.02, size=3))

    if preset == "stereo+gimbal":
        T1 = _pose(_small_rotation(rng, 4.0, np.array([0.5, -1.0, 0.8]) * DEG), jit([0.11, 0.0, 0.0]))
        T2 = _pose(_small_rotation(rng, 4.0, np.array([1.0, -1.5, 2.0]) * DEG), jit([0.055, 0.09, 0.01]))
        ch, (tau2,), rng_g = _chain_for(rng, "gimbal", [T2])
        cams = (
            CameraMount("cam0", camera=cam_s),
            CameraMount("cam1", T_cs=T1, camera=cam_d),
            CameraMount("cam2", "gimbal", tau_d=tau2, camera=cam_d),
        )
        return CameraCluster(cams, (ch,)), {"gimbal": rng_g}
    if preset == "gimbal-pair":
        T1 = _pose(_small_rotation(rng, 4.0, np.array([1.0, -1.5, 2.0]) * DEG), jit([0.10, -0.005, 0.01]))
        T2 = _pose(_small_rotation(rng, 4.0, np.array([-1.0, 2.0, -1.0]) * DEG), jit([0.10, 0.035, 0.01]))
        ch, (tau1, tau2), rng_g = _chain_for(rng, "gimbal", [T1, T2])
        cams = (
            CameraMount("cam0", camera=cam_s),
            CameraMount("cam1", "gimbal", tau_d=tau1, camera=cam_d),
            CameraMount("cam2", "gimbal", tau_d=tau2, camera=thermal),
        )
        return CameraCluster(cams, (ch,)), {"gimbal": rng_g}
    T1 = _pose(_small_rotation(rng, 4.0, np.array([1.0, -1.5, 2.0]) * DEG), jit([0.10, -0.005, 0.01]))
    T2 = _pose(_small_rotation(rng, 4.0, np.array([-1.0, 1.0, -2.0]) * DEG), jit([-0.10, 0.005, 0.0]))
    ch1, (tau1,), r1 = _chain_for(rng, "gimbal", [T1])
    ch2, (tau2,), r2 = _chain_for(rng, "gimbal2", [T2])
    if rng is None:  # the pinned mechanism mirrored: its base on the other side
        ch2 = ChainSpec("gimbal2", ch2.tau_s + np.array([0, 0, 0, 0.20, 0, 0]), ch2.dh)
        mid = r2.mean(axis=1)
        tau2 = chain.tau_from_se3(T2 @ chain.inv_se3(chain.T_eb(ch2.dh, mid) @ ch2.T_bs()))
    cams = (
        CameraMount("cam0", camera=cam_s),
        CameraMount("cam1", "gimbal", tau_d=tau1, camera=cam_d),
        CameraMount("cam2", "gimbal2", tau_d=tau2, camera=thermal),
    )
    return CameraCluster(cams, (ch1, ch2)), {"gimbal": r1, "gimbal2": r2}


def _sees(camera: CameraModel, T_cs: FloatArray, p_s: FloatArray, margin: float) -> bool:
    p = p_s @ T_cs[:3, :3].T + T_cs[:3, 3]
    if not np.all(camera.in_front(p)):
        return False
    uv, _ = camera.project(p, jacobian=False)
    return bool(np.all(camera.in_image(uv, margin)))


def _groups(cluster: CameraCluster, cams: list[str]) -> int:
    return len({cluster.camera(c).chain or c for c in cams})


def perturb_cluster(cluster: CameraCluster, cfg: ClusterSceneConfig, rng: np.random.Generator) -> CameraCluster:
    """Initial values: every translation + N(0, sigma_t), every angle (Euler, twist) + N(0, sigma_r)."""
    st, sr = cfg.init_translation_sigma, cfg.init_rotation_sigma
    tau_noise = np.r_[np.full(3, sr), np.full(3, st)]
    cams = []
    for c in cluster.cameras:
        if c.chain is not None:
            assert c.tau_d is not None
            cams.append(CameraMount(c.name, c.chain, tau_d=c.tau_d + rng.normal(size=6) * tau_noise, camera=c.camera))
        elif c.name == "cam0":
            cams.append(c)
        else:
            assert c.T_cs is not None
            tau = chain.tau_from_se3(c.T_cs) + rng.normal(size=6) * tau_noise
            cams.append(CameraMount(c.name, T_cs=chain.se3_from_tau(tau), camera=c.camera))
    chains = []
    for ch in cluster.chains:
        dh_noise = np.tile([st, st, sr], (ch.n_joints, 1))
        chains.append(
            ChainSpec(
                ch.name, ch.tau_s + rng.normal(size=6) * tau_noise, ch.dh + rng.normal(size=ch.dh.shape) * dh_noise
            )
        )
    return CameraCluster(tuple(cams), tuple(chains))


def simulate_cluster(
    preset: str = "stereo+gimbal", seed: int = 0, config: ClusterSceneConfig | None = None
) -> SimulatedCluster:
    """A simulated data set of ``preset`` (module docstring), seeded."""
    cfg = config or ClusterSceneConfig()
    rng = np.random.default_rng(seed)
    truth, ranges = preset_cluster(preset, rng if cfg.random_geometry else None)
    K = cfg.n_snapshots
    joints = {ch: grid_joint_samples(K, ranges[ch], rng) for ch in truth.chain_names}
    pts = cfg.target.points
    centre_t = pts.mean(axis=0)
    names = truth.camera_names
    snaps, poses = [], []
    for k in range(K):
        theta = {ch: joints[ch][k] for ch in truth.chain_names}
        T = {c: truth.T_cs(c, theta) for c in names}
        centres = np.array([-T[c][:3, :3].T @ T[c][:3, 3] for c in names])
        axes = np.array([T[c][2, :3] for c in names])  # optical axes in s
        found = None
        for _ in range(BOARD_TRIES):
            dist = rng.uniform(*cfg.distance_range)
            aim = np.mean(centres + dist * axes, axis=0)
            aim[:2] += rng.normal(scale=cfg.lateral_jitter, size=2)
            tilt_axis = rng.normal(size=2)
            R_st = _axis_rotation(np.array([tilt_axis[0], tilt_axis[1], 0.0]), rng.uniform(0.0, cfg.board_tilt))
            R_st = R_st @ chain.rot_z(rng.uniform(-15.0, 15.0) * DEG)
            T_st = np.eye(4)
            T_st[:3, :3] = R_st
            T_st[:3, 3] = aim - R_st @ centre_t
            p_s = pts @ R_st.T + T_st[:3, 3]
            seen = [c for c in names if _sees(truth.camera(c).camera, T[c], p_s, cfg.margin_px)]  # type: ignore[arg-type]
            if _groups(truth, seen) >= 2:
                found = (T_st, p_s, seen)
                break
        if found is None:
            raise RuntimeError(f"{preset} seed {seed}: no board pose seen by two rigid groups at snapshot {k}")
        T_st, p_s, seen = found
        obs = {}
        for c in seen:
            cam = truth.camera(c).camera
            assert cam is not None
            p = p_s @ T[c][:3, :3].T + T[c][:3, 3]
            uv = cam.project(p, jacobian=False)[0] + rng.normal(scale=cfg.pixel_sigma, size=(len(pts), 2))
            obs[c] = Observation(np.arange(len(pts)), uv)
        guess = {ch: theta[ch] + rng.normal(scale=cfg.init_joint_sigma, size=theta[ch].shape) for ch in theta}
        snaps.append(ClusterSnapshot(1_000_000_000 + k * 100_000_000, obs, guess))
        poses.append(T_st)
    intr = {c.name: c.camera for c in truth.cameras if c.camera is not None}
    data = ClusterDataset(intr, pts, snaps, f"simulation({preset}, seed={seed})")
    initial = perturb_cluster(truth, cfg, rng)
    return SimulatedCluster(data, truth, initial, joints, np.array(poses), ranges, preset, seed, cfg)


def _axis_rotation(axis: FloatArray, angle: float) -> FloatArray:
    n = float(np.linalg.norm(axis))
    if n < 1e-12:
        return np.eye(3)
    Kx = chain.skew(axis / n)
    return np.eye(3) + np.sin(angle) * Kx + (1.0 - np.cos(angle)) * Kx @ Kx


# ------------------------------------------------------------------ writing a data set


@dataclass
class WrittenCluster:
    """The files :func:`write_cluster_dataset` wrote."""

    detections: Path
    cluster: Path
    target: Path
    ground_truth: Path


def write_cluster_dataset(out: str | Path, sim: SimulatedCluster) -> WrittenCluster:
    """Write a simulated cluster as files::

        OUT/detections/cam<k>/<ns>.csv  yac detection files, one per camera that sees the target
                                        (:func:`dcc_fg.cluster_data.read_cluster_detections` reads them)
        OUT/cluster.yaml                the perturbed initial cluster with intrinsics (cameras:/chains: form)
        OUT/target.yaml                 Kalibr target (an AprilGrid: the detection format holds tag ids)
        OUT/ground_truth.yaml           format, preset, seed, the true cluster, per snapshot the
                                        timestamp_ns, cameras, theta (chain -> rad), T_st (4x4, s <- t)

    Raises:
        ValueError: a target that is not an AprilGrid; an existing ``OUT/detections`` folder.
    """
    root = Path(out)
    target = sim.config.target
    if target.target_type != "aprilgrid":
        raise ValueError("a cluster detection folder needs an AprilGrid target (yac files hold tag ids)")
    det = root / "detections"
    if det.exists():
        raise ValueError(f"{det} exists; choose another output folder")
    grid = (target.rows, target.cols, target.tag_size, target.tag_spacing)
    for c in sim.truth.camera_names:
        (det / c).mkdir(parents=True)
    for s in sim.data.snapshots:
        for c, obs in s.observations.items():
            write_detection_table(det / c / f"{s.timestamp_ns}.csv", s.timestamp_ns, grid, obs.ids, obs.pixels,
                                  target.points[obs.ids])  # fmt: skip
    paths = WrittenCluster(det, root / "cluster.yaml", root / "target.yaml", root / "ground_truth.yaml")
    write_text_atomic(paths.cluster, yaml.safe_dump(sim.initial.to_dict(), sort_keys=False))
    write_text_atomic(paths.target, yaml.safe_dump(target.to_kalibr(), sort_keys=False))
    truth = {
        "format": "dcc-fg cluster ground truth 1",
        "preset": sim.preset,
        "seed": sim.seed,
        "pixel_sigma": sim.config.pixel_sigma,
        "cluster": sim.truth.to_dict(),
        "ranges": {ch: r.tolist() for ch, r in sim.ranges.items()},
        "snapshots": [
            {
                "timestamp_ns": int(s.timestamp_ns),
                "cameras": s.cameras,
                "theta": {ch: sim.joints[ch][i].tolist() for ch in sim.truth.chain_names},
                "T_st": sim.T_st[i].tolist(),
            }
            for i, s in enumerate(sim.data.snapshots)
        ],
    }
    write_text_atomic(paths.ground_truth, yaml.safe_dump(plain(truth), sort_keys=False))
    return paths
