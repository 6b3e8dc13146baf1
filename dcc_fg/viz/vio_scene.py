"""What the interactive view shows of a VIO run, computed without any viewer (:mod:`dcc_fg.viz.rerun_log`).

Frames as in ``docs/architecture.md``: ``W`` the estimate's world (gravity along -z, metres), ``I`` body
(IMU), ``s`` static camera (``T_sI`` maps IMU points into s), the gimbal chain relative to s at each
keyframe's estimated joint angles. The ground truth lives in its own world frame; it is brought into
``W`` by the inverse of the alignment the evaluation uses (:func:`dcc_fg.vio.evaluate.align_trajectory`:
SE(3), or Sim(3) for ``mono`` runs), so the estimate is shown as it was computed and the truth moves.

Per frame (:class:`~dcc_fg.vio.pipeline.FrameEvent`): each camera's tracked features in pixels of its
distorted image (the front end's normalized undistorted coordinates ``[x, y, 1]`` projected through the
camera model), each with a class (:data:`TRACK_CLASSES`: static / gimbal camera, matched across the two
cameras or not, rejected by stage two), and at keyframes the window's landmarks in W with a class
(:data:`LANDMARK_CLASSES`: seen by the static camera in that frame, only by the gimbal camera, or by neither).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from dcc_fg.data.vio import TrackFrame
from dcc_fg.io.bags import bag_reader, is_bag
from dcc_fg.vio.backend import VioResult
from dcc_fg.vio.evaluate import NS, POSE_TOPIC, GroundTruth, align_trajectory, load_ground_truth
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
ClassArray = NDArray[np.uint16]
log = logging.getLogger(__name__)

#: Class ids of a tracked feature (the recording's annotation context gives each its label and colour).
STATIC_ONLY, STATIC_MATCHED, GIMBAL_ONLY, GIMBAL_MATCHED, GIMBAL_REJECTED = range(5)
#: Class ids of a window landmark at a keyframe.
LANDMARK_STATIC, LANDMARK_GIMBAL_ONLY, LANDMARK_UNSEEN = range(5, 8)
#: Label and colour (RGB) of every class id.
TRACK_CLASSES: dict[int, tuple[str, tuple[int, int, int]]] = {
    STATIC_ONLY: ("static camera, not matched in the gimbal camera", (30, 140, 255)),
    STATIC_MATCHED: ("static camera, matched in the gimbal camera (shared id)", (40, 220, 40)),
    GIMBAL_ONLY: ("gimbal camera, not matched in the static camera", (255, 160, 0)),
    GIMBAL_MATCHED: ("gimbal camera, matched in the static camera (shared id)", (40, 220, 40)),
    GIMBAL_REJECTED: ("gimbal camera, rejected by stage two (outlier)", (240, 40, 40)),
}
LANDMARK_CLASSES: dict[int, tuple[str, tuple[int, int, int]]] = {
    LANDMARK_STATIC: ("landmark seen by the static camera in this keyframe", (30, 140, 255)),
    LANDMARK_GIMBAL_ONLY: ("landmark seen only by the gimbal camera in this keyframe", (255, 160, 0)),
    LANDMARK_UNSEEN: ("landmark of the window not seen in this keyframe", (150, 150, 150)),
}


def bag_has_ground_truth(bag: str | Path) -> bool:
    """True when ``bag`` is a ROS bag with the simulator's ground-truth pose topic (``/ground_truth/pose``)."""
    path = Path(bag)
    if not is_bag(path):
        return False
    try:
        with bag_reader(path) as reader:
            return any(c.topic == POSE_TOPIC for c in reader.connections)
    except (ValueError, OSError):
        return False


def find_ground_truth(bag: str | Path, explicit: str | Path | None) -> GroundTruth | None:
    """The ground truth to show: ``explicit`` (TUM file or bag, :func:`~dcc_fg.vio.evaluate.load_ground_truth`),
    else the VIO bag's own ``/ground_truth/pose`` topic when it has one (simulated flights), else None."""
    if explicit is not None:
        return load_ground_truth(explicit)
    if bag_has_ground_truth(bag):
        log.info("rerun: showing the ground truth of %s (%s)", bag, POSE_TOPIC)
        return load_ground_truth(bag)
    return None


