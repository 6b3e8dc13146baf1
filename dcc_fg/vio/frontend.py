"""VIO front end: KLT feature tracks in the static and the gimbal camera, in one landmark-id space.

Per synchronized frame pair (:meth:`Frontend.process`):

1. **Static camera s**: pyramidal Lucas-Kanade tracking with a forward-backward check, then
   essential-matrix RANSAC (OpenCV's USAC with local optimization) on undistorted normalized
   coordinates, threshold in pixels / focal length, twice: between the previous and the current
   frame, and between the current frame and ``ransac_window`` frames ago for the tracks that
   old.  Consecutive frames have a short baseline that leaves the translation weakly determined,
   so a small independently moving cluster can fool the two-frame test for a frame or two; the
   long-baseline test catches it.  Frames with almost no parallax skip RANSAC (the essential
   matrix is degenerate without translation).  New corners (Shi-Tomasi) fill the image with a
   minimum spacing.
2. **Gimbal camera d**: tracked and refilled the same way, but *not* rejected with a motion
   model: the extrinsics T_ds(theta) change with the unknown joint angles, so an epipolar test
   with stale extrinsics removes exactly the measurements that would correct them (the paper,
   section V-B).  Instead the paper's proposed two-stage handling is offered: the back end
   optimizes with these tracks, then calls :meth:`Frontend.reject_dynamic` with the updated
   T_ds(theta) of the previous and current frame (and, if it has it, the static camera's metric
   motion); tracks inconsistent with the implied epipolar geometry are removed and their ids
   returned so the back end can drop those observations and re-optimize.  Passing a
   :class:`GimbalHint` to :meth:`Frontend.process` applies the same test immediately (one pass,
   for callers with a good prediction).
3. **Static <-> gimbal matching** so that shared landmarks make the joint angles observable:
   tracks of one camera whose id is not seen by the other get rotation-invariant ORB descriptors
   and are matched (mutual nearest neighbour, ratio test).  Together with the pairs already
   sharing an id they go through a RANSAC fit of the rotation between the two cameras, with
   the translation taken from the current T_ds estimate: the test (the image of the static ray
   for depths >= ``match_min_depth``) then needs no up-to-date joint angles, only a lever arm.
   The younger of the two tracks takes the older one's id (for the back end this just ends the
   younger track: ids are never re-assigned to different points); shared pairs that fail the
   test are split.
4. **Further cameras** of an N-camera cluster (run index >= 2, :class:`~dcc_fg.data.cameras.RunCamera`):
   each has its own tracker drawing ids from the same counter.  A camera rigid to the body gets the
   static camera's temporal RANSAC (its motion is a rigid motion too); a camera on the gimbal is not
   rejected over time, like the gimbal camera.  Each is matched against cam0 with the machinery of
   step 3 (:meth:`Frontend._match_pair`), so landmarks seen by a static stereo pair share ids from
   the first frame.  For a rigid camera with a known ``T_cs`` the check is stricter than the
   rotation RANSAC: every pair must lie on the epipolar segment of ``E = [t]x R`` from ``T_cs``
   (depths >= ``match_min_depth``) within ``match_rigid_threshold`` pixels.  When the id of a cam0
   track changes in a merge, the tracks of the other cameras that share it follow, so the links
   between cam0, the gimbal camera and the further cameras survive.

Output: a :class:`~dcc_fg.data.vio.TrackFrame` of undistorted normalized coordinates
(:meth:`CameraModel.undistort_points`).  Pixels follow OpenCV's convention.  Times in ns.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from dcc_fg.data.cameras import RunCamera
from dcc_fg.data.vio import CameraTracks, TrackFrame
from dcc_fg.detection import to_gray8
from dcc_fg.vio.epipolar import (
    depth_segment_distance,
    essential,
    homogeneous,
    rotation_prediction,
    rotation_ransac,
    sampson_distance,
)
from dcc_fg.vio.matching import OrbDescriber, mutual_ratio_matches
from factors.camera import CameraModel
from factors.chain import inv_se3

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class FrontendConfig:
    """Front-end parameters (pixels unless stated).

    Attributes:
        max_features: tracks kept per camera.
        refill_ratio: new corners are detected only when fewer than ``refill_ratio * max_features``
            tracks are left (Shi-Tomasi over the whole image is the front end's largest cost).
        min_distance: minimum spacing between tracks of one camera.
        quality_level: Shi-Tomasi quality relative to the best corner.
        klt_window, klt_levels: Lucas-Kanade window size and pyramid levels.
        fb_threshold: forward-backward tracking error above which a track is dropped.
        border: tracks closer than this to the image border are dropped.
        ransac_threshold: static-camera essential-matrix RANSAC threshold.
        ransac_confidence: RANSAC confidence.
        min_parallax: median static flow below which RANSAC is skipped.
        ransac_window: frames between the two views of the second, long-baseline RANSAC.
        match_every: run static<->gimbal matching every n-th frame.
        match_ratio, match_max_hamming: descriptor ratio test and distance bound (bits of 256).
        match_epipolar_threshold: static<->gimbal check with the translation of the T_ds estimate and
            the rotation fitted to the matches, normalized units (~radians).
        match_min_depth: smallest scene depth (metres) for that check.
        match_rotation_threshold: angle (rad) of the pure-rotation check used without a T_ds estimate
            (it must exceed the parallax of the nearest points: baseline / depth).
        min_pairs: fewer static<->gimbal pairs than this are checked against the T_ds estimate alone.
        match_rigid_threshold: pixels (the further camera's mean focal length): largest distance of a
            cam0 <-> rigid further camera pair from the epipolar segment under the known ``T_cs``
            (a full epipolar test; KLT and corner noise are a few tenths of a pixel, the rest is
            left for calibration error).
        match_klt: also follow cam0's unshared tracks into a rigid further camera, and the gimbal camera's
            into a further camera on the gimbal, with KLT (:meth:`Frontend._seed_from`; sub-pixel pairs,
            and as many as the views share).
        dynamic_threshold: gimbal-camera epipolar (Sampson) threshold of the second stage.
        dynamic_rotation_threshold: gimbal-camera threshold when the motion is a pure rotation.
    """

    max_features: int = 150
    refill_ratio: float = 0.8
    min_distance: float = 20.0
    quality_level: float = 0.01
    klt_window: int = 17
    klt_levels: int = 3
    fb_threshold: float = 1.0
    border: int = 5
    ransac_threshold: float = 1.0
    ransac_confidence: float = 0.99999
    min_parallax: float = 1.0
    ransac_window: int = 4
    match_every: int = 2
    match_ratio: float = 0.8
    match_max_hamming: int = 64
    match_epipolar_threshold: float = 0.02
    match_min_depth: float = 0.3
    match_rotation_threshold: float = 0.05
    min_pairs: int = 6
    match_rigid_threshold: float = 1.5
    match_klt: bool = True
    dynamic_threshold: float = 2.0
    dynamic_rotation_threshold: float = 4.0

    @staticmethod
    def for_resolution(width: int, height: int) -> FrontendConfig:
        """Defaults scaled to an image size: the fields above suit 640x480; smaller images get a
        proportionally smaller spacing, a 15-pixel KLT window below 480 pixels of width and fewer
        tracks below 400 (at 320x240 that halves the cost, see benchmarks/bench_frontend.py)."""
        s = min(width / 640.0, height / 480.0)
        if s >= 0.99:
            return FrontendConfig()
        return FrontendConfig(
            min_distance=max(8.0, round(20.0 * s)),
            klt_window=17 if width >= 480 else 15,
            max_features=150 if width >= 400 else 120,
        )


@dataclass(frozen=True)
class GimbalHint:
    """Extrinsics the back end believes in, for the gimbal-camera rejection.

    ``T_ds_prev`` / ``T_ds_cur``: static -> gimbal camera at the previous and the current frame
    (4x4, metres).  ``T_s_cur_prev``: the static camera's motion between those frames (maps
    points of the previous static frame into the current one, metres), or None to use the
    front end's own estimate from the static tracks (rotation and translation direction; the
    gimbal lever arm is then neglected).
    """

    T_ds_prev: FloatArray
    T_ds_cur: FloatArray
    T_s_cur_prev: FloatArray | None = None


def motion_from_pair(x0: FloatArray, x1: FloatArray, E: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(R, t) with |t| = 1 from an essential matrix and its inlier normalized points (cheirality)."""
    _, R, t, _ = cv2.recoverPose(E, x0, x1, np.eye(3))
    return R, t.ravel() / max(float(np.linalg.norm(t)), 1e-12)


