"""Encoderless calibration of a whole camera cluster in one factor graph (paper III-A/B, N cameras).

Frames (docs/architecture.md): ``s`` = the reference static camera cam0; ``T_ab`` maps points of b
into a; ``t`` the target. Unknowns of the graph (gtsam keys ``gtsam.symbol(char, index)``):

* ``x(i)``: the target pose ``T_st`` of snapshot i (Pose3, right perturbation ``T Exp([omega, v])``);
* ``e(n)``: ``T_cs`` of static camera ``cam<n>`` (n >= 1; Pose3): its extrinsics, as Kalibr's
  multi-camera calibration estimates them (but from the reference camera cam0, not the previous one);
* ``c(k)``: the free entries of chain k's ``[tau_s (6), d_1, a_1, alpha_1, ..., d_L, a_L, alpha_L]``
  (rad, m); the gauge-fixed entries are constants at their initial values;
* ``d(n)``: ``tau_d`` (6) of camera ``cam<n>`` on a chain: end effector e -> that camera;
* ``j(i * n_chains + k)``: the L joint angles of chain k in snapshot i (rad), for the snapshots in
  which a camera on chain k sees the target.

One factor per (snapshot, camera that sees the target), with analytic Jacobians: cam0 projects
``T_st p_t``; a static camera ``T_cs T_st p_t``; a camera c on chain k
``T_de(tau_d,c) inv(A_1 ... A_L) T_bs(tau_s) T_st p_t`` (:func:`factors.chain.transform_points`
with ``kin = [tau_s, tau_d,c, dh]``). Residuals are whitened by the pixel sigma (optionally a
per-corner robust loss, :class:`factors.calibration.RobustLoss`).

Gauge (per chain, the directions the images cannot see; :func:`gauge_of_chain`). A change of the
end-effector frame ``e -> e G`` (G constant) moves every ``tau_d`` of the chain's cameras together
and is invisible; with the DH form it shows as ``d_L, a_L, alpha_L`` and a constant offset of
``theta_L`` (``Rz(theta + delta) Tz(d) Tx(a) Rx(alpha) = A_L(theta) G``). Likewise a change of the
base frame ``b -> Rz(beta) Tz(h) b`` is absorbed by ``theta_1`` and ``d_1``, and shows as
``tau_s.rz``, ``tau_s.tz``. So each chain with L >= 1 has the same 6 gauge directions as the
two-camera problem however many cameras it carries (:func:`dcc_fg.calibration_graph.gauge_fixed_kin`,
mode ``encoderless``: ``tau_s.rz, tau_s.tz, d_L, a_L, alpha_L`` held, plus a prior on the mean of
``theta_L``); no ``tau_d`` is held: all of a chain's cameras absorb the end-frame change together,
once. A chain with L = 0 holds all of ``tau_s`` (only ``T_de T_bs`` of each camera is seen). The
static cameras' ``T_cs`` and the target poses have no gauge (cam0 is the reference). The test
suite checks that the information matrix of the *full* parameterization has exactly this many null
directions and the gauge-fixed one none.

A snapshot constrains the unknown links between the cameras that see the target: it is used when
they belong to at least two *rigid groups* (each static camera alone, each chain with its cameras);
other snapshots (one camera, or only cameras of one chain) are left out and counted.

Initial values: the target pose from PnP in the first static camera that sees it (through its
initial ``T_cs``); each static camera's ``T_cs`` from the mean of its PnP poses relative to the target
poses; each chain fitted at the pose level (:func:`dcc_fg.init.robust_pose_level_init`) to the PnP
``T_cs`` of its best-observed camera, its other cameras' ``tau_d`` in closed form (chains with L = 0:
every ``tau_d`` in closed form, :func:`dcc_fg.init.zero_joint_init`). Joint angles: the snapshot's
guesses, else inverse kinematics of the PnP ``T_cs``. With a cluster of cam0 and one camera cam1 on an
L = 0 chain this is exactly the two-camera ``calibrate`` with ``--joints 0``: same unknowns, same
start, same cost.

Uncertainty: the dense information matrix of the gauge-fixed graph at the solution (per-snapshot
blocks; small clusters), inverted and scaled by the a-posteriori variance factor; each camera's
``T_cs(theta_i)`` covariance (6x6, tangent ``[omega, v]``, right perturbation) by the chain rule
(:func:`factors.chain.d_T_ds_tangent`). Observability: the null space of the information of the
full parameterization with the per-snapshot unknowns eliminated (orthogonal projection per
snapshot, as :func:`dcc_fg.covariance.information_schur`).
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np
from numpy.typing import NDArray

from dcc_fg.calibration_graph import (
    GAUGE_SIGMA,
    gauge_fixed_joint_offsets,
    gauge_fixed_kin,
    gauge_reference_snapshots,
    solve_graph,
)
from dcc_fg.cluster import CameraCluster, CameraMount, ChainSpec
from dcc_fg.cluster_data import ClusterDataset
from dcc_fg.covariance import null_space, observable_mask
from dcc_fg.init import joint_angles_from_T_ds, mean_pose, pnp_pose, robust_pose_level_init
from dcc_fg.model import GimbalCalibration
from dcc_fg.util.errors import stage
from factors import chain
from factors.calibration import RobustLoss, mean_prior_factor, pose_point_jacobian
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]
REFERENCE = "cam0"
TAU = ("rx", "ry", "rz", "tx", "ty", "tz")
POSE = ("wx", "wy", "wz", "vx", "vy", "vz")
MIN_CORNERS = 4
# pose-level fit of each chain's start (as dcc_fg.calibrate)
POSE_LEVEL_REL_TOL = 1e-12
POSE_LEVEL_MAX_ITERATIONS = 200


# ------------------------------------------------------------------ the kinematic state


@dataclass
class ClusterKinematics:
    """Values of the cluster's constant unknowns.

    Attributes:
        mounts: camera -> chain name (None: static), every camera (cam0 static).
        chain_order: the chains, in the order of the flat joint-angle vector.
        tau_s: chain -> (6,) ``T_bs``: s -> chain base (rad, m).
        dh: chain -> (L, 3) DH rows ``[d, a, alpha]`` (m, m, rad).
        tau_d: chain camera -> (6,) ``T_ce``: end effector -> camera (rad, m).
        T_cs: static camera -> (4, 4) s -> camera (m); cam0 the identity.
    """

    mounts: dict[str, str | None]
    chain_order: list[str]
    tau_s: dict[str, FloatArray]
    dh: dict[str, FloatArray]
    tau_d: dict[str, FloatArray]
    T_cs: dict[str, FloatArray]

    @staticmethod
    def from_cluster(cluster: CameraCluster) -> ClusterKinematics:
        """The values of a :class:`~dcc_fg.cluster.CameraCluster`."""
        mounts = {c.name: c.chain for c in cluster.cameras}
        tau_d = {c.name: np.array(c.tau_d, dtype=float) for c in cluster.cameras if c.tau_d is not None}
        T_cs = {c.name: np.array(c.T_cs, dtype=float) for c in cluster.cameras if c.T_cs is not None}
        return ClusterKinematics(
            mounts,
            cluster.chain_names,
            {c.name: c.tau_s.copy() for c in cluster.chains},
            {c.name: c.dh.copy() for c in cluster.chains},
            tau_d,
            T_cs,
        )

    @staticmethod
    def static_pair(T_c1s: FloatArray | None = None) -> ClusterKinematics:
        """cam0 and a static cam1 with ``T_cs`` = ``T_c1s`` (identity when None): no chain (a stereo rig)."""
        T = np.eye(4) if T_c1s is None else np.asarray(T_c1s, dtype=float)
        return ClusterKinematics({"cam0": None, "cam1": None}, [], {}, {}, {}, {"cam0": np.eye(4), "cam1": T})

    def copy(self) -> ClusterKinematics:
        return ClusterKinematics(
            dict(self.mounts),
            list(self.chain_order),
            {k: v.copy() for k, v in self.tau_s.items()},
            {k: v.copy() for k, v in self.dh.items()},
            {k: v.copy() for k, v in self.tau_d.items()},
            {k: v.copy() for k, v in self.T_cs.items()},
        )

    @property
    def cameras(self) -> list[str]:
        return sorted(self.mounts, key=lambda c: int(c[3:]))

    def cameras_on(self, chain_name: str) -> list[str]:
        return [c for c in self.cameras if self.mounts[c] == chain_name]

    @property
    def static_unknown(self) -> list[str]:
        """The static cameras with unknown ``T_cs`` (all but cam0)."""
        return [c for c in self.cameras if self.mounts[c] is None and c != REFERENCE]

    def n_joints(self, chain_name: str) -> int:
        return int(self.dh[chain_name].shape[0])

    def kin_of(self, camera: str) -> FloatArray:
        """``[tau_s, tau_d, dh]`` (12 + 3L) of a chain camera (:mod:`factors.chain`)."""
        ch = self.mounts[camera]
        assert ch is not None
        return np.concatenate([self.tau_s[ch], self.tau_d[camera], self.dh[ch].ravel()])

    def T_cs_of(self, camera: str, theta: FloatArray | None = None) -> FloatArray:
        """s -> ``camera`` (4x4) at its chain's joint angles ``theta`` (L,) rad (static cameras ignore it)."""
        ch = self.mounts[camera]
        if ch is None:
            return self.T_cs.get(camera, np.eye(4)).copy()
        L = self.n_joints(ch)
        th = np.zeros(0) if theta is None else np.asarray(theta, dtype=float).reshape(L)
        return chain.T_ds(self.kin_of(camera), th, L)

    def to_cluster(self, intrinsics: Mapping[str, CameraModel] | None = None) -> CameraCluster:
        """As a :class:`~dcc_fg.cluster.CameraCluster` (needs at least one chain)."""
        cams = []
        for c in self.cameras:
            model = None if intrinsics is None else intrinsics.get(c)
            ch = self.mounts[c]
            if ch is None:
                cams.append(CameraMount(c, None, T_cs=None if c == REFERENCE else self.T_cs[c], camera=model))
            else:
                cams.append(CameraMount(c, ch, tau_d=self.tau_d[c], camera=model))
        chains = [ChainSpec(k, self.tau_s[k], self.dh[k]) for k in self.chain_order]
        return CameraCluster(tuple(cams), tuple(chains))


