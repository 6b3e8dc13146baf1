"""Files of a VIO run: ``trajectory.tum`` (body/IMU frame ``T_WI``), ``joint_angles.csv`` (and with
``joint_sigmas`` ``joint_angles_sigma.csv``; further gimbal chains of an N-camera run
``joint_angles_<chain>.csv``) and ``summary.json``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dcc_fg.io.outputs import write_joint_angles_csv, write_joint_sigmas_csv, write_json
from dcc_fg.io.tum import write_tum
from dcc_fg.vio.backend.options import VioResult


def segment_bounds(result: VioResult) -> list[tuple[int, int]]:
    """``[start_ns, end_ns)`` of every trajectory segment when the smoother restarted (more than one
    segment; else empty). Poses of different segments are not in one world frame, so each segment is
    also written as ``trajectory_segment_K.tum`` (K from 1) for evaluating it on its own."""
    segments = result.stats.get("segments") or []
    if len(segments) < 2:
        return []
    starts = [int(s["start_ns"]) for s in segments]
    ends = starts[1:] + [np.iinfo(np.int64).max]
    return list(zip(starts, ends, strict=True))


def write_vio_outputs(out_dir: str | Path, result: VioResult, extra: dict[str, Any] | None = None) -> None:
    """``OUT/trajectory.tum`` (body/IMU frame), ``OUT/joint_angles.csv`` (dcc/scc) and ``OUT/summary.json``;
    after a restart of the smoother also ``OUT/trajectory_segment_K.tum`` per segment (:func:`segment_bounds`)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_tum(out / "trajectory.tum", result.timestamps_ns, result.T_WI)
    for k, (t0, t1) in enumerate(segment_bounds(result), start=1):
        sel = (result.timestamps_ns >= t0) & (result.timestamps_ns < t1)
        write_tum(out / f"trajectory_segment_{k}.tum", result.timestamps_ns[sel], result.T_WI[sel])
    if result.mode != "mono" and result.theta.shape[1] > 0:
        write_joint_angles_csv(out / "joint_angles.csv", result.timestamps_ns, result.theta)
        if result.theta_sigma is not None:
            write_joint_sigmas_csv(out / "joint_angles_sigma.csv", result.timestamps_ns, result.theta_sigma)
    for name, theta in result.chain_theta.items():  # further gimbal chains of an N-camera run
        write_joint_angles_csv(out / f"joint_angles_{name}.csv", result.timestamps_ns, theta)
    summary = {
        "mode": result.mode,
        "keyframes": int(result.timestamps_ns.size),
        "start_ns": int(result.timestamps_ns[0]) if result.timestamps_ns.size else None,
        "end_ns": int(result.timestamps_ns[-1]) if result.timestamps_ns.size else None,
        "final_acc_bias": result.acc_bias[-1] if result.timestamps_ns.size else None,
        "final_gyro_bias": result.gyro_bias[-1] if result.timestamps_ns.size else None,
        **result.stats,
        **(extra or {}),
    }
    write_json(out / "summary.json", summary)
