"""Trajectory and joint-angle accuracy of a VIO run against ground truth (paper Tables IV and V).

Metrics (computed with ``evo`` on the time-overlap of estimate and ground truth, poses associated
within ``max_diff`` seconds):

* APE of the translation after alignment: SE(3) (the IMU makes scale observable) or Sim(3)
  (monocular runs); RMSE, mean, median, max in metres;
* RPE of the translation over ``rpe_delta`` metres of travel (m);
* normalized translation RMSE = 100 * APE RMSE / distance travelled (percent; Table IV);
* normalized rotation RMSE = RMSE of the rotation-angle error after alignment / distance (rad/m);
* joint-angle RMSE per joint (rad; Table V), ground truth linearly interpolated to the keyframes; for
  the further gimbal chains of an N-camera run (``joint_angles_<chain>.csv``) per chain.

Ground truth is a TUM file (body/IMU frame) or a ROS1/ROS2 bag with ``geometry_msgs/PoseStamped``
on ``/ground_truth/pose`` and ``sensor_msgs/JointState`` on ``/ground_truth/joints`` (the primary
chain) and ``/ground_truth/joints_<chain>`` (further chains), what the flight simulator writes (the pose
and primary joint topic names are parameters).
"""

from __future__ import annotations

import copy
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from evo.core import metrics, sync
from evo.core.trajectory import PoseTrajectory3D
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from dcc_fg.io.bags import bag_reader, is_bag, stamp_ns
from dcc_fg.io.outputs import read_joint_angles_csv, write_json
from dcc_fg.io.tum import read_tum

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
NS = 1_000_000_000
POSE_TOPIC = "/ground_truth/pose"
JOINT_TOPIC = "/ground_truth/joints"


@dataclass(frozen=True)
class GroundTruth:
    """Body poses ``T_WI`` (N, 4, 4) at ``t_ns`` and optional joint angles (M, L) at ``joint_t_ns``;
    ``chains``: further gimbal chains' joint angles, chain name -> (times ns (M,), angles (M, L) rad)."""

    t_ns: IntArray
    T_WI: FloatArray
    joint_t_ns: IntArray | None = None
    joints: FloatArray | None = None
    chains: dict[str, tuple[IntArray, FloatArray]] = field(default_factory=dict)

    def chain(self, name: str) -> GroundTruth:
        """This ground truth with further chain ``name``'s joint angles as its joints (for :func:`joint_rmse`);
        ValueError when it has none."""
        if name not in self.chains:
            raise ValueError(f"the ground truth has no joint angles of chain {name!r} (topic {JOINT_TOPIC}_{name})")
        t, q = self.chains[name]
        return GroundTruth(self.t_ns, self.T_WI, t, q)


def _read_bag_ground_truth(path: Path, pose_topic: str, joint_topic: str) -> GroundTruth:
    poses: list[tuple[int, list[float]]] = []
    joints: list[tuple[int, list[float]]] = []
    further: dict[str, list[tuple[int, list[float]]]] = {}
    chain_prefix = JOINT_TOPIC + "_"
    with bag_reader(path) as reader:
        topics = {c.topic for c in reader.connections}
        if pose_topic not in topics:
            raise ValueError(f"{path}: no ground-truth topic '{pose_topic}' (topics: {', '.join(sorted(topics))})")
        wanted = {pose_topic, joint_topic} | {t for t in topics if t.startswith(chain_prefix)}
        conns = [c for c in reader.connections if c.topic in wanted]
        for conn, t, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            stamp = stamp_ns(msg, t)
            if conn.topic == pose_topic:
                p, q = msg.pose.position, msg.pose.orientation
                poses.append((stamp, [p.x, p.y, p.z, q.x, q.y, q.z, q.w]))
            elif conn.topic == joint_topic:
                joints.append((stamp, [float(x) for x in msg.position]))
            else:
                further.setdefault(conn.topic[len(chain_prefix) :], []).append(
                    (stamp, [float(x) for x in msg.position])
                )
    poses.sort(key=lambda x: x[0])
    arr = np.array([p for _, p in poses])
    T = np.tile(np.eye(4), (arr.shape[0], 1, 1))
    T[:, :3, :3] = Rotation.from_quat(arr[:, 3:7]).as_matrix()
    T[:, :3, 3] = arr[:, :3]
    t = np.array([s for s, _ in poses], dtype=np.int64)
    chains = {name: _joint_series(rows) for name, rows in further.items()}
    if not joints:
        return GroundTruth(t, T, chains=chains)
    jt, jq = _joint_series(joints)
    return GroundTruth(t, T, jt, jq, chains)