def gauge_of_chain(n_joints: int) -> tuple[NDArray[np.bool_], list[int]]:
    """(mask over the chain vector ``[tau_s (6), dh (3L)]`` of the entries held, joints whose mean
    angle is held): the two-camera encoderless gauge (module docstring); no ``tau_d`` is held."""
    kin_mask = gauge_fixed_kin(n_joints, "encoderless")
    assert not kin_mask[6:12].any()
    return np.concatenate([kin_mask[0:6], kin_mask[12:]]), gauge_fixed_joint_offsets(n_joints, "encoderless")


def chain_vector_names(name: str, n_joints: int) -> list[str]:
    """Names of the entries of a chain vector ``[tau_s, dh]``: ``gimbal.tau_s.rx`` ... ``gimbal.dh2.alpha``."""
    out = [f"{name}.tau_s.{c}" for c in TAU]
    for link in range(1, n_joints + 1):
        out += [f"{name}.dh{link}.d", f"{name}.dh{link}.a", f"{name}.dh{link}.alpha"]
    return out


# ------------------------------------------------------------------ options, problem, result


@dataclass(frozen=True)
class ClusterOptions:
    """Options of :func:`calibrate_cluster`.

    Attributes:
        pixel_sigma: corner noise (px, 1 sigma per axis); None estimates it (variance factor).
        robust / robust_k: None, ``huber`` or ``cauchy``, threshold in pixels.
        max_iterations: Levenberg-Marquardt iterations.
        compute_covariance: covariances and observability at the solution.
        pose_level_init: fit each chain to the PnP poses before the corner-level solve (off: start
            exactly at the given kinematics and the joint-angle guesses / IK).
    """

    pixel_sigma: float | None = None
    robust: str | None = None
    robust_k: float = 2.0
    max_iterations: int = 500
    compute_covariance: bool = True
    pose_level_init: bool = True

    def __post_init__(self) -> None:
        if self.pixel_sigma is not None and not (np.isfinite(self.pixel_sigma) and self.pixel_sigma > 0):
            raise ValueError(f"pixel_sigma must be a positive number of pixels, got {self.pixel_sigma}")
        if not (isinstance(self.max_iterations, int | np.integer) and self.max_iterations >= 1):
            raise ValueError(f"max_iterations must be an integer >= 1, got {self.max_iterations!r}")


@dataclass
class ClusterProblem:
    """What the graph is built from.

    Attributes:
        data: the used snapshots only (see :func:`usable_snapshots`).
        model0: initial values; the gauge-fixed entries stay at these.
        chain_free: chain -> mask over ``[tau_s, dh]`` of the estimated entries.
        offsets: chain -> joints (0-based) whose mean angle is held.
        has_theta: chain -> (K,) whether the chain's joint angles of snapshot i are unknowns.
        thetas0: chain -> (K, L) initial joint angles (rad; NaN rows where not unknowns).
        T_st0: (K, 4, 4) initial target poses in s.
        sigma: pixel sigma of the whitening; robust: the per-corner loss or None.
    """

    data: ClusterDataset
    model0: ClusterKinematics
    chain_free: dict[str, NDArray[np.bool_]]
    offsets: dict[str, list[int]]
    has_theta: dict[str, NDArray[np.bool_]]
    thetas0: dict[str, FloatArray]
    T_st0: FloatArray
    sigma: float = 1.0
    robust: RobustLoss | None = None

    @property
    def n_snapshots(self) -> int:
        return len(self.data.snapshots)

    @property
    def chains(self) -> list[str]:
        return self.model0.chain_order

    def chain_index(self, name: str) -> int:
        return self.chains.index(name)

    @property
    def n_gauge(self) -> int:
        """Directions the gauge rules fix: held chain entries and held mean joint angles."""
        return sum(int((~m).sum()) for m in self.chain_free.values()) + sum(len(o) for o in self.offsets.values())