@dataclass(frozen=True)
class TruthInEstimateFrame:
    """Ground truth brought into the estimate's world W at the keyframes it overlaps.

    ``keyframes`` (N,) indices into the result's keyframes; ``T_WI`` (N, 4, 4) true body poses in W
    (rotation and position, metres; for Sim(3) the positions are divided by the alignment's ``scale``);
    ``theta`` (N, L) true joint angles (rad) interpolated to the keyframe times, or None; ``alignment``
    ``se3`` or ``sim3``."""

    keyframes: IntArray
    T_WI: FloatArray
    theta: FloatArray | None
    alignment: str
    scale: float


def truth_in_estimate_frame(result: VioResult, gt: GroundTruth, max_diff_s: float = 0.01) -> TruthInEstimateFrame:
    """The ground truth at the result's keyframes (associated within ``max_diff_s`` s), in W.

    The evaluation aligns the estimate onto the truth, ``p_gt ~ s R p_W + t`` (s = 1 for SE(3)); here the
    inverse is applied to the truth: ``R`` from the mean rotation difference of the associated poses, then
    ``s, t`` by linear least squares on the positions.

    Raises:
        ValueError: the estimate and the truth do not overlap in time (from the association).
    """
    align = "sim3" if result.mode == "mono" else "se3"
    aligned = align_trajectory(result.timestamps_ns, result.T_WI, gt, align, max_diff_s)
    t_kf = result.timestamps_ns.astype(np.int64)
    idx = np.abs(t_kf[None, :] - np.round(aligned.t_s * NS).astype(np.int64)[:, None]).argmin(axis=1)
    R_est = result.T_WI[idx, :3, :3]
    # aligned rotations are R @ R_est: the mean of R_aligned R_est^T, projected onto SO(3)
    M = np.einsum("nij,nkj->ik", aligned.T_WI_est[:, :3, :3], R_est)
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)))]) @ Vt
    q = result.T_WI[idx, :3, 3] @ R.T
    scale, t = 1.0, np.mean(aligned.p_est - q, axis=0)
    if align == "sim3":
        A = np.zeros((3 * len(idx), 4))
        A[:, 0] = q.reshape(-1)
        A[:, 1:] = np.tile(np.eye(3), (len(idx), 1))
        sol, *_ = np.linalg.lstsq(A, aligned.p_est.reshape(-1), rcond=None)
        scale, t = float(sol[0]), sol[1:]
    T = np.repeat(np.eye(4)[None], len(idx), axis=0)
    T[:, :3, :3] = np.einsum("ji,njk->nik", R, aligned.T_WI_gt[:, :3, :3])
    T[:, :3, 3] = ((aligned.p_gt - t) @ R) / scale
    theta = None
    if gt.joints is not None and gt.joint_t_ns is not None and result.theta.size:
        tq = t_kf[idx].astype(float)
        jt = gt.joint_t_ns.astype(float)
        theta = np.column_stack([np.interp(tq, jt, gt.joints[:, j]) for j in range(gt.joints.shape[1])])
    return TruthInEstimateFrame(idx.astype(np.int64), T, theta, align, scale)


def segment_slices(result: VioResult) -> list[slice]:
    """Keyframe index ranges of the trajectory segments (one slice when the smoother never restarted);
    poses of different segments are not in one frame, so each is drawn as its own line."""
    t = result.timestamps_ns
    starts = sorted({int(s["start_ns"]) for s in result.stats.get("segments") or []})
    cuts = [int(np.searchsorted(t, s)) for s in starts if 0 < np.searchsorted(t, s) < len(t)]
    bounds = [0, *sorted(set(cuts)), len(t)]
    return [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True) if b > a]


@dataclass(frozen=True)
class CameraTracks:
    """One camera's tracked features in one frame: ``ids`` (N,) track ids, ``uv`` (N, 2) pixels of the
    distorted image, ``classes`` (N,) class ids (:data:`TRACK_CLASSES`)."""

    ids: IntArray
    uv: FloatArray
    classes: ClassArray