def _joint_series(rows: list[tuple[int, list[float]]]) -> tuple[IntArray, FloatArray]:
    """JointState rows (stamp ns, positions) as time-sorted arrays."""
    rows = sorted(rows, key=lambda x: x[0])
    return np.array([s for s, _ in rows], dtype=np.int64), np.array([q for _, q in rows], dtype=float)


def load_ground_truth(path: str | Path, pose_topic: str = POSE_TOPIC, joint_topic: str = JOINT_TOPIC) -> GroundTruth:
    """Read a TUM file or a bag (see module docstring)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: ground truth not found")
    if is_bag(path):
        return _read_bag_ground_truth(path, pose_topic, joint_topic)
    t, T = read_tum(path)
    return GroundTruth(t, T)


def _trajectory(t_ns: IntArray, T: FloatArray) -> Any:
    q = Rotation.from_matrix(T[:, :3, :3]).as_quat()
    return PoseTrajectory3D(
        positions_xyz=T[:, :3, 3].copy(), orientations_quat_wxyz=q[:, [3, 0, 1, 2]], timestamps=t_ns / NS
    )


def _associate_and_align(
    est_t_ns: IntArray, est_T: FloatArray, gt: GroundTruth, align: str, max_diff: float
) -> tuple[Any, Any, float]:
    """evo trajectories (reference, estimate) associated within ``max_diff`` s, the estimate aligned
    to the reference in place (SE(3), Sim(3) or not at all), and the alignment's scale."""
    if align not in ("se3", "sim3", "none"):
        raise ValueError(f"alignment '{align}' is not one of se3, sim3, none")
    ref = _trajectory(gt.t_ns, gt.T_WI)
    est = _trajectory(np.asarray(est_t_ns, dtype=np.int64), np.asarray(est_T, float))
    try:
        ref, est = sync.associate_trajectories(ref, est, max_diff=max_diff)
    except sync.SyncException as err:
        raise ValueError(f"estimate and ground truth do not overlap in time ({err})") from None
    if est.num_poses < 3:
        raise ValueError(f"only {est.num_poses} poses overlap the ground truth within {max_diff} s")
    scale = 1.0
    if align != "none":
        _, _, s = est.align(ref, correct_scale=(align == "sim3"))
        scale = float(s)
    return ref, est, scale


@dataclass(frozen=True)
class AlignedTrajectory:
    """An estimate associated with the ground truth in time and aligned to it, as the evaluation sees it.

    ``t_s`` (N,) seconds (the estimate's stamps, same clock as the inputs); ``T_WI_est`` and
    ``T_WI_gt`` (N, 4, 4) body poses in the ground truth's world frame W (metres) after the
    ``alignment`` (``se3``, ``sim3`` or ``none``; ``scale`` is 1 unless Sim(3)).
    """

    t_s: FloatArray
    T_WI_est: FloatArray
    T_WI_gt: FloatArray
    alignment: str
    scale: float

    @property
    def p_est(self) -> FloatArray:
        """(N, 3) aligned estimated body positions in W (m)."""
        return self.T_WI_est[:, :3, 3]

    @property
    def p_gt(self) -> FloatArray:
        """(N, 3) ground-truth body positions in W (m) at the same times."""
        return self.T_WI_gt[:, :3, 3]