@dataclass
class ClusterState:
    """A point of the unknowns: constant kinematics, joint angles chain -> (K, L) rad (NaN where not
    unknowns), target poses (K, 4, 4)."""

    model: ClusterKinematics
    thetas: dict[str, FloatArray]
    T_st: FloatArray


@dataclass
class ClusterCalibrationResult:
    """Everything :func:`calibrate_cluster` produces.

    Attributes:
        model: the estimated kinematics (static ``T_cs``, chains' ``tau_s``/``dh``, cameras' ``tau_d``).
        joint_angles: chain -> (K, L) estimated joint angles (rad), NaN where no camera of the chain
            saw the target; K = the used snapshots (``snapshot_index`` into the input data).
        joint_angle_std: chain -> (K, L) 1-sigma (rad).
        T_st: (K, 4, 4) target poses in s.
        snapshot_index: (K,) indices of the used snapshots in the input data.
        skipped_snapshots: indices of the input snapshots left out (one rigid group only).
        parameter_std: parameter name -> 1-sigma (rad or m; NaN where held by the gauge);
            names ``CHAIN.tau_s.rx``, ``CHAIN.dhL.alpha``, ``camN.tau_d.tx``, ``camN.T_cs.wx`` (static
            cameras: tangent of ``T_cs``, rad and m).
        observable: parameter name -> observable from the images (full parameterization's null space).
        gauge_fixed: the names of the held chain entries, and ``CHAIN.theta{l}.mean`` for held means.
        T_cs_covariances: camera -> (K, 6, 6) covariance of ``T_cs(theta_i)`` (tangent ``[omega, v]``,
            rad and m, right perturbation); NaN where the camera's chain has no angles in snapshot i.
        residuals: camera -> list over the snapshots it sees of ((n,) snapshot position, (N, 2) pixel
            residuals h(x) - z).
        null_space_dim / n_gauge: nullity of the full parameterization's information, and the number
            of directions the gauge rules fix (equal when the data determine everything else).
        iterations, initial_error, final_error, solve_time_s, variance_factor: solver report.
    """

    model: ClusterKinematics
    intrinsics: dict[str, CameraModel]
    joint_angles: dict[str, FloatArray]
    joint_angle_std: dict[str, FloatArray]
    T_st: FloatArray
    snapshot_index: NDArray[np.int64]
    skipped_snapshots: list[int]
    parameter_std: dict[str, float]
    observable: dict[str, bool]
    gauge_fixed: list[str]
    T_cs_covariances: dict[str, FloatArray] | None
    residuals: dict[str, list[tuple[int, FloatArray]]]
    null_space_dim: int
    n_gauge: int
    iterations: int
    initial_error: float
    final_error: float
    solve_time_s: float
    variance_factor: float
    extra: dict[str, Any] = field(default_factory=dict)

    def T_cs(self, camera: str, i: int) -> FloatArray:
        """Estimated s -> ``camera`` (4x4) in used snapshot i."""
        ch = self.model.mounts[camera]
        return self.model.T_cs_of(camera, None if ch is None else self.joint_angles[ch][i])

    def cluster(self) -> CameraCluster:
        """The result as a :class:`~dcc_fg.cluster.CameraCluster` with intrinsics (needs a chain)."""
        return self.model.to_cluster(self.intrinsics)

    def reprojection_rms(self) -> dict[str, float]:
        """Camera -> RMS pixel residual per axis, and ``all``."""
        out, every = {}, []
        for cam, blocks in self.residuals.items():
            r = np.concatenate([b for _, b in blocks]) if blocks else np.zeros((0, 2))
            every.append(r)
            out[cam] = float(np.sqrt(np.mean(r * r))) if r.size else float("nan")
        r = np.concatenate(every) if every else np.zeros((0, 2))
        out["all"] = float(np.sqrt(np.mean(r * r))) if r.size else float("nan")
        return out


# ------------------------------------------------------------------ input checks


def rigid_groups(model: ClusterKinematics, cameras: list[str]) -> set[str]:
    """The rigid groups of ``cameras``: each static camera by itself, each chain once."""
    return {model.mounts[c] or c for c in cameras}


def usable_snapshots(data: ClusterDataset, model: ClusterKinematics) -> tuple[list[int], list[int]]:
    """(used, skipped) snapshot indices: a snapshot is used when its cameras span >= 2 rigid groups."""
    used, skipped = [], []
    for i, s in enumerate(data.snapshots):
        (used if len(rigid_groups(model, s.cameras)) >= 2 else skipped).append(i)
    return used, skipped


def check_cluster_data(data: ClusterDataset, model: ClusterKinematics) -> tuple[list[int], list[int]]:
    """ValueError naming the problem for input the solver cannot use; returns :func:`usable_snapshots`."""
    src = data.source
    missing = [c for c in model.cameras if c not in data.cameras]
    if missing:
        raise ValueError(f"{src}: no intrinsics for camera(s) {', '.join(missing)} of the cluster")
    n_pts = data.target_points.shape[0]
    for i, s in enumerate(data.snapshots):
        tag = f"{src}: snapshot {i} (t={s.timestamp_ns} ns)"
        for cam, obs in s.observations.items():
            if cam not in model.mounts:
                raise ValueError(f"{tag}: camera {cam} is not in the cluster ({', '.join(model.cameras)})")
            if len(obs) < MIN_CORNERS:
                raise ValueError(f"{tag}: only {len(obs)} corners in camera {cam} (need >= {MIN_CORNERS})")
            if not np.all(np.isfinite(obs.pixels)):
                raise ValueError(f"{tag}: NaN or infinite pixel coordinates in camera {cam}")
            if obs.ids.min() < 0 or obs.ids.max() >= n_pts:
                raise ValueError(f"{tag}: corner ids outside the target's 0..{n_pts - 1} in camera {cam}")
    used, skipped = usable_snapshots(data, model)
    if not used:
        raise ValueError(
            f"{src}: no snapshot links two rigid groups of the cluster (each needs cameras on both sides of an "
            "unknown link: two static cameras, or a static camera and a chain camera, or cameras on two chains)"
        )
    seen = {c for i in used for c in data.snapshots[i].cameras}
    unseen = [c for c in model.cameras if c != REFERENCE and c not in seen]
    if unseen:
        raise ValueError(
            f"{src}: camera(s) {', '.join(unseen)} never see the target together with a camera of another rigid "
            "group: their extrinsics are undetermined"
        )
    for ch in model.chain_order:
        L = model.n_joints(ch)
        n_obs = sum(any(model.mounts[c] == ch for c in data.snapshots[i].cameras) for i in used)
        fixed, offsets = gauge_of_chain(L)
        n_unknown = int((~fixed).sum()) + 6 * len(model.cameras_on(ch)) - len(offsets)
        if L >= 6:
            raise ValueError(f"chain {ch}: encoderless calibration of L={L} joints is not possible (at most 5)")
        need = int(np.ceil(n_unknown / (6 - L)))
        if n_obs < need:
            raise ValueError(
                f"{src}: chain {ch} (L={L}) is seen in {n_obs} usable snapshots; its unknowns need at least {need}"
            )
    return used, skipped