@dataclass
class DynamicSnapshot:
    """Gimbal tracks of one frame (ids, normalized positions now and in the previous frame, NaN for
    tracks born in it) and the static camera's inlier pair ``(x0, x1, E)`` of that frame."""

    ids: IntArray
    prev_xy: FloatArray
    xy: FloatArray
    static_pair: tuple[FloatArray, FloatArray, FloatArray] | None = None
    motion: tuple[FloatArray, FloatArray] | None = None

    def static_motion(self) -> tuple[FloatArray, FloatArray] | None:
        """(R, t) of the static camera between the two frames (|t| = 1), or None (little parallax)."""
        if self.motion is None and self.static_pair is not None:
            self.motion = motion_from_pair(*self.static_pair)
        return self.motion


def gimbal_outliers(snap: DynamicSnapshot, hint: GimbalHint, camera: CameraModel, config: FrontendConfig) -> BoolArray:
    """Mask over the gimbal tracks of ``snap`` that are inconsistent with the extrinsics of ``hint``.

    With the extrinsics of the previous and the current frame, the gimbal camera's motion is
    ``T_{d1 d0} = T_ds(theta_1) T_{s1 s0} T_ds(theta_0)^-1``; tracks whose Sampson error
    under that motion exceeds ``config.dynamic_threshold`` pixels (``camera``'s mean focal length)
    are outliers (a motion with no translation uses the rotation-only prediction and
    ``config.dynamic_rotation_threshold``). Without ``hint.T_s_cur_prev`` the static rotation and
    translation direction estimated from the static tracks are used (the lever arm of the gimbal is
    then neglected); without those (too little parallax) the static camera is taken as not moving.
    Tracks born in this frame are never outliers.
    """
    bad = np.zeros(snap.ids.shape[0], dtype=bool)
    both = np.isfinite(snap.prev_xy[:, 0])
    if not np.any(both):
        return bad
    T0, T1 = np.asarray(hint.T_ds_prev, float), np.asarray(hint.T_ds_cur, float)
    if hint.T_s_cur_prev is not None:
        T_d = T1 @ np.asarray(hint.T_s_cur_prev, float) @ inv_se3(T0)
        R_d, t_d = T_d[:3, :3], T_d[:3, 3]
    else:
        motion = snap.static_motion()
        R_s, t_s = motion if motion is not None else (np.eye(3), np.zeros(3))
        R_d = T1[:3, :3] @ R_s @ T0[:3, :3].T
        t_d = T1[:3, :3] @ t_s
    x0, x1 = snap.prev_xy[both], snap.xy[both]
    f = float(np.mean(camera.intrinsics[:2]))
    if np.linalg.norm(t_d) > 1e-6:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R_d, t_d
        out = sampson_distance(essential(T), x0, x1) * f > config.dynamic_threshold
    else:
        pred, front = rotation_prediction(R_d, x0)
        out = ~front | (np.linalg.norm(pred - x1, axis=1) * f > config.dynamic_rotation_threshold)
    bad[np.flatnonzero(both)[out]] = True
    return bad