def align_trajectory(
    est_t_ns: IntArray, est_T: FloatArray, gt: GroundTruth, align: str = "se3", max_diff: float = 0.01
) -> AlignedTrajectory:
    """Associate and align an estimated body trajectory exactly as :func:`evaluate_trajectory` does."""
    ref, est, scale = _associate_and_align(est_t_ns, est_T, gt, align, max_diff)
    return AlignedTrajectory(
        np.asarray(est.timestamps, float), np.asarray(est.poses_se3), np.asarray(ref.poses_se3), align, scale
    )


def evaluate_trajectory(
    est_t_ns: IntArray,
    est_T: FloatArray,
    gt: GroundTruth,
    align: str = "se3",
    max_diff: float = 0.01,
    rpe_delta: float = 1.0,
) -> dict[str, Any]:
    """APE / RPE / normalized errors of an estimated body trajectory (see module docstring)."""
    ref, est, scale = _associate_and_align(est_t_ns, est_T, gt, align, max_diff)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    rot = metrics.APE(metrics.PoseRelation.rotation_angle_rad)
    rot.process_data((ref, est))
    distance = float(ref.path_length)
    stats = ape.get_all_statistics()
    out: dict[str, Any] = {
        "alignment": align,
        "scale": scale,
        "poses": int(est.num_poses),
        "duration_s": float(ref.timestamps[-1] - ref.timestamps[0]),
        "distance_m": distance,
        "ape_rmse_m": float(stats["rmse"]),
        "ape_mean_m": float(stats["mean"]),
        "ape_median_m": float(stats["median"]),
        "ape_max_m": float(stats["max"]),
        "rotation_rmse_rad": float(rot.get_statistic(metrics.StatisticsType.rmse)),
        "normalized_translation_rmse_percent": 100.0 * float(stats["rmse"]) / distance if distance > 0 else None,
        "normalized_rotation_rmse_rad_per_m": (
            float(rot.get_statistic(metrics.StatisticsType.rmse)) / distance if distance > 0 else None
        ),
    }
    try:
        rpe = metrics.RPE(metrics.PoseRelation.translation_part, rpe_delta, metrics.Unit.meters, all_pairs=False)
        rpe.process_data((copy.deepcopy(ref), copy.deepcopy(est)))
        out["rpe_rmse_m"] = float(rpe.get_statistic(metrics.StatisticsType.rmse))
        out["rpe_delta_m"] = rpe_delta
    except Exception as err:  # evo raises its own errors for too-short trajectories
        out["rpe_rmse_m"] = None
        out["rpe_error"] = str(err)
    return out


def joint_rmse(est_t_ns: IntArray, est_theta: FloatArray, gt: GroundTruth) -> list[float] | None:
    """Per-joint RMSE (rad) of estimated joint angles against interpolated ground truth (overlap only)."""
    if gt.joints is None or gt.joint_t_ns is None or est_theta.size == 0:
        return None
    est_theta = np.asarray(est_theta, float).reshape(len(est_t_ns), -1)
    if est_theta.shape[1] != gt.joints.shape[1]:
        raise ValueError(f"estimate has {est_theta.shape[1]} joints, ground truth {gt.joints.shape[1]}")
    inside = (est_t_ns >= gt.joint_t_ns[0]) & (est_t_ns <= gt.joint_t_ns[-1])
    if inside.sum() == 0:
        raise ValueError("joint-angle estimates do not overlap the ground-truth joint states")
    t = est_t_ns[inside].astype(float)
    truth = np.column_stack(
        [np.interp(t, gt.joint_t_ns.astype(float), gt.joints[:, j]) for j in range(est_theta.shape[1])]
    )
    err = est_theta[inside] - truth
    return [float(x) for x in np.sqrt(np.mean(err**2, axis=0))]