# ------------------------------------------------------------------ residuals


@dataclass(frozen=True)
class CameraTerm:
    """The corners of one camera in one snapshot: target points (N, 3) in t and pixels (N, 2)."""

    snapshot: int
    camera: str
    p_t: FloatArray
    z: FloatArray


def terms_of(data: ClusterDataset) -> list[CameraTerm]:
    """Every (snapshot, camera) pair with its corners, in snapshot then camera order."""
    P = data.target_points
    return [
        CameraTerm(i, c, P[s.observations[c].ids], s.observations[c].pixels)
        for i, s in enumerate(data.snapshots)
        for c in s.cameras
    ]


def term_residual(
    model: ClusterKinematics,
    camera_model: CameraModel,
    term: CameraTerm,
    theta: FloatArray | None,
    T_st: FloatArray,
    jacobians: bool,
) -> tuple[FloatArray, dict[str, FloatArray]]:
    """Pixel residual ``h(x) - z`` (N, 2) of one camera's corners and its Jacobians (N, 2, width) by
    block: ``X`` (target pose, 6), ``E`` (static ``T_cs``, 6), ``C`` (the *full* chain vector
    ``[tau_s, dh]``, 6 + 3L), ``D`` (``tau_d``, 6), ``J`` (joint angles, L)."""
    R_st, t_st = T_st[:3, :3], T_st[:3, 3]
    p_s = term.p_t @ R_st.T + t_st
    ch = model.mounts[term.camera]
    blocks: dict[str, FloatArray] = {}
    if ch is None:
        T_cs = model.T_cs.get(term.camera, np.eye(4))
        p_c = p_s @ T_cs[:3, :3].T + T_cs[:3, 3]
        uv, Jp = camera_model.project(p_c, jacobian=jacobians)
        if jacobians:
            assert Jp is not None
            blocks["X"] = np.einsum("nij,jk,nkl->nil", Jp, T_cs[:3, :3], pose_point_jacobian(R_st, term.p_t))
            if term.camera != REFERENCE:
                blocks["E"] = np.einsum("nij,njk->nik", Jp, pose_point_jacobian(T_cs[:3, :3], p_s))
        return uv - term.z, blocks
    L = model.n_joints(ch)
    th = np.zeros(0) if theta is None else theta
    p_c, Jc = chain.transform_points(model.kin_of(term.camera), th, p_s, L, jacobians=jacobians)
    uv, Jp = camera_model.project(p_c, jacobian=jacobians)
    if jacobians:
        assert Jc is not None and Jp is not None
        cols = np.r_[0:6, 12 : 12 + 3 * L]
        blocks["X"] = np.einsum("nij,jk,nkl->nil", Jp, Jc.d_point, pose_point_jacobian(R_st, term.p_t))
        blocks["C"] = np.einsum("nij,njk->nik", Jp, Jc.d_kin[:, :, cols])
        blocks["D"] = np.einsum("nij,njk->nik", Jp, Jc.d_kin[:, :, 6:12])
        blocks["J"] = np.einsum("nij,njk->nik", Jp, Jc.d_theta)
    return uv - term.z, blocks


# ------------------------------------------------------------------ keys and variables


def camera_number(name: str) -> int:
    return int(name[3:])


class Keys:
    """The gtsam keys of a problem's unknowns (module docstring)."""

    def __init__(self, problem: ClusterProblem) -> None:
        self.problem = problem
        self.n_chains = len(problem.chains)

    @staticmethod
    def X(i: int) -> int:
        return int(gtsam.symbol("x", i))

    @staticmethod
    def E(camera: str) -> int:
        return int(gtsam.symbol("e", camera_number(camera)))

    @staticmethod
    def D(camera: str) -> int:
        return int(gtsam.symbol("d", camera_number(camera)))

    def C(self, chain_name: str) -> int | None:
        """The chain vector's key, None when every entry is held (an L = 0 chain)."""
        if not self.problem.chain_free[chain_name].any():
            return None
        return int(gtsam.symbol("c", self.problem.chain_index(chain_name)))

    def J(self, i: int, chain_name: str) -> int:
        return int(gtsam.symbol("j", i * max(self.n_chains, 1) + self.problem.chain_index(chain_name)))


def model_from_values(problem: ClusterProblem, keys: Keys, values: gtsam.Values) -> ClusterKinematics:
    """The kinematics held in ``values`` (held entries from ``problem.model0``)."""
    m = problem.model0.copy()
    for ch in problem.chains:
        k = keys.C(ch)
        if k is not None:
            vec = np.concatenate([m.tau_s[ch], m.dh[ch].ravel()])
            vec[problem.chain_free[ch]] = values.atVector(k)
            m.tau_s[ch], m.dh[ch] = vec[:6], vec[6:].reshape(-1, 3)
    for c in m.cameras:
        if m.mounts[c] is not None:
            m.tau_d[c] = values.atVector(keys.D(c))
        elif c != REFERENCE:
            m.T_cs[c] = values.atPose3(keys.E(c)).matrix()
    return m


def initial_values(problem: ClusterProblem, keys: Keys, state: ClusterState) -> gtsam.Values:
    """gtsam values of ``state``."""
    values = gtsam.Values()
    m = state.model
    for ch in problem.chains:
        k = keys.C(ch)
        if k is not None:
            values.insert(k, np.concatenate([m.tau_s[ch], m.dh[ch].ravel()])[problem.chain_free[ch]])
        for i in np.flatnonzero(problem.has_theta[ch]):
            if m.n_joints(ch):
                values.insert(keys.J(int(i), ch), state.thetas[ch][i].copy())
    for c in m.cameras:
        if m.mounts[c] is not None:
            values.insert(keys.D(c), m.tau_d[c].copy())
        elif c != REFERENCE:
            values.insert(keys.E(c), gtsam.Pose3(m.T_cs[c]))
    for i in range(problem.n_snapshots):
        values.insert(keys.X(i), gtsam.Pose3(state.T_st[i]))
    return values


def term_keys(problem: ClusterProblem, keys: Keys, term: CameraTerm) -> list[tuple[str, int]]:
    """(block name, key) of the unknowns one camera term depends on, in factor order."""
    out = [("X", keys.X(term.snapshot))]
    ch = problem.model0.mounts[term.camera]
    if ch is None:
        if term.camera != REFERENCE:
            out.append(("E", keys.E(term.camera)))
        return out
    k = keys.C(ch)
    if k is not None:
        out.append(("C", k))
    out.append(("D", keys.D(term.camera)))
    if problem.model0.n_joints(ch):
        out.append(("J", keys.J(term.snapshot, ch)))
    return out