def pixels(camera: CameraModel, xy: FloatArray) -> FloatArray:
    """Normalized undistorted image coordinates (N, 2) -> pixels (N, 2) of the distorted image: the
    camera's projection of the camera-frame points ``[x, y, 1]``."""
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    uv, _ = camera.project(np.column_stack([xy, np.ones(len(xy))]), jacobian=False)
    return uv


def frame_tracks(
    frame: TrackFrame, rejected_ids: IntArray, static_camera: CameraModel, dynamic_camera: CameraModel | None
) -> tuple[CameraTracks, CameraTracks | None]:
    """The static and (with ``dynamic_camera``) the gimbal camera's tracks of ``frame``. A track is
    matched when its id is in both cameras' id lists; a gimbal track whose id is in ``rejected_ids``
    (stage two, after this frame) is rejected, whether matched or not."""
    s_ids = np.asarray(frame.static_ids, dtype=np.int64)
    d_ids = np.asarray(frame.dynamic_ids, dtype=np.int64)
    s_cls = np.where(np.isin(s_ids, d_ids), STATIC_MATCHED, STATIC_ONLY).astype(np.uint16)
    static = CameraTracks(s_ids, pixels(static_camera, frame.static_xy), s_cls)
    if dynamic_camera is None:
        return static, None
    d_cls = np.where(np.isin(d_ids, s_ids), GIMBAL_MATCHED, GIMBAL_ONLY).astype(np.uint16)
    d_cls[np.isin(d_ids, np.asarray(rejected_ids, dtype=np.int64))] = GIMBAL_REJECTED
    return static, CameraTracks(d_ids, pixels(dynamic_camera, frame.dynamic_xy), d_cls)


def further_tracks(frame: TrackFrame, cameras: dict[int, tuple[CameraModel, bool]]) -> dict[int, CameraTracks]:
    """The tracks of the further cameras of ``frame`` (run index -> :class:`CameraTracks`) for the cameras
    in ``cameras`` (run index -> (model, on a gimbal)): a track is matched when cam0 sees its id too; a
    rigid camera's tracks take the static camera's classes, a gimbal camera's the gimbal camera's."""
    s_ids = np.asarray(frame.static_ids, dtype=np.int64)
    out = {}
    for c in frame.extra:
        if c.camera not in cameras:
            continue
        model, on_gimbal = cameras[c.camera]
        ids = np.asarray(c.ids, dtype=np.int64)
        matched, only = (GIMBAL_MATCHED, GIMBAL_ONLY) if on_gimbal else (STATIC_MATCHED, STATIC_ONLY)
        cls = np.where(np.isin(ids, s_ids), matched, only).astype(np.uint16)
        out[c.camera] = CameraTracks(ids, pixels(model, c.xy), cls)
    return out


@dataclass(frozen=True)
class WindowLandmarks:
    """The sliding window's landmarks at a keyframe: ``ids`` (N,) track ids, ``points`` (N, 3) in W
    (metres), ``classes`` (N,) class ids (:data:`LANDMARK_CLASSES`)."""

    ids: IntArray
    points: FloatArray
    classes: ClassArray


def window_landmarks(landmarks: dict[int, FloatArray], frame: TrackFrame) -> WindowLandmarks:
    """``landmarks`` (track id -> point in W, m) with their class in ``frame``: seen by the static camera,
    else only by the gimbal camera, else by neither (a window landmark observed at earlier keyframes)."""
    ids = np.fromiter(landmarks.keys(), dtype=np.int64, count=len(landmarks))
    points = np.array(list(landmarks.values()), dtype=float).reshape(-1, 3)
    classes = np.full(len(ids), LANDMARK_UNSEEN, dtype=np.uint16)
    classes[np.isin(ids, np.asarray(frame.dynamic_ids, dtype=np.int64))] = LANDMARK_GIMBAL_ONLY
    classes[np.isin(ids, np.asarray(frame.static_ids, dtype=np.int64))] = LANDMARK_STATIC
    return WindowLandmarks(ids, points, classes)