@dataclass
class FrontendStats:
    """Counters and per-frame timings in milliseconds: wall-clock per stage, and the process CPU
    time of the whole frame (``cpu_ms``, less sensitive to other processes on a shared machine)."""

    frames: int = 0
    static_ms: list[float] = field(default_factory=list)
    dynamic_ms: list[float] = field(default_factory=list)
    match_ms: list[float] = field(default_factory=list)
    cpu_ms: list[float] = field(default_factory=list)
    fb_rejected: int = 0
    ransac_rejected: int = 0
    ransac_tested: int = 0
    dynamic_rejected: int = 0
    matches: int = 0
    pairs_split: int = 0
    frames_without_gimbal: int = 0
    gimbal_images_between: int = 0
    #: all further cameras together per frame (tracking, rejection, detection, matching with cam0), ms
    extra_ms: list[float] = field(default_factory=list)
    #: per further camera (by name): ms per frame with its image, matches merged, pairs split, frames without image
    camera_ms: dict[str, list[float]] = field(default_factory=dict)
    camera_matches: dict[str, int] = field(default_factory=dict)
    camera_pairs_split: dict[str, int] = field(default_factory=dict)
    camera_frames_without_image: dict[str, int] = field(default_factory=dict)
    camera_seeded: dict[str, int] = field(default_factory=dict)

    def summary(self) -> dict[str, float]:
        """Medians of the timings and the counters; with further cameras also ``extra_ms_median`` and,
        per camera ``NAME``, ``NAME_ms_median``, ``NAME_matches``, ``NAME_pairs_split`` and
        ``NAME_frames_without_image``. ``total_*`` includes the further cameras."""

        def med(x: list[float]) -> float:
            return float(np.median(x)) if x else 0.0

        extra = self.extra_ms if len(self.extra_ms) == len(self.static_ms) else [0.0] * len(self.static_ms)
        total = [
            a + b + c + e for a, b, c, e in zip(self.static_ms, self.dynamic_ms, self.match_ms, extra, strict=True)
        ]
        return {
            "frames": float(self.frames),
            "static_ms_median": med(self.static_ms),
            "dynamic_ms_median": med(self.dynamic_ms),
            "match_ms_median": med(self.match_ms),
            "total_ms_median": med(total),
            "total_ms_mean": float(np.mean(total)) if total else 0.0,
            "cpu_ms_median": med(self.cpu_ms),
            "ransac_tested": float(self.ransac_tested),
            "ransac_inlier_ratio": 1.0 - self.ransac_rejected / max(self.ransac_tested, 1),
            "matches": float(self.matches),
            "frames_without_gimbal": float(self.frames_without_gimbal),
            "gimbal_images_between": float(self.gimbal_images_between),
            **self._camera_summary(),
        }

    def _camera_summary(self) -> dict[str, float]:
        if not self.camera_ms:
            return {}
        out = {"extra_ms_median": float(np.median(self.extra_ms)) if self.extra_ms else 0.0}
        for name, ms in self.camera_ms.items():
            out[f"{name}_ms_median"] = float(np.median(ms)) if ms else 0.0
            out[f"{name}_matches"] = float(self.camera_matches.get(name, 0))
            out[f"{name}_pairs_split"] = float(self.camera_pairs_split.get(name, 0))
            out[f"{name}_frames_without_image"] = float(self.camera_frames_without_image.get(name, 0))
            out[f"{name}_seeded"] = float(self.camera_seeded.get(name, 0))
        return out