def whiten(
    r: FloatArray, Js: list[FloatArray], sigma: float, robust: RobustLoss | None
) -> tuple[FloatArray, list[FloatArray]]:
    """Whitened (and robustified) residual (N, 2) and Jacobian blocks (N, 2, w)."""
    r = r / sigma
    Js = [J / sigma for J in Js]
    if robust is None:
        return r, Js
    if not Js:
        return robust.scale(r)[:, None] * r, Js
    widths = [J.shape[2] for J in Js]
    r, J_all = robust.apply(r, np.concatenate(Js, axis=2))
    return r, np.split(J_all, np.cumsum(widths)[:-1], axis=2)


def term_factor(problem: ClusterProblem, keys: Keys, term: CameraTerm) -> gtsam.CustomFactor:
    """The reprojection factor of one camera's corners in one snapshot (unit noise; whitened inside)."""
    named = term_keys(problem, keys, term)
    cam = problem.data.cameras[term.camera]
    ch = problem.model0.mounts[term.camera]
    free = problem.chain_free[ch] if ch is not None else None

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[FloatArray] | None) -> FloatArray:
        m = model_from_values(problem, keys, values)
        theta = None
        if ch is not None and m.n_joints(ch):
            theta = values.atVector(keys.J(term.snapshot, ch))
        T_st = values.atPose3(keys.X(term.snapshot)).matrix()
        r, blocks = term_residual(m, cam, term, theta, T_st, H is not None)
        Js = []
        if H is not None:
            for name, _ in named:
                J = blocks[name]
                Js.append(J[:, :, free] if name == "C" else J)
        r, Js = whiten(r, Js, problem.sigma, problem.robust)
        if H is not None:
            for k, J in enumerate(Js):
                H[k] = J.reshape(-1, J.shape[2])
        return r.reshape(-1)

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(2 * term.p_t.shape[0]), [k for _, k in named], error)


def build_graph(problem: ClusterProblem, state: ClusterState) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """The graph (a factor per camera term, the mean priors of the gauge) and its values at ``state``."""
    keys = Keys(problem)
    graph = gtsam.NonlinearFactorGraph()
    for term in terms_of(problem.data):
        graph.add(term_factor(problem, keys, term))
    for ch in problem.chains:
        idx = np.flatnonzero(problem.has_theta[ch])
        ref = idx[gauge_reference_snapshots(len(idx))]
        for j in problem.offsets[ch]:
            mean = float(problem.thetas0[ch][ref, j].mean())
            graph.add(mean_prior_factor([keys.J(int(i), ch) for i in ref], j, mean, GAUGE_SIGMA))
    return graph, initial_values(problem, keys, state)


# ------------------------------------------------------------------ initial values


def _T_ct(data: ClusterDataset, i: int, camera: str) -> FloatArray:
    s = data.snapshots[i]
    obs = s.observations[camera]
    return pnp_pose(data.cameras[camera], data.target_points[obs.ids], obs.pixels)


def initial_state(
    data: ClusterDataset, initial: ClusterKinematics, pose_level: bool = True
) -> tuple[ClusterKinematics, dict[str, FloatArray], FloatArray, dict[str, FloatArray]]:
    """(kinematics, joint angles chain -> (K, L) rad, target poses (K, 4, 4), joint-angle guesses) to
    start the graph from: PnP, static extrinsics from mean relative poses, chains fitted at the pose
    level (module docstring)."""
    model = initial.copy()
    K = len(data.snapshots)
    pnp: dict[tuple[int, str], FloatArray] = {}
    with stage("PnP", hint="check the camera intrinsics and the target description"):
        for i, s in enumerate(data.snapshots):
            for c in s.cameras:
                pnp[(i, c)] = _T_ct(data, i, c)
    # target poses: through the first static camera seeing it (initial T_cs), cam0 first
    T_st = np.zeros((K, 4, 4))
    anchored = np.zeros(K, dtype=bool)
    for i, s in enumerate(data.snapshots):
        stat = [c for c in s.cameras if model.mounts[c] is None]
        if REFERENCE in stat:
            T_st[i], anchored[i] = pnp[(i, REFERENCE)], True
    # static cameras: mean of T_ct inv(T_st) over the snapshots cam0 anchors; then anchor the rest
    for c in model.static_unknown:
        rel = [pnp[(i, c)] @ chain.inv_se3(T_st[i]) for i in range(K) if anchored[i] and (i, c) in pnp]
        if rel:
            model.T_cs[c] = mean_pose(np.array(rel))
    for i, s in enumerate(data.snapshots):
        if anchored[i]:
            continue
        stat = [c for c in s.cameras if model.mounts[c] is None]
        if stat:
            T_st[i], anchored[i] = chain.inv_se3(model.T_cs[stat[0]]) @ pnp[(i, stat[0])], True
    guesses: dict[str, FloatArray] = {}
    thetas: dict[str, FloatArray] = {}
    for ch in model.chain_order:
        L = model.n_joints(ch)
        guess = np.full((K, L), np.nan)
        for i, s in enumerate(data.snapshots):
            if s.joints is not None and ch in s.joints:
                guess[i] = np.asarray(s.joints[ch], dtype=float).reshape(L)
        guesses[ch] = guess
    # chains seen in anchored snapshots
    for ch in model.chain_order:
        thetas[ch] = _init_chain(data, model, ch, pnp, T_st, anchored, guesses[ch], pose_level)
    # snapshots without a static camera: through a chain camera at its guessed angles, else at the
    # median of its angles in the anchored snapshots (the other chains' angles then by IK)
    for i, s in enumerate(data.snapshots):
        if anchored[i]:
            continue
        c = next(c for c in s.cameras if model.mounts[c] is not None)
        ch = model.mounts[c]
        assert ch is not None
        th = guesses[ch][i]
        if not np.all(np.isfinite(th)):
            known = thetas[ch][np.all(np.isfinite(thetas[ch]), axis=1)]
            th = np.median(known, axis=0) if len(known) else np.zeros(model.n_joints(ch))
        thetas[ch][i] = th
        T_st[i] = chain.inv_se3(model.T_cs_of(c, th)) @ pnp[(i, c)]
        anchored[i] = True
        for c2 in s.cameras:
            ch2 = model.mounts[c2]
            if ch2 is not None and ch2 != ch and model.n_joints(ch2):
                cal = GimbalCalibration(model.kin_of(c2), model.n_joints(ch2))
                known = thetas[ch2][np.all(np.isfinite(thetas[ch2]), axis=1)]
                g = guesses[ch2][i] if np.all(np.isfinite(guesses[ch2][i])) else None
                if g is None and len(known):
                    g = np.median(known, axis=0)
                thetas[ch2][i] = joint_angles_from_T_ds(cal, pnp[(i, c2)] @ chain.inv_se3(T_st[i]), g)
    return model, thetas, T_st, guesses


