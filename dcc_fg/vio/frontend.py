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

Output: a :class:`~dcc_fg.data.vio.TrackFrame` of undistorted normalized coordinates
(:meth:`CameraModel.undistort_points`).  Pixels follow OpenCV's convention.  Times in ns.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from dcc_fg.data.vio import TrackFrame
from dcc_fg.detection import to_gray8
from dcc_fg.vio.epipolar import (
    depth_segment_distance,
    essential,
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

    def summary(self) -> dict[str, float]:
        def med(x: list[float]) -> float:
            return float(np.median(x)) if x else 0.0

        total = [a + b + c for a, b, c in zip(self.static_ms, self.dynamic_ms, self.match_ms, strict=True)]
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
        }


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
        """Drop the younger of two tracks closer than ``min_distance`` (tracks drift together)."""
        if len(self) < 2:
            return
        order = np.argsort(-self.ages, kind="stable")
        w, h = self.camera.resolution
        mask = np.full((h, w), 255, dtype=np.uint8)
        keep = np.zeros(len(self), dtype=bool)
        r = int(self.config.min_distance)
        for i in order:
            x, y = int(round(float(self.pts[i, 0]))), int(round(float(self.pts[i, 1])))
            if mask[min(max(y, 0), h - 1), min(max(x, 0), w - 1)]:
                keep[i] = True
                cv2.circle(mask, (x, y), r, 0, -1)
        self._mask = mask
        self.keep(keep)

    def detect(self) -> None:
        """Add Shi-Tomasi corners away from the existing tracks up to ``max_features``."""
        assert self.gray is not None
        need = self.config.max_features - len(self)
        if need <= 0 or (len(self) >= self.config.refill_ratio * self.config.max_features):
            return
        w, h = self.camera.resolution
        mask = getattr(self, "_mask", None)
        if mask is None or mask.shape != (h, w) or len(self) < 2:
            mask = np.full((h, w), 255, dtype=np.uint8)
            r = int(self.config.min_distance)
            for x, y in self.pts:
                cv2.circle(mask, (int(round(float(x))), int(round(float(y)))), r, 0, -1)
        b = self.config.border
        mask[:b, :] = 0
        mask[h - b :, :] = 0
        mask[:, :b] = 0
        mask[:, w - b :] = 0
        corners = cv2.goodFeaturesToTrack(
            self.gray, need, self.config.quality_level, self.config.min_distance, mask=mask, blockSize=3
        )
        self._mask = None
        if corners is None:
            return
        new = corners.reshape(-1, 2).astype(np.float32)
        n = new.shape[0]
        self.pts = np.vstack([self.pts, new])
        self.ids = np.concatenate([self.ids, np.fromiter(itertools.islice(self._ids, n), np.int64, n)])
        self.ages = np.concatenate([self.ages, np.zeros(n, dtype=np.int64)])
        self.xy = np.vstack([self.xy, self.camera.undistort_points(new.astype(np.float64))])
        self.prev_xy = np.vstack([self.prev_xy, np.full((n, 2), np.nan)])
        self.hist = np.concatenate([self.hist, np.full((n, self.hist.shape[1], 2), np.nan)])

    def tracked(self) -> BoolArray:
        """Tracks that also existed in the previous frame."""
        return np.isfinite(self.prev_xy[:, 0])