class CameraTracker:
    """KLT tracks of one camera: pixel positions, ids, ages and the previous normalized positions."""

    def __init__(self, camera: CameraModel, config: FrontendConfig, ids: Iterator[int]) -> None:
        self.camera = camera
        self.config = config
        self._ids = ids
        self.gray: NDArray[np.uint8] | None = None
        self.pts = np.zeros((0, 2), dtype=np.float32)
        self.ids = np.zeros(0, dtype=np.int64)
        self.ages = np.zeros(0, dtype=np.int64)
        self.xy = np.zeros((0, 2))
        #: normalized position in the previous frame (NaN for tracks born this frame)
        self.prev_xy = np.zeros((0, 2))
        #: normalized positions 1..H frames ago, (N, H, 2), NaN where the track did not exist yet
        self.hist = np.zeros((0, max(config.ransac_window, 1), 2))
        self._prev_ids = np.zeros(0, dtype=np.int64)
        #: normalized positions at the last frame while stepping through images between frames, else None
        self.frame_xy: FloatArray | None = None
        self._lk = {
            "winSize": (config.klt_window, config.klt_window),
            "maxLevel": config.klt_levels,
            "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.03),
        }

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def keep(self, mask: BoolArray) -> None:
        self.pts, self.ids, self.ages = self.pts[mask], self.ids[mask], self.ages[mask]
        self.xy, self.prev_xy, self.hist = self.xy[mask], self.prev_xy[mask], self.hist[mask]
        if self.frame_xy is not None:
            self.frame_xy = self.frame_xy[mask]

    def track(self, gray: NDArray[np.uint8], step: bool = False) -> int:
        """Track into a new image; returns how many tracks the forward-backward check dropped.

        ``step``: an image between two frames (no frame of its own): the tracks move on, but their
        previous-frame positions, history and ages stay those of the last frame."""
        if gray.shape[::-1] != tuple(self.camera.resolution):
            w, h = self.camera.resolution
            raise ValueError(f"image is {gray.shape[1]}x{gray.shape[0]} but the camera model says {w}x{h}")
        prev, self.gray = self.gray, gray
        if step and self.frame_xy is None:
            self.frame_xy = self.xy.copy()
        elif not step:
            at_frame = self.xy if self.frame_xy is None else self.frame_xy
            self.prev_xy = at_frame.copy()
            self.hist = np.concatenate([at_frame[:, None, :], self.hist[:, :-1]], axis=1)
            self.frame_xy = None
        if prev is None or len(self) == 0:
            return 0
        p0 = self.pts.reshape(-1, 1, 2)
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev, gray, p0, None, **self._lk)
        p0r, st2, _ = cv2.calcOpticalFlowPyrLK(gray, prev, p1, None, **self._lk)
        fb = np.linalg.norm((p0r - p0).reshape(-1, 2), axis=1)
        p1 = p1.reshape(-1, 2)
        b = self.config.border
        w, h = self.camera.resolution
        inside = (p1[:, 0] >= b) & (p1[:, 0] <= w - 1 - b) & (p1[:, 1] >= b) & (p1[:, 1] <= h - 1 - b)
        ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < self.config.fb_threshold) & inside
        self.pts = p1.astype(np.float32)
        if not step:
            self.ages = self.ages + 1
        self.xy = self.camera.undistort_points(self.pts.astype(np.float64)) if len(self) else self.xy
        n_bad = int((~ok & inside).sum())
        self.keep(ok)
        return n_bad

    def enforce_spacing(self) -> None:
        """Drop the younger of two tracks closer than ``min_distance`` (tracks drift together): oldest first,
        a track is kept unless a kept one lies within ``min_distance`` pixels (rounded pixel positions)."""
        n = len(self)
        if n < 2:
            return
        r = int(self.config.min_distance)
        pairs = cKDTree(np.rint(self.pts.astype(np.float64))).query_pairs(r, output_type="ndarray")
        if pairs.shape[0] == 0:
            return
        neighbours: dict[int, list[int]] = {}
        for i, j in pairs.tolist():
            neighbours.setdefault(i, []).append(j)
            neighbours.setdefault(j, []).append(i)
        keep = np.ones(n, dtype=bool)
        blocked: set[int] = set()
        for i in sorted(neighbours, key=lambda i: (-int(self.ages[i]), i)):
            if i in blocked:
                keep[i] = False
            else:
                blocked.update(neighbours[i])
        self.keep(keep)

    def detect(self) -> None:
        """Add Shi-Tomasi corners away from the existing tracks up to ``max_features``."""
        assert self.gray is not None
        need = self.config.max_features - len(self)
        if need <= 0 or (len(self) >= self.config.refill_ratio * self.config.max_features):
            return
        w, h = self.camera.resolution
        mask = np.full((h, w), 255, dtype=np.uint8)
        r = int(self.config.min_distance)
        for x, y in np.rint(self.pts).astype(int).tolist():
            cv2.circle(mask, (x, y), r, 0, -1)
        b = self.config.border
        mask[:b, :] = 0
        mask[h - b :, :] = 0
        mask[:, :b] = 0
        mask[:, w - b :] = 0
        corners = cv2.goodFeaturesToTrack(
            self.gray, need, self.config.quality_level, self.config.min_distance, mask=mask, blockSize=3
        )
        if corners is None:
            return
        new = corners.reshape(-1, 2).astype(np.float32)
        n = new.shape[0]
        self.add(new, np.fromiter(itertools.islice(self._ids, n), np.int64, n))

    def add(self, new: NDArray[np.float32], ids: IntArray) -> None:
        """Start tracks at pixels ``new`` (N, 2) with the given ids (new ids, or another camera's)."""
        n = new.shape[0]
        self.pts = np.vstack([self.pts, new])
        self.ids = np.concatenate([self.ids, np.asarray(ids, dtype=np.int64)])
        self.ages = np.concatenate([self.ages, np.zeros(n, dtype=np.int64)])
        self.xy = np.vstack([self.xy, self.camera.undistort_points(new.astype(np.float64))])
        self.prev_xy = np.vstack([self.prev_xy, np.full((n, 2), np.nan)])
        self.hist = np.concatenate([self.hist, np.full((n, self.hist.shape[1], 2), np.nan)])

    def tracked(self) -> BoolArray:
        """Tracks that also existed in the previous frame."""
        return np.isfinite(self.prev_xy[:, 0])