def _init_chain(
    data: ClusterDataset,
    model: ClusterKinematics,
    ch: str,
    pnp: dict[tuple[int, str], FloatArray],
    T_st: FloatArray,
    anchored: NDArray[np.bool_],
    guess: FloatArray,
    pose_level: bool,
) -> FloatArray:
    """Joint angles (K, L) of chain ``ch`` (NaN where none of its cameras sees the target) and, in
    place, its kinematics fitted to the PnP ``T_cs`` of its cameras in the anchored snapshots."""
    K, L = len(data.snapshots), model.n_joints(ch)
    cams = model.cameras_on(ch)
    seen = {c: [i for i in range(K) if anchored[i] and (i, c) in pnp] for c in cams}
    T_cs = {c: {i: pnp[(i, c)] @ chain.inv_se3(T_st[i]) for i in seen[c]} for c in cams}
    thetas = np.full((K, L), np.nan)
    if L == 0:
        for c in cams:
            if seen[c]:
                T_de = mean_pose(np.array(list(T_cs[c].values()))) @ chain.inv_se3(chain.se3_from_tau(model.tau_s[ch]))
                model.tau_d[c] = chain.tau_from_se3(T_de)
        return np.zeros((K, 0))
    primary = max(cams, key=lambda c: len(seen[c]))
    idx = seen[primary]
    cal = GimbalCalibration(model.kin_of(primary), L)
    th0 = np.array([
        guess[i] if np.all(np.isfinite(guess[i])) else joint_angles_from_T_ds(cal, T_cs[primary][i], None) for i in idx
    ]).reshape(len(idx), L)  # fmt: skip
    kin = model.kin_of(primary)
    if pose_level and idx:
        fixed = gauge_fixed_kin(L, "encoderless")
        offsets = gauge_fixed_joint_offsets(L, "encoderless")
        with stage(
            "pose-level initialization", hint="check the initial kinematics or use the automatic initialization"
        ):
            kin, th0, _ = robust_pose_level_init(
                kin, L, np.array([T_cs[primary][i] for i in idx]), th0, ~fixed, offsets, True,
                rel_tol=POSE_LEVEL_REL_TOL, max_iterations=POSE_LEVEL_MAX_ITERATIONS,
            )  # fmt: skip
    model.tau_s[ch], model.tau_d[primary], model.dh[ch] = kin[0:6], kin[6:12], kin[12:].reshape(L, 3)
    thetas[idx] = th0
    # the other cameras: tau_d in closed form from the snapshots they share with the primary (at its
    # fitted joint angles), then joint angles by IK where the primary does not see the target
    T_bs = chain.se3_from_tau(model.tau_s[ch])
    for c in cams:
        if c == primary:
            continue
        T_de = [T_cs[c][i] @ chain.inv_se3(chain.T_eb(model.dh[ch], thetas[i]) @ T_bs) for i in seen[c] if i in idx]
        if T_de:
            model.tau_d[c] = chain.tau_from_se3(mean_pose(np.array(T_de)))
        for i in [i for i in seen[c] if not np.all(np.isfinite(thetas[i]))]:
            g = guess[i] if np.all(np.isfinite(guess[i])) else None
            if g is None and len(idx):
                g = np.median(thetas[idx], axis=0)
            thetas[i] = joint_angles_from_T_ds(GimbalCalibration(model.kin_of(c), L), T_cs[c][i], g)
    return thetas


def make_problem(
    data: ClusterDataset, initial: ClusterKinematics, opt: ClusterOptions
) -> tuple[ClusterProblem, ClusterState, list[int], list[int]]:
    """Checks, the used snapshots, initial values and the gauge: (problem, start state, used, skipped)."""
    used, skipped = check_cluster_data(data, initial)
    sub = ClusterDataset(dict(data.cameras), data.target_points, [data.snapshots[i] for i in used], data.source)
    model, thetas, T_st, _ = initial_state(sub, initial, opt.pose_level_init)
    K = len(used)
    chain_free, offsets, has_theta = {}, {}, {}
    for ch in model.chain_order:
        fixed, offs = gauge_of_chain(model.n_joints(ch))
        chain_free[ch], offsets[ch] = ~fixed, offs
        has_theta[ch] = np.array([any(model.mounts[c] == ch for c in s.cameras) for s in sub.snapshots], dtype=bool)
        if model.n_joints(ch) == 0:
            thetas[ch] = np.zeros((K, 0))
    sigma = opt.pixel_sigma if opt.pixel_sigma is not None else 1.0
    robust = RobustLoss(opt.robust, opt.robust_k / sigma) if opt.robust else None
    problem = ClusterProblem(sub, model, chain_free, offsets, has_theta, thetas, T_st, sigma, robust)
    return problem, ClusterState(model.copy(), {k: v.copy() for k, v in thetas.items()}, T_st.copy()), used, skipped


# ------------------------------------------------------------------ dense information


class Columns:
    """Column layout of the dense information matrix: global unknowns (chain vectors, ``tau_d``,
    static ``T_cs``) first, then per snapshot its joint angles and target pose.

    ``full``: every chain entry is a column (no gauge), else only the free ones.
    """

    def __init__(self, problem: ClusterProblem, full: bool) -> None:
        self.problem, self.full = problem, full
        self.names: list[str] = []
        self.block: dict[tuple[str, str], NDArray[np.int64]] = {}
        m = problem.model0
        for ch in problem.chains:
            names = chain_vector_names(ch, m.n_joints(ch))
            mask = np.ones(len(names), dtype=bool) if full else problem.chain_free[ch]
            self._add(("C", ch), [n for n, k in zip(names, mask, strict=True) if k])
        for c in m.cameras:
            if m.mounts[c] is not None:
                self._add(("D", c), [f"{c}.tau_d.{t}" for t in TAU])
            elif c != REFERENCE:
                self._add(("E", c), [f"{c}.T_cs.{t}" for t in POSE])
        self.n_global = len(self.names)
        for i in range(problem.n_snapshots):
            for ch in problem.chains:
                L = m.n_joints(ch)
                if problem.has_theta[ch][i] and L:
                    self._add(("J", f"{i}:{ch}"), [f"theta[{i}].{ch}.{j + 1}" for j in range(L)])
            self._add(("X", str(i)), [f"T_st[{i}].{t}" for t in POSE])

    def _add(self, key: tuple[str, str], names: list[str]) -> None:
        self.block[key] = np.arange(len(self.names), len(self.names) + len(names))
        self.names += names

    @property
    def n(self) -> int:
        return len(self.names)

    def snapshot_columns(self, i: int) -> NDArray[np.int64]:
        cols = [self.block[("J", f"{i}:{ch}")] for ch in self.problem.chains if ("J", f"{i}:{ch}") in self.block]
        return np.concatenate([*cols, self.block[("X", str(i))]])


