"""What the interactive view shows of a calibration, computed without any viewer (:mod:`dcc_fg.viz.rerun_log`).

Frames and symbols as in ``docs/architecture.md``: ``s`` static camera (the calibration's world: every
3D pose here is ``T_s<frame>``, mapping points of that frame into s, metres), ``b`` gimbal base, DH frames
``1 .. L-1`` between the joints, ``e`` end effector, ``d`` gimbal camera, ``t`` target. Pixels are in the
distorted images.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from dcc_fg.calibrate import CalibrationResult
from dcc_fg.data import CalibrationDataset
from dcc_fg.model import GimbalCalibration
from dcc_fg.plots.chain3d import chain_frames, joint_axes
from factors import chain

FloatArray = NDArray[np.float64]

#: Entity name of each chain frame of :func:`dcc_fg.plots.chain3d.chain_frames` (``l`` -> ``link_l``).
FRAME_NAMES = {"s": "static_camera", "b": "gimbal_base", "e": "end_effector", "d": "gimbal_camera"}


def frame_name(key: str) -> str:
    """Entity name of the chain frame ``key`` (``s``, ``b``, ``1`` .. ``L-1``, ``e``, ``d``)."""
    return FRAME_NAMES.get(key, f"link_{key}")


def chain_poses(cal: GimbalCalibration, theta: FloatArray) -> dict[str, FloatArray]:
    """``{entity name: T_s<frame>}`` (4x4, frame -> s, metres) of every chain frame at joint angles
    ``theta`` (L,) rad: static camera, gimbal base, the DH frames between the joints, end effector, gimbal
    camera, in that order."""
    return {frame_name(k): T for k, T in chain_frames(cal, theta).items()}


def joint_axis_segments(cal: GimbalCalibration, theta: FloatArray, half_length: float) -> FloatArray:
    """(L, 2, 3) segment of each joint's rotation axis in s (the z axis of DH frame l-1), ``half_length``
    metres to either side of its origin."""
    segs = [np.stack([p - half_length * u, p + half_length * u]) for p, u in joint_axes(cal, theta)]
    return np.asarray(segs, dtype=float).reshape(-1, 2, 3)


@dataclass(frozen=True)
class SnapshotCorners:
    """One camera's corners of one snapshot: target point ``ids`` (N,), ``detected`` and ``reprojected``
    pixels (N, 2; the model's prediction at the solution: target pose ``T_st``, ``T_ds(theta)``)."""

    ids: NDArray[np.int64]
    detected: FloatArray
    reprojected: FloatArray


def snapshot_corners(data: CalibrationDataset, result: CalibrationResult, i: int) -> tuple[SnapshotCorners, ...]:
    """Static and gimbal camera corners of snapshot ``i``: detected, and reprojected through the
    estimated target pose ``T_st`` and chain ``T_ds(theta_i)``."""
    snap = data.snapshots[i]
    T_st = np.asarray(result.T_st[i], dtype=float)
    T_dt = result.T_ds(i) @ T_st
    out = []
    for obs, cam, T in ((snap.static, data.static_camera, T_st), (snap.dynamic, data.dynamic_camera, T_dt)):
        p_t = data.target_points[obs.ids]
        p_c = p_t @ T[:3, :3].T + T[:3, 3]
        uv, _ = cam.project(p_c, jacobian=False)
        out.append(SnapshotCorners(obs.ids, obs.pixels, uv))
    return out[0], out[1]


def residual_rms(residuals: list[FloatArray]) -> FloatArray:
    """Per snapshot RMS per axis of the pixel residuals (NaN for a snapshot without corners)."""
    return np.array([float(np.sqrt(np.mean(r * r))) if r.size else float("nan") for r in residuals])


def axis_length(result: CalibrationResult) -> float:
    """Length (m) of the drawn frame axes: a tenth of the median target distance, at least 2 cm."""
    dist = np.linalg.norm(np.asarray(result.T_st, float)[:, :3, 3], axis=1)
    return max(0.02, 0.1 * float(np.median(dist))) if dist.size else 0.05


def target_outline(points: FloatArray) -> FloatArray:
    """(5, 3) closed rectangle around the target corners in the target frame t (metres, z = 0 plane
    of the board)."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    z = float(np.mean(points[:, 2]))
    return np.array([[lo[0], lo[1], z], [hi[0], lo[1], z], [hi[0], hi[1], z], [lo[0], hi[1], z], [lo[0], lo[1], z]])


def inverse(T: FloatArray) -> FloatArray:
    """Inverse of a 4x4 rigid transform."""
    return chain.inv_se3(np.asarray(T, dtype=float))