class Frontend:
    """Feature tracks of a static camera and an optional gimbal camera (see the module docstring).

    Args:
        static_camera: model of the static camera s.
        dynamic_camera: model of the gimbal camera d, or None (static camera only, ``mono``).
        config: parameters (default: :meth:`FrontendConfig.for_resolution` of the static camera).
        T_ds: initial estimate of static -> gimbal camera (4x4) for the matching check, or None.
    """

    def __init__(
        self,
        static_camera: CameraModel,
        dynamic_camera: CameraModel | None = None,
        config: FrontendConfig | None = None,
        T_ds: FloatArray | None = None,
    ) -> None:
        self.config = config or FrontendConfig.for_resolution(*static_camera.resolution)
        self._ids = itertools.count()
        self.static = CameraTracker(static_camera, self.config, self._ids)
        self.dynamic = CameraTracker(dynamic_camera, self.config, self._ids) if dynamic_camera else None
        self.T_ds = None if T_ds is None else np.asarray(T_ds, dtype=float)
        self.stats = FrontendStats()
        self._describer = OrbDescriber()
        self._static_motion: tuple[FloatArray, FloatArray] | None = None
        self._static_pair: tuple[FloatArray, FloatArray, FloatArray] | None = None

    # ------------------------------------------------------------------ per frame
    def reset(self) -> None:
        """Forget every track (e.g. after a gap in the images: KLT cannot bridge seconds); the
        next frame starts new tracks with new ids."""
        for tracker in (self.static, self.dynamic):
            if tracker is not None:
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
    ) -> TrackFrame:
        """Track one synchronized frame pair and return its observations.

        Args:
            timestamp_ns: frame time, ns.
            static_image, dynamic_image: images (grey or BGR, 8 or 16 bit); without ``dynamic_image``
                (the gimbal camera has no image near this one) the gimbal tracks wait for its next
                image and the frame has no gimbal observations.
            T_ds: the back end's current estimate of static -> gimbal camera (4x4) for matching;
                keeps the previous estimate when None.
            gimbal_hint: if given, reject gimbal tracks right away (see :meth:`reject_dynamic`);
                by default nothing is rejected in the gimbal camera at this stage.
        """
        if T_ds is not None:
            self.T_ds = np.asarray(T_ds, dtype=float)
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
        self.stats.frames += 1
        self.stats.static_ms.append(1e3 * (t1 - t0))
        self.stats.dynamic_ms.append(1e3 * (t2 - t1))
        self.stats.match_ms.append(1e3 * (t3 - t2))
        self.stats.cpu_ms.append(1e3 * (time.process_time() - c0))
        if self.dynamic is not None and not gimbal:
            self.stats.frames_without_gimbal += 1
        return self.frame(timestamp_ns, gimbal)

    def track_gimbal(self, dynamic_image: NDArray[np.generic]) -> None:
        """Step the gimbal tracks through a gimbal image without a static partner (a gimbal camera
        faster than the static one): KLT and its forward-backward check only, no detection or
        matching; the next :meth:`process` continues from this image."""
        if self.dynamic is None:
            return
        self.stats.fb_rejected += self.dynamic.track(to_gray8(dynamic_image), step=True)
        self.stats.gimbal_images_between += 1

    def frame(self, timestamp_ns: int, with_gimbal: bool = True) -> TrackFrame:
        """The current observations as a TrackFrame (without the gimbal camera's when ``with_gimbal``
        is False: a frame without a gimbal image)."""
        s = self.static
        if self.dynamic is None or not with_gimbal:
            return TrackFrame(int(timestamp_ns), s.ids.copy(), s.xy.copy())
        d = self.dynamic
        return TrackFrame(int(timestamp_ns), s.ids.copy(), s.xy.copy(), d.ids.copy(), d.xy.copy())

    # ------------------------------------------------------------------ static camera
    def _reject_static(self) -> None:
        """Essential-matrix RANSAC between consecutive frames, and between this frame and
        ``ransac_window`` frames ago for the tracks that old (a longer baseline constrains the
        translation far better, so a small independently moving cluster that fooled the
        two-frame test is caught after at most ``ransac_window`` frames)."""
        s = self.static
        self._static_motion = None
        self._static_pair = None
        keep = np.ones(len(s), dtype=bool)
        for lag in sorted({1, max(self.config.ransac_window, 1)}):
            x0 = s.prev_xy if lag == 1 else s.hist[:, lag - 1]
            inl = self._ransac(x0, s.xy, s.camera, store=lag == 1)
            if inl is not None:
                keep &= inl
        s.keep(keep)

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

    def drop_dynamic(self, ids: IntArray) -> int:
        """Stop tracking the gimbal tracks with these ids (those still alive); returns how many."""
        d = self.dynamic
        if d is None or len(ids) == 0:
            return 0
        gone = np.isin(d.ids, ids)
        d.keep(~gone)
        self.stats.dynamic_rejected += int(gone.sum())
        return int(gone.sum())

    # ------------------------------------------------------------------ static <-> gimbal
    def _match(self) -> None:
        """Match unshared tracks across the cameras and verify every shared pair geometrically.

        New descriptor matches and the pairs already sharing an id go through one rotation
        RANSAC (translation from the T_ds estimate when there is one, so only the rotation,
        which the joint angles change most, comes from the data).  Inlier matches merge ids;
        shared pairs that became outliers (a KLT track slid onto another corner) are split by
        giving the gimbal track a fresh id.  With fewer than ``min_pairs`` pairs the T_ds
        estimate alone decides (nothing new is merged without one).
        """
        s, d = self.static, self.dynamic
        assert d is not None and s.gray is not None and d.gray is not None
        cfg = self.config
        _, sh_s, sh_d = np.intersect1d(s.ids, d.ids, return_indices=True)
        cand_s = np.flatnonzero(~np.isin(s.ids, d.ids))
        cand_d = np.flatnonzero(~np.isin(d.ids, s.ids))
        new_s = new_d = np.zeros(0, dtype=np.int64)
        if cand_s.size and cand_d.size and self.stats.frames % max(cfg.match_every, 1) == 0:
            ks, desc_s = self._describer.describe(s.gray, s.pts[cand_s].astype(np.float64))
            kd, desc_d = self._describer.describe(d.gray, d.pts[cand_d].astype(np.float64))
            ma, mb, _ = mutual_ratio_matches(desc_s, desc_d, cfg.match_ratio, cfg.match_max_hamming)
            new_s, new_d = cand_s[ks[ma]], cand_d[kd[mb]]
        i_s = np.concatenate([sh_s.astype(np.int64), new_s])
        i_d = np.concatenate([sh_d.astype(np.int64), new_d])
        if i_s.size == 0:
            return
        t_ds = None if self.T_ds is None else self.T_ds[:3, 3]
        if i_s.size >= cfg.min_pairs:
            thr = cfg.match_epipolar_threshold if t_ds is not None else cfg.match_rotation_threshold
            R, ok = rotation_ransac(s.xy[i_s], d.xy[i_d], thr, t_ds, cfg.match_min_depth, seed=self.stats.frames)
            if R is None:
                ok = np.zeros(i_s.size, dtype=bool)
        elif self.T_ds is not None:
            err = depth_segment_distance(self.T_ds, s.xy[i_s], d.xy[i_d], cfg.match_min_depth)
            ok = err < cfg.match_epipolar_threshold
        else:
            ok = np.zeros(i_s.size, dtype=bool)
            ok[: sh_s.size] = True  # too few pairs to judge: keep the existing ones
        n_sh = sh_s.size
        bad = i_d[:n_sh][~ok[:n_sh]]
        if bad.size:
            d.ids[bad] = np.fromiter(itertools.islice(self._ids, bad.size), np.int64, bad.size)
            d.ages[bad] = 0
            self.stats.pairs_split += int(bad.size)
        m_s, m_d = i_s[n_sh:][ok[n_sh:]], i_d[n_sh:][ok[n_sh:]]
        younger_d = d.ages[m_d] <= s.ages[m_s]
        d.ids[m_d[younger_d]] = s.ids[m_s[younger_d]]
        s.ids[m_s[~younger_d]] = d.ids[m_d[~younger_d]]
        self.stats.matches += int(m_s.size)