def snapshot_jacobians(
    problem: ClusterProblem, cols: Columns, state: ClusterState
) -> list[tuple[NDArray[np.int64], FloatArray]]:
    """Per snapshot, (columns, whitened Jacobian (rows, len(columns))) of all its camera terms (no
    robust loss): the columns are the global unknowns and the snapshot's own (the others are zero)."""
    out = []
    by_snapshot: dict[int, list[CameraTerm]] = {}
    for term in terms_of(problem.data):
        by_snapshot.setdefault(term.snapshot, []).append(term)
    m = state.model
    g = cols.n_global
    for i in range(problem.n_snapshots):
        idx = np.concatenate([np.arange(g), cols.snapshot_columns(i)])
        pos = np.full(cols.n, -1)
        pos[idx] = np.arange(idx.size)
        rows = []
        for term in by_snapshot.get(i, []):
            ch = m.mounts[term.camera]
            theta = state.thetas[ch][i] if ch is not None and m.n_joints(ch) else None
            r, blocks = term_residual(m, problem.data.cameras[term.camera], term, theta, state.T_st[i], True)
            Jb = np.zeros((r.size, idx.size))
            for name, J in blocks.items():
                if name == "C":
                    assert ch is not None
                    mask = np.ones(J.shape[2], dtype=bool) if cols.full else problem.chain_free[ch]
                    if mask.any():
                        Jb[:, pos[cols.block[("C", ch)]]] = J[:, :, mask].reshape(r.size, -1)
                    continue
                key = {"X": ("X", str(i)), "E": ("E", term.camera), "D": ("D", term.camera)}.get(name)
                if name == "J":
                    assert ch is not None
                    if J.shape[2] == 0:
                        continue
                    key = ("J", f"{i}:{ch}")
                assert key is not None
                Jb[:, pos[cols.block[key]]] = J.reshape(r.size, -1)
            rows.append(Jb / problem.sigma)
        out.append((idx, np.vstack(rows)))
    return out


def information(problem: ClusterProblem, state: ClusterState, full: bool) -> tuple[FloatArray, Columns]:
    """Dense information matrix ``J^T J`` of the whitened residuals at ``state`` (plus, when not
    ``full``, the gauge's mean priors) and its columns."""
    cols = Columns(problem, full)
    H = np.zeros((cols.n, cols.n))
    for idx, J in snapshot_jacobians(problem, cols, state):
        H[np.ix_(idx, idx)] += J.T @ J
    if not full:
        for ch in problem.chains:
            idx = np.flatnonzero(problem.has_theta[ch])
            ref = idx[gauge_reference_snapshots(len(idx))]
            for j in problem.offsets[ch]:
                row = np.zeros(cols.n)
                for i in ref:
                    row[cols.block[("J", f"{i}:{ch}")][j]] = 1.0 / (len(ref) * GAUGE_SIGMA)
                H += np.outer(row, row)
    return H, cols


def schur_global(problem: ClusterProblem, state: ClusterState) -> tuple[FloatArray, FloatArray, list[str]]:
    """Information of the *full* global unknowns (no gauge) with the per-snapshot unknowns eliminated
    (orthogonal projection per snapshot); returns (S, scale = sqrt of the diagonal before elimination,
    names)."""
    cols = Columns(problem, full=True)
    g = cols.n_global
    S = np.zeros((g, g))
    diag = np.zeros(g)
    for _, J in snapshot_jacobians(problem, cols, state):
        Jg, Jl = J[:, :g], J[:, g:]
        diag += np.sum(Jg * Jg, axis=0)
        Q, _ = np.linalg.qr(Jl)
        P = Jg - Q @ (Q.T @ Jg)
        S += P.T @ P
    return S, np.sqrt(diag), cols.names[:g]


# ------------------------------------------------------------------ solve


def state_from_values(problem: ClusterProblem, values: gtsam.Values) -> ClusterState:
    keys = Keys(problem)
    m = model_from_values(problem, keys, values)
    thetas = {}
    for ch in problem.chains:
        L = m.n_joints(ch)
        th = np.full((problem.n_snapshots, L), np.nan)
        if L:
            for i in np.flatnonzero(problem.has_theta[ch]):
                th[i] = values.atVector(keys.J(int(i), ch))
        thetas[ch] = th
    T_st = np.array([values.atPose3(keys.X(i)).matrix() for i in range(problem.n_snapshots)])
    return ClusterState(m, thetas, T_st)


def residuals_at(problem: ClusterProblem, state: ClusterState) -> dict[str, list[tuple[int, FloatArray]]]:
    """Camera -> [(snapshot, (N, 2) pixel residuals h(x) - z)] at ``state`` (unwhitened)."""
    out: dict[str, list[tuple[int, FloatArray]]] = {c: [] for c in state.model.cameras}
    for term in terms_of(problem.data):
        ch = state.model.mounts[term.camera]
        theta = state.thetas[ch][term.snapshot] if ch is not None and state.model.n_joints(ch) else None
        r, _ = term_residual(
            state.model, problem.data.cameras[term.camera], term, theta, state.T_st[term.snapshot], False
        )
        out[term.camera].append((term.snapshot, r))
    return out


def T_cs_jacobian(problem: ClusterProblem, cols: Columns, state: ClusterState, camera: str, i: int) -> FloatArray:
    """(6, n) Jacobian of ``T_cs(theta_i)`` (tangent, right perturbation) with respect to the columns."""
    G = np.zeros((6, cols.n))
    m = state.model
    ch = m.mounts[camera]
    if ch is None:
        if camera != REFERENCE:
            G[:, cols.block[("E", camera)]] = np.eye(6)
        return G
    L = m.n_joints(ch)
    th = state.thetas[ch][i] if L else np.zeros(0)
    J_kin, J_th = chain.d_T_ds_tangent(m.kin_of(camera), th, L)
    mask = np.ones(6 + 3 * L, dtype=bool) if cols.full else problem.chain_free[ch]
    J_chain = np.concatenate([J_kin[:, 0:6], J_kin[:, 12:]], axis=1)[:, mask]
    if mask.any():
        G[:, cols.block[("C", ch)]] = J_chain
    G[:, cols.block[("D", camera)]] = J_kin[:, 6:12]
    if L:
        G[:, cols.block[("J", f"{i}:{ch}")]] = J_th
    return G


def T_cs_covariances(
    problem: ClusterProblem, cols: Columns, state: ClusterState, C: FloatArray
) -> dict[str, FloatArray]:
    """Per camera, the (K, 6, 6) covariance of ``T_cs(theta_i)`` at every snapshot (NaN where the
    camera's chain has no joint angles in that snapshot), propagated from the covariance ``C`` of the
    parameters laid out by ``cols`` through :func:`T_cs_jacobian`."""
    out = {}
    for c in state.model.cameras:
        covs = np.full((problem.n_snapshots, 6, 6), np.nan)
        ch = state.model.mounts[c]
        for i in range(problem.n_snapshots):
            if ch is not None and not problem.has_theta[ch][i]:
                continue
            G = T_cs_jacobian(problem, cols, state, c, i)
            covs[i] = G @ C @ G.T
        out[c] = covs
    return out