def output_mode_and_alignment(out_dir: str | Path, align: str = "auto") -> tuple[str | None, str]:
    """The mode of a VIO output folder (from ``summary.json``, None if absent) and the alignment to use:
    ``align`` itself, or for ``'auto'`` Sim(3) when the mode is ``mono`` and SE(3) otherwise.
    Raises FileNotFoundError when the folder has no ``trajectory.tum``."""
    out_dir = Path(out_dir)
    traj = out_dir / "trajectory.tum"
    if not traj.is_file():
        raise FileNotFoundError(f"{traj}: no trajectory (run dcc-fg vio first)")
    mode = None
    summary = out_dir / "summary.json"
    if summary.is_file():
        mode = json.loads(summary.read_text()).get("mode")
    if align == "auto":
        align = "sim3" if mode == "mono" else "se3"
    return mode, align


def evaluate_folder(out_dir: str | Path, ground_truth: str | Path, align: str = "auto") -> dict[str, Any]:
    """The evaluation of ``OUT/trajectory.tum`` (+ ``joint_angles.csv``) of a VIO run, without writing.

    ``align='auto'`` uses Sim(3) for runs whose ``summary.json`` says mode ``mono``, SE(3) otherwise.
    """
    out_dir = Path(out_dir)
    mode, align = output_mode_and_alignment(out_dir, align)
    gt = load_ground_truth(ground_truth)
    t, T = read_tum(out_dir / "trajectory.tum")
    result = {"mode": mode, "ground_truth": str(ground_truth), **evaluate_trajectory(t, T, gt, align)}
    joints_csv = out_dir / "joint_angles.csv"
    if joints_csv.is_file() and mode != "mono":
        jt, theta = read_joint_angles_csv(joints_csv)
        rmse = joint_rmse(jt, theta, gt)
        if rmse is not None:
            result["joint_rmse_rad"] = rmse
    for csv in sorted(out_dir.glob("joint_angles_*.csv")):  # further gimbal chains
        name = csv.stem[len("joint_angles_") :]
        if name == "sigma" or name not in gt.chains:
            continue
        jt, theta = read_joint_angles_csv(csv)
        result.setdefault("chain_joint_rmse_rad", {})[name] = joint_rmse(jt, theta, gt.chain(name))
    return result


def evaluate_output(out_dir: str | Path, ground_truth: str | Path, align: str = "auto") -> dict[str, Any]:
    """:func:`evaluate_folder`, written to ``OUT/evaluation.json``."""
    result = evaluate_folder(out_dir, ground_truth, align)
    write_json(Path(out_dir) / "evaluation.json", result)
    return result


def format_evaluation(result: dict[str, Any]) -> str:
    """Text table of an evaluation (the paper's Table IV / V quantities)."""
    lines = [
        f"alignment                         {result['alignment']} (scale {result['scale']:.4f})",
        f"poses / duration / distance       {result['poses']} / {result['duration_s']:.1f} s / "
        f"{result['distance_m']:.2f} m",
        f"APE translation RMSE              {result['ape_rmse_m']:.4f} m (max {result['ape_max_m']:.4f} m)",
    ]
    if result.get("rpe_rmse_m") is not None:
        lines.append(f"RPE translation RMSE per {result['rpe_delta_m']:g} m     {result['rpe_rmse_m']:.4f} m")
    if result.get("normalized_translation_rmse_percent") is not None:
        lines.append(f"normalized translation RMSE       {result['normalized_translation_rmse_percent']:.3g} %")
        lines.append(f"normalized rotation RMSE          {result['normalized_rotation_rmse_rad_per_m']:.3g} rad/m")
    for j, r in enumerate(result.get("joint_rmse_rad") or [], start=1):
        lines.append(f"joint {j} angle RMSE                {r:.3g} rad")
    for name, rmse in (result.get("chain_joint_rmse_rad") or {}).items():
        for j, r in enumerate(rmse or [], start=1):
            lines.append(f"{name} joint {j} angle RMSE".ljust(34) + f"{r:.3g} rad")
    for seg in result.get("segments") or []:
        ape = seg.get("ape_rmse_m")
        text = f"{ape:.4f} m over {seg['keyframes']} keyframes" if ape is not None else f"{seg['keyframes']} keyframes"
        lines.append(f"segment {seg['file']}: APE RMSE {text} (aligned on its own)")
    return "\n".join(lines)