class Frontend:
    """Feature tracks of a static camera, an optional gimbal camera and further cameras (module docstring).

    Args:
        static_camera: model of the static camera s (cam0).
        dynamic_camera: model of the gimbal camera d, or None (static camera only, ``mono``).
        config: parameters (default: :meth:`FrontendConfig.for_resolution` of the static camera).
        T_ds: initial estimate of static -> gimbal camera (4x4) for the matching check, or None.
        extra: further cameras of the run (run index >= 2), in the order of the images given to
            :meth:`process`; rigid ones start with their ``T_cs``, gimbal ones without an estimate.
    """

    def __init__(
        self,
        static_camera: CameraModel,
        dynamic_camera: CameraModel | None = None,
        config: FrontendConfig | None = None,
        T_ds: FloatArray | None = None,
        extra: Sequence[RunCamera] = (),
    ) -> None:
        self.config = config or FrontendConfig.for_resolution(*static_camera.resolution)
        self._ids = itertools.count()
        self.static = CameraTracker(static_camera, self.config, self._ids)
        self.dynamic = CameraTracker(dynamic_camera, self.config, self._ids) if dynamic_camera else None
        self.T_ds = None if T_ds is None else np.asarray(T_ds, dtype=float)
        self.extra_cameras = tuple(extra)
        indices = [c.index for c in self.extra_cameras]
        if len(set(indices)) != len(indices):
            raise ValueError(f"further cameras with repeated run indices: {indices}")
        self.extra = [CameraTracker(c.model, self.config, self._ids) for c in self.extra_cameras]
        #: current estimates s -> further camera (4x4), None while unknown (a gimbal camera before any estimate)
        self.extra_T_cs: list[FloatArray | None] = [
            None if c.on_gimbal else np.asarray(c.T_cs_at(None), dtype=float) for c in self.extra_cameras
        ]
        self.stats = FrontendStats()
        for c in self.extra_cameras:
            self.stats.camera_ms[c.name] = []
        self._describer = OrbDescriber()
        self._static_motion: tuple[FloatArray, FloatArray] | None = None
        self._static_pair: tuple[FloatArray, FloatArray, FloatArray] | None = None

    def _trackers(self) -> list[CameraTracker]:
        """Every tracker: static, gimbal (if any), further cameras."""
        return [self.static, *([self.dynamic] if self.dynamic is not None else []), *self.extra]

    # ------------------------------------------------------------------ per frame
    def reset(self) -> None:
        """Forget every track (e.g. after a gap in the images: KLT cannot bridge seconds); the
        next frame starts new tracks with new ids."""
        for tracker in self._trackers():
            tracker.gray = None
            tracker.keep(np.zeros(len(tracker), dtype=bool))
        self._static_motion = None
        self._static_pair = None

    def process(
        self,
        timestamp_ns: int,
        static_image: NDArray[np.generic],
        dynamic_image: NDArray[np.generic] | None = None,
        T_ds: FloatArray | None = None,
        gimbal_hint: GimbalHint | None = None,
        extra_images: Sequence[NDArray[np.generic] | None] = (),
        extra_T_cs: Sequence[FloatArray | None] | None = None,
    ) -> TrackFrame:
        """Track one synchronized frame and return its observations.

        Args:
            timestamp_ns: frame time, ns.
            static_image, dynamic_image: images (grey or BGR, 8 or 16 bit); without ``dynamic_image``
                (the gimbal camera has no image near this one) the gimbal tracks wait for its next
                image and the frame has no gimbal observations.
            T_ds: the back end's current estimate of static -> gimbal camera (4x4) for matching;
                keeps the previous estimate when None.
            gimbal_hint: if given, reject gimbal tracks right away (see :meth:`reject_dynamic`);
                by default nothing is rejected in the gimbal camera at this stage.
            extra_images: one image (or None: no image near this frame; its tracks wait for the next
                one) per further camera, in the order of ``extra`` at construction; empty: none this frame.
            extra_T_cs: current estimates s -> further camera (4x4; None entries keep the previous
                estimate), e.g. ``cam.T_cs_at(theta)`` at the predicted joint angles; None keeps all.
        """
        if T_ds is not None:
            self.T_ds = np.asarray(T_ds, dtype=float)
        images = list(extra_images) if len(extra_images) else [None] * len(self.extra)
        if len(images) != len(self.extra):
            raise ValueError(f"{len(images)} images for {len(self.extra)} further cameras")
        if extra_T_cs is not None:
            if len(extra_T_cs) != len(self.extra):
                raise ValueError(f"{len(extra_T_cs)} T_cs estimates for {len(self.extra)} further cameras")
            for k, T in enumerate(extra_T_cs):
                if T is not None:
                    self.extra_T_cs[k] = np.asarray(T, dtype=float)
        c0 = time.process_time()
        t0 = time.perf_counter()
        self.stats.fb_rejected += self.static.track(to_gray8(static_image))
        self._reject_static()
        self.static.enforce_spacing()
        self.static.detect()
        t1 = time.perf_counter()
        gimbal = self.dynamic is not None and dynamic_image is not None
        if gimbal:
            assert self.dynamic is not None and dynamic_image is not None
            self.stats.fb_rejected += self.dynamic.track(to_gray8(dynamic_image))
            if gimbal_hint is not None:
                self.reject_dynamic(gimbal_hint)
            self.dynamic.enforce_spacing()
            self.dynamic.detect()
        t2 = time.perf_counter()
        if gimbal:
            self._match()
        t3 = time.perf_counter()
        seen = [self._process_extra(k, image, gimbal) for k, image in enumerate(images)]
        t4 = time.perf_counter()
        self.stats.frames += 1
        self.stats.static_ms.append(1e3 * (t1 - t0))
        self.stats.dynamic_ms.append(1e3 * (t2 - t1))
        self.stats.match_ms.append(1e3 * (t3 - t2))
        self.stats.extra_ms.append(1e3 * (t4 - t3))
        self.stats.cpu_ms.append(1e3 * (time.process_time() - c0))
        if self.dynamic is not None and not gimbal:
            self.stats.frames_without_gimbal += 1
        return self.frame(timestamp_ns, gimbal, seen)

    def _process_extra(self, k: int, image: NDArray[np.generic] | None, gimbal: bool = False) -> bool:
        """Track further camera ``k`` into its image, reject (rigid cameras only), refill and match it
        with cam0; a camera on the gimbal is first seeded from and matched with the gimbal camera (when
        that has an image this frame, ``gimbal``): both sit on the same end effector, so their relative
        pose ``T_cd = T_cs(theta) T_ds(theta)^-1`` is known exactly whatever the joint angles. False when
        the camera has no image this frame."""
        cam, tracker = self.extra_cameras[k], self.extra[k]
        stats = self.stats
        if image is None:
            stats.camera_frames_without_image[cam.name] = stats.camera_frames_without_image.get(cam.name, 0) + 1
            return False
        t0 = time.perf_counter()
        stats.fb_rejected += tracker.track(to_gray8(image))
        if not cam.on_gimbal:
            self._reject_rigid(tracker)
        T_cs = self.extra_T_cs[k]
        seeded = 0
        T_cd = None
        if cam.on_gimbal and gimbal and T_cs is not None and self.T_ds is not None and self.dynamic is not None:
            T_cd = T_cs @ inv_se3(self.T_ds)
        if self.config.match_klt and not cam.on_gimbal and T_cs is not None:
            seeded = self._seed_from(self.static, tracker, T_cs)
        elif self.config.match_klt and T_cd is not None:
            assert self.dynamic is not None
            seeded = self._seed_from(self.dynamic, tracker, T_cd)
        stats.camera_seeded[cam.name] = stats.camera_seeded.get(cam.name, 0) + seeded
        tracker.enforce_spacing()
        tracker.detect()
        merged = split = 0
        if T_cd is not None:
            assert self.dynamic is not None
            merged, split = self._match_pair(tracker, T_cd, exact=True, first=self.dynamic)
        m, sp = self._match_pair(tracker, T_cs, exact=not cam.on_gimbal)
        merged, split = merged + m, split + sp
        stats.camera_matches[cam.name] = stats.camera_matches.get(cam.name, 0) + merged
        stats.camera_pairs_split[cam.name] = stats.camera_pairs_split.get(cam.name, 0) + split
        stats.camera_ms[cam.name].append(1e3 * (time.perf_counter() - t0))
        return True

    def track_gimbal(self, dynamic_image: NDArray[np.generic]) -> None:
        """Step the gimbal tracks through a gimbal image without a static partner (a gimbal camera
        faster than the static one): KLT and its forward-backward check only, no detection or
        matching; the next :meth:`process` continues from this image."""
        if self.dynamic is None:
            return
        self.stats.fb_rejected += self.dynamic.track(to_gray8(dynamic_image), step=True)
        self.stats.gimbal_images_between += 1

    def frame(
        self, timestamp_ns: int, with_gimbal: bool = True, with_extra: Sequence[bool] | None = None
    ) -> TrackFrame:
        """The current observations as a TrackFrame (without the gimbal camera's when ``with_gimbal``
        is False: a frame without a gimbal image; with the further cameras flagged in ``with_extra``,
        default all)."""
        s = self.static
        flags = [True] * len(self.extra) if with_extra is None else list(with_extra)
        extra = tuple(
            CameraTracks(cam.index, t.ids.copy(), t.xy.copy())
            for cam, t, on in zip(self.extra_cameras, self.extra, flags, strict=True)
            if on
        )
        if self.dynamic is None or not with_gimbal:
            return TrackFrame(int(timestamp_ns), s.ids.copy(), s.xy.copy(), extra=extra)
        d = self.dynamic
        return TrackFrame(int(timestamp_ns), s.ids.copy(), s.xy.copy(), d.ids.copy(), d.xy.copy(), extra=extra)

    def _seed_from(self, first: CameraTracker, other: CameraTracker, T_cs: FloatArray) -> int:
        """Follow the tracks of camera ``first`` that ``other`` does not share into ``other``'s image, the
        two cameras' relative pose ``T_cs`` (``first`` -> ``other``) being known exactly (a rigid camera and
        cam0, or two cameras on the gimbal's end effector): pyramidal KLT from ``first``'s image, started
        at the image of each ray at infinite depth (the baseline's parallax is left to the pyramid),
        forward-backward checked, and kept when within ``match_rigid_threshold`` pixels of the epipolar
        segment (depths >= ``match_min_depth``).  The new tracks take ``first``'s ids; returns how many."""
        s, cfg = first, self.config
        assert s.gray is not None and other.gray is not None
        cand = np.flatnonzero(~np.isin(s.ids, other.ids))
        if cand.size == 0:
            return 0
        rays = homogeneous(s.xy[cand]) @ T_cs[:3, :3].T
        front = rays[:, 2] > 1e-6
        cand, rays = cand[front], rays[front]
        if cand.size == 0:
            return 0
        guess, _ = other.camera.project(rays, jacobian=False)
        p0 = s.pts[cand].reshape(-1, 1, 2).astype(np.float32)
        p1 = guess.reshape(-1, 1, 2).astype(np.float32)
        lk = dict(other._lk, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(s.gray, other.gray, p0, p1, **lk)
        back = p0.copy()
        p0r, st2, _ = cv2.calcOpticalFlowPyrLK(other.gray, s.gray, p1, back, **lk)
        p1 = p1.reshape(-1, 2)
        fb = np.linalg.norm((p0r - p0).reshape(-1, 2), axis=1)
        b = cfg.border
        w, h = other.camera.resolution
        inside = (p1[:, 0] >= b) & (p1[:, 0] <= w - 1 - b) & (p1[:, 1] >= b) & (p1[:, 1] <= h - 1 - b)
        ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < cfg.fb_threshold) & inside
        if not np.any(ok):
            return 0
        xy = other.camera.undistort_points(p1[ok].astype(np.float64))
        f = float(np.mean(other.camera.intrinsics[:2]))
        err = depth_segment_distance(T_cs, s.xy[cand[ok]], xy, cfg.match_min_depth) * f
        good = err < cfg.match_rigid_threshold
        n = int(good.sum())
        if n:
            other.add(p1[ok][good].astype(np.float32), s.ids[cand[ok][good]])
            other.xy[-n:] = xy[good]
        return n

    # ------------------------------------------------------------------ static (rigid) cameras
    def _reject_static(self) -> None:
        """Temporal RANSAC of the static camera (:meth:`_reject_rigid`), keeping its two-view
        geometry for :meth:`static_motion`."""
        self._static_motion = None
        self._static_pair = None
        self._reject_rigid(self.static, store=True)

    def _reject_rigid(self, tracker: CameraTracker, store: bool = False) -> None:
        """Essential-matrix RANSAC between consecutive frames, and between this frame and
        ``ransac_window`` frames ago for the tracks that old (a longer baseline constrains the
        translation far better, so a small independently moving cluster that fooled the
        two-frame test is caught after at most ``ransac_window`` frames). Valid for any camera rigid
        to the body; ``store``: keep the consecutive-frame inliers as the static camera's pair."""
        keep = np.ones(len(tracker), dtype=bool)
        for lag in sorted({1, max(self.config.ransac_window, 1)}):
            x0 = tracker.prev_xy if lag == 1 else tracker.hist[:, lag - 1]
            inl = self._ransac(x0, tracker.xy, tracker.camera, store=store and lag == 1)
            if inl is not None:
                keep &= inl
        tracker.keep(keep)

    def _ransac(self, x0: FloatArray, x1: FloatArray, camera: CameraModel, store: bool) -> BoolArray | None:
        """Inlier mask over all tracks (tracks without an ``x0`` are inliers); None if not run."""
        both = np.isfinite(x0[:, 0])
        n = int(both.sum())
        if n < 8:
            return None
        a, b = x0[both], x1[both]
        f = float(np.mean(camera.intrinsics[:2]))
        if np.median(np.linalg.norm(b - a, axis=1)) * f < self.config.min_parallax:
            return None
        E, mask = cv2.findEssentialMat(
            a,
            b,
            np.eye(3),
            method=cv2.USAC_ACCURATE,
            prob=self.config.ransac_confidence,
            threshold=self.config.ransac_threshold / f,
            maxIters=1000,
        )
        if E is None or mask is None or E.shape != (3, 3):
            return None
        inl = mask.ravel().astype(bool)
        self.stats.ransac_tested += n
        self.stats.ransac_rejected += int((~inl).sum())
        if store:
            self._static_pair = (a[inl], b[inl], E)
        out = np.ones(x0.shape[0], dtype=bool)
        out[np.flatnonzero(both)[~inl]] = False
        return out

    def static_motion(self) -> tuple[FloatArray, FloatArray] | None:
        """(R, t) of the static camera between the last two frames from its tracks (|t| = 1), or
        None when the parallax was too small; maps points of the previous frame into the current."""
        if self._static_motion is None and self._static_pair is not None:
            self._static_motion = motion_from_pair(*self._static_pair)
        return self._static_motion

    # ------------------------------------------------------------------ gimbal camera
    def reject_dynamic(self, hint: GimbalHint) -> IntArray:
        """Second stage of the gimbal-camera outlier handling: remove the tracks that
        :meth:`dynamic_outliers` flags and return their ids (for the back end to drop)."""
        d = self.dynamic
        if d is None:
            return np.zeros(0, dtype=np.int64)
        bad = self.dynamic_outliers(hint)
        removed = d.ids[bad].copy()
        d.keep(~bad)
        self.stats.dynamic_rejected += int(removed.shape[0])
        return removed

    def dynamic_outliers(self, hint: GimbalHint, snapshot: DynamicSnapshot | None = None) -> BoolArray:
        """Gimbal tracks inconsistent with the extrinsics of ``hint``: :func:`gimbal_outliers` over
        the current tracks, or over the tracks of ``snapshot`` (taken with :meth:`dynamic_snapshot`)."""
        if self.dynamic is None:
            return np.zeros(0, dtype=bool)
        snap = snapshot if snapshot is not None else self.dynamic_snapshot()
        return gimbal_outliers(snap, hint, self.dynamic.camera, self.config)

    def dynamic_snapshot(self) -> DynamicSnapshot:
        """The gimbal tracks of the current frame and the static camera's two-view geometry, for a
        later :meth:`dynamic_outliers` (e.g. by a back end running a frame behind the front end)."""
        d = self.dynamic
        if d is None:
            raise ValueError("the front end has no gimbal camera")
        motion = self._static_motion
        return DynamicSnapshot(d.ids.copy(), d.prev_xy.copy(), d.xy.copy(), self._static_pair, motion)

    def _further(self, index: int) -> CameraTracker:
        """The tracker of further camera ``index`` (run index); ValueError naming the cameras there are."""
        for cam, tracker in zip(self.extra_cameras, self.extra, strict=True):
            if cam.index == index:
                return tracker
        known = ", ".join(str(c.index) for c in self.extra_cameras) or "none"
        raise ValueError(f"no further camera with run index {index} (further cameras: {known})")

    def camera_snapshot(self, index: int) -> DynamicSnapshot:
        """:meth:`dynamic_snapshot` of further camera ``index`` (a camera on a gimbal): its tracks of the
        current frame and the static camera's two-view geometry, for the second-stage outlier test
        (:func:`gimbal_outliers` with that camera's ``T_cs`` at the two frames' joint angles)."""
        t = self._further(index)
        return DynamicSnapshot(t.ids.copy(), t.prev_xy.copy(), t.xy.copy(), self._static_pair, self._static_motion)

    def drop_camera(self, index: int, ids: IntArray) -> int:
        """Stop tracking camera ``index``'s tracks with these ids (1: the gimbal camera, :meth:`drop_dynamic`;
        >= 2: a further camera); the other cameras' tracks with the same ids go on. Returns how many."""
        if index == 1:
            return self.drop_dynamic(ids)
        t = self._further(index)
        if len(ids) == 0:
            return 0
        gone = np.isin(t.ids, ids)
        t.keep(~gone)
        return int(gone.sum())

    def drop_dynamic(self, ids: IntArray) -> int:
        """Stop tracking the gimbal tracks with these ids (those still alive); returns how many."""
        d = self.dynamic
        if d is None or len(ids) == 0:
            return 0
        gone = np.isin(d.ids, ids)
        d.keep(~gone)
        self.stats.dynamic_rejected += int(gone.sum())
        return int(gone.sum())

    # ------------------------------------------------------------------ cam0 <-> other cameras
    def _match(self) -> None:
        """Match unshared static and gimbal tracks and verify every shared pair (:meth:`_match_pair`
        with the T_ds estimate)."""
        assert self.dynamic is not None
        merged, split = self._match_pair(self.dynamic, self.T_ds, exact=False)
        self.stats.matches += merged
        self.stats.pairs_split += split

    def _match_pair(
        self, other: CameraTracker, T_cs: FloatArray | None, exact: bool, first: CameraTracker | None = None
    ) -> tuple[int, int]:
        """Match unshared tracks of cam0 (or camera ``first``; ``T_cs`` then maps ``first`` into ``other``)
        and camera ``other`` and verify every shared pair geometrically.

        New descriptor matches and the pairs already sharing an id are checked together
        (:meth:`_pair_inliers`: rotation RANSAC with the translation of the ``T_cs`` estimate, or with
        ``exact`` and a ``T_cs`` the full epipolar test of each pair).  Inlier matches merge ids (the
        younger track takes the older one's id, :meth:`_rename`); shared pairs that became outliers
        (a KLT track slid onto another corner) are split by giving ``other``'s track a fresh id.
        Returns (matches merged, pairs split).
        """
        s = self.static if first is None else first
        assert s.gray is not None and other.gray is not None
        cfg = self.config
        _, sh_s, sh_c = np.intersect1d(s.ids, other.ids, return_indices=True)
        cand_s = np.flatnonzero(~np.isin(s.ids, other.ids))
        cand_c = np.flatnonzero(~np.isin(other.ids, s.ids))
        new_s = new_c = np.zeros(0, dtype=np.int64)
        if cand_s.size and cand_c.size and self.stats.frames % max(cfg.match_every, 1) == 0:
            ks, desc_s = self._describer.describe(s.gray, s.pts[cand_s].astype(np.float64))
            kc, desc_c = self._describer.describe(other.gray, other.pts[cand_c].astype(np.float64))
            ma, mb, _ = mutual_ratio_matches(desc_s, desc_c, cfg.match_ratio, cfg.match_max_hamming)
            new_s, new_c = cand_s[ks[ma]], cand_c[kc[mb]]
        i_s = np.concatenate([sh_s.astype(np.int64), new_s])
        i_c = np.concatenate([sh_c.astype(np.int64), new_c])
        if i_s.size == 0:
            return 0, 0
        n_sh = sh_s.size
        ok = self._pair_inliers(s.xy[i_s], other.xy[i_c], other.camera, T_cs, exact, n_sh)
        bad = i_c[:n_sh][~ok[:n_sh]]
        if bad.size:
            other.ids[bad] = np.fromiter(itertools.islice(self._ids, bad.size), np.int64, bad.size)
            other.ages[bad] = 0
        m_s, m_c = i_s[n_sh:][ok[n_sh:]], i_c[n_sh:][ok[n_sh:]]
        younger_c = other.ages[m_c] <= s.ages[m_s]
        self._rename(other, m_c[younger_c], s.ids[m_s[younger_c]])
        self._rename(s, m_s[~younger_c], other.ids[m_c[~younger_c]])
        return int(m_s.size), int(bad.size)

    def _pair_inliers(
        self,
        xy_s: FloatArray,
        xy_c: FloatArray,
        camera: CameraModel,
        T_cs: FloatArray | None,
        exact: bool,
        n_shared: int,
    ) -> BoolArray:
        """Which cam0 <-> camera c correspondences (normalized, cam0 first; the first ``n_shared``
        already share an id) are geometrically consistent.

        ``exact`` with a ``T_cs`` (a rigid camera whose extrinsics are known): each pair on its own,
        distance from the epipolar segment of the cam0 ray (depths >= ``match_min_depth``) below
        ``match_rigid_threshold`` pixels of ``camera``.  Otherwise (extrinsics that change with the
        joint angles): one rotation RANSAC with the translation of ``T_cs`` (pure rotation without
        one); with fewer than ``min_pairs`` pairs the ``T_cs`` estimate alone decides, and without
        one only the shared pairs are kept.
        """
        cfg = self.config
        if exact and T_cs is not None:
            f = float(np.mean(camera.intrinsics[:2]))
            return depth_segment_distance(T_cs, xy_s, xy_c, cfg.match_min_depth) * f < cfg.match_rigid_threshold
        t_cs = None if T_cs is None else T_cs[:3, 3]
        if xy_s.shape[0] >= cfg.min_pairs:
            thr = cfg.match_epipolar_threshold if t_cs is not None else cfg.match_rotation_threshold
            R, ok = rotation_ransac(xy_s, xy_c, thr, t_cs, cfg.match_min_depth, seed=self.stats.frames)
            if R is None:
                ok = np.zeros(xy_s.shape[0], dtype=bool)
        elif T_cs is not None:
            err = depth_segment_distance(T_cs, xy_s, xy_c, cfg.match_min_depth)
            ok = err < cfg.match_epipolar_threshold
        else:
            ok = np.zeros(xy_s.shape[0], dtype=bool)
            ok[:n_shared] = True  # too few pairs to judge: keep the existing ones
        return ok

    def _rename(self, tracker: CameraTracker, idx: IntArray, new_ids: IntArray) -> None:
        """Give tracks ``idx`` of ``tracker`` the ids ``new_ids``; tracks of the other cameras that
        shared an old id follow (unless that camera holds the new id already), so a merge with cam0
        keeps the links of cam0's track to the gimbal and further cameras."""
        if idx.size == 0:
            return
        old = tracker.ids[idx].copy()
        tracker.ids[idx] = new_ids
        for other in self._trackers():
            if other is tracker or len(other) == 0:
                continue
            hit = np.flatnonzero(np.isin(other.ids, old))
            if hit.size == 0:
                continue
            mapping = dict(zip(old.tolist(), np.asarray(new_ids).tolist(), strict=True))
            present = set(other.ids.tolist())
            for i in hit:
                new = mapping[int(other.ids[i])]
                if new not in present:
                    other.ids[i] = new
                    present.add(new)