def calibrate_cluster(
    data: ClusterDataset,
    initial: ClusterKinematics | CameraCluster,
    options: ClusterOptions | None = None,
) -> ClusterCalibrationResult:
    """Calibrate a whole camera cluster (encoderless) in one graph.

    Args:
        data: the snapshots (any subset of cameras each; snapshot ``joints`` are per-chain guesses).
        initial: initial kinematics (e.g. from :func:`dcc_fg.cluster_init.auto_initialize_cluster`, or
            hand-measured); the gauge-fixed entries keep these values (after the pose-level fit).
        options: :class:`ClusterOptions`.

    Raises:
        ValueError: unusable input (named): unknown cameras, too few corners, no snapshot linking two
            rigid groups, a camera never seen with another group, too few snapshots for a chain.
        dcc_fg.util.errors.EstimatorError: a numerical stage failed.
    """
    opt = options or ClusterOptions()
    model0 = ClusterKinematics.from_cluster(initial) if isinstance(initial, CameraCluster) else initial
    t0 = time.perf_counter()
    problem, start, used, skipped = make_problem(data, model0, opt)
    graph, values = build_graph(problem, start)
    solved = solve_graph(graph, values, opt.max_iterations)
    state = state_from_values(problem, solved.values)
    residuals = residuals_at(problem, state)
    n_obs = 2 * sum(r.shape[0] for blocks in residuals.values() for _, r in blocks)
    cols_fixed = Columns(problem, full=False)
    n_unknowns = cols_fixed.n - sum(len(o) for o in problem.offsets.values())
    ss = sum(float(np.sum(r * r)) for blocks in residuals.values() for _, r in blocks) / problem.sigma**2
    variance_factor = 1.0 if opt.pixel_sigma is not None else ss / max(n_obs - n_unknowns, 1)

    names_all: list[str] = []
    for ch in problem.chains:
        names_all += chain_vector_names(ch, problem.model0.n_joints(ch))
    gauge_fixed = [n for ch in problem.chains
                   for n, f in zip(chain_vector_names(ch, problem.model0.n_joints(ch)), problem.chain_free[ch],
                                   strict=True) if not f]  # fmt: skip
    gauge_fixed += [f"{ch}.theta{j + 1}.mean" for ch in problem.chains for j in problem.offsets[ch]]
    std: dict[str, float] = {n: float("nan") for n in gauge_fixed if not n.endswith(".mean")}
    observable: dict[str, bool] = {}
    T_cov: dict[str, FloatArray] | None = None
    theta_std = {ch: np.full_like(state.thetas[ch], np.nan) for ch in problem.chains}
    null_dim = -1
    if opt.compute_covariance:
        with stage("observability at the solution"):
            S, scale, gnames = schur_global(problem, state)
            N = null_space(S, scale=scale)
            null_dim = int(N.shape[1])
            observable = {n: bool(o) for n, o in zip(gnames, observable_mask(N), strict=True)}
        with stage("covariances", hint="run without covariances (compute_covariance=False)"):
            H, cols = information(problem, state, full=False)
            d = np.sqrt(np.maximum(np.diag(H), 1e-300))
            C = np.linalg.inv(H / np.outer(d, d)) / np.outer(d, d) * variance_factor
        for k, n in enumerate(cols.names[: cols.n_global]):
            std[n] = float(np.sqrt(max(C[k, k], 0.0)))
        for ch in problem.chains:
            for i in np.flatnonzero(problem.has_theta[ch]):
                if ("J", f"{i}:{ch}") in cols.block:
                    b = cols.block[("J", f"{i}:{ch}")]
                    theta_std[ch][i] = np.sqrt(np.maximum(np.diag(C[np.ix_(b, b)]), 0.0))
        T_cov = T_cs_covariances(problem, cols, state, C)
    result = ClusterCalibrationResult(
        model=state.model,
        intrinsics=dict(data.cameras),
        joint_angles=state.thetas,
        joint_angle_std=theta_std,
        T_st=state.T_st,
        snapshot_index=np.asarray(used, dtype=np.int64),
        skipped_snapshots=skipped,
        parameter_std=std,
        observable=observable,
        gauge_fixed=gauge_fixed,
        T_cs_covariances=T_cov,
        residuals=residuals,
        null_space_dim=null_dim,
        n_gauge=problem.n_gauge,
        iterations=solved.iterations,
        initial_error=solved.initial_error,
        final_error=solved.final_error,
        solve_time_s=time.perf_counter() - t0,
        variance_factor=variance_factor,
    )
    result.extra["problem"] = problem
    result.extra["start"] = start
    return result


# ------------------------------------------------------------------ at given values (Cramer-Rao bound)


def problem_at(
    data: ClusterDataset,
    model: ClusterKinematics,
    thetas: Mapping[str, FloatArray],
    T_st: FloatArray,
    sigma: float,
) -> tuple[ClusterProblem, ClusterState]:
    """The problem and state at given values (e.g. the simulator's truth), for information matrices:
    the used snapshots of ``data``, the gauge of :func:`gauge_of_chain`, joint angles chain -> (K, L)
    and target poses (K, 4, 4) over all of ``data``'s snapshots (rad, m), pixel ``sigma``."""
    used, _ = usable_snapshots(data, model)
    sub = ClusterDataset(dict(data.cameras), data.target_points, [data.snapshots[i] for i in used], data.source)
    chain_free, offsets, has_theta, th = {}, {}, {}, {}
    for ch in model.chain_order:
        fixed, offs = gauge_of_chain(model.n_joints(ch))
        chain_free[ch], offsets[ch] = ~fixed, offs
        has_theta[ch] = np.array([any(model.mounts[c] == ch for c in s.cameras) for s in sub.snapshots], dtype=bool)
        th[ch] = np.asarray(thetas[ch], dtype=float)[used].reshape(len(used), model.n_joints(ch))
    T = np.asarray(T_st, dtype=float)[used]
    problem = ClusterProblem(sub, model.copy(), chain_free, offsets, has_theta, th, T, sigma, None)
    return problem, ClusterState(model.copy(), th, T)


def T_cs_bound(problem: ClusterProblem, state: ClusterState, rel_tol: float = 1e-12) -> dict[str, FloatArray]:
    """Cramer-Rao bound of every camera's ``T_cs(theta_i)`` (camera -> (K, 6, 6), tangent ``[omega, v]``,
    NaN where not defined) from the information of the *full* parameterization at ``state``: its
    Jacobi-scaled pseudo-inverse without the exact null space (the gauge), projected by the Jacobian
    of ``T_cs(theta_i)``, which is gauge-invariant. Independent of the gauge rules of the solver."""
    H, cols = information(problem, state, full=True)
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    w, V = np.linalg.eigh(H / np.outer(d, d))
    keep = w > rel_tol * w.max()
    C = (V[:, keep] / w[keep]) @ V[:, keep].T / np.outer(d, d)
    return T_cs_covariances(problem, cols, state, C)
