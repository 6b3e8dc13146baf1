"""Landmark management: track bookkeeping, triangulation and landmark quality checks.

Tracks arrive as :class:`~dcc_fg.data.vio.TrackFrame` ids (one id space across both cameras) with
undistorted normalized coordinates. A track that is not yet a landmark is buffered as
(keyframe, camera 0 static / 1 gimbal, xy) observations; once it spans ``min_track_keyframes``
keyframes it is triangulated (linear DLT) and kept if the point is finite, within depth limits, in
front of every camera, reprojects within ``triangulation_gate`` sigmas and has
``min_parallax_deg`` of parallax. Landmarks are Point3 in W (m); a landmark is forgotten once its
last observation leaves the window. Camera poses ``T_Wc`` map camera points into W.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import gtsam
import numpy as np
from numpy.typing import NDArray

from dcc_fg.data.vio import TrackFrame
from dcc_fg.vio.backend.keys import landmark_key
from dcc_fg.vio.backend.options import FloatArray, VioOptions

Observation = tuple[int, int, FloatArray]  # (keyframe, camera 0 static / 1 gimbal, normalized xy)


def validate_frames(frames: list[TrackFrame], source: str = "tracks") -> None:
    """Frames must be time-ordered with matching id/coordinate counts and finite coordinates."""
    if not frames:
        raise ValueError(f"{source}: no camera frames")
    last = None
    for i, f in enumerate(frames):
        if last is not None and f.timestamp_ns <= last:
            raise ValueError(f"{source}: frame {i} timestamp {f.timestamp_ns} is not after {last}")
        last = f.timestamp_ns
        views = [("static", f.static_ids, f.static_xy), ("dynamic", f.dynamic_ids, f.dynamic_xy)]
        views += [(f"camera {c.camera}", c.ids, c.xy) for c in f.extra]
        for cam, ids, xy in views:
            if xy.shape != (ids.shape[0], 2):
                raise ValueError(f"{source}: frame {i} {cam}: {ids.shape[0]} ids but xy has shape {xy.shape}")
            if not np.all(np.isfinite(xy)):
                raise ValueError(f"{source}: frame {i} {cam}: non-finite coordinates")


def triangulate_batch(T_Wc: FloatArray, xy: FloatArray) -> FloatArray:
    """Linear (DLT) triangulation of N points, each from M camera poses ``T_Wc`` (N, M, 4, 4) and
    normalized ``xy`` (N, M, 2); (N, 3) points in W, NaN where the solution is at infinity."""
    R_cW = np.swapaxes(T_Wc[..., :3, :3], -1, -2)
    P = np.concatenate([R_cW, -R_cW @ T_Wc[..., :3, 3:4]], axis=-1)  # (N, M, 3, 4) = [R_cW | t_cW]
    A = np.concatenate([xy[..., :1] * P[..., 2, :] - P[..., 0, :], xy[..., 1:2] * P[..., 2, :] - P[..., 1, :]], axis=1)
    _, _, vt = np.linalg.svd(A)
    h = vt[:, -1, :]
    out = np.full((h.shape[0], 3), np.nan)
    finite = np.abs(h[:, 3]) >= 1e-12
    out[finite] = h[finite, :3] / h[finite, 3:4]
    return out


def triangulate(T_Wc: FloatArray, xy: FloatArray) -> FloatArray:
    """Linear (DLT) triangulation of one point from camera poses T_Wc (M, 4, 4) and normalized xy (M, 2)."""
    return triangulate_batch(T_Wc[None], xy[None])[0]


def landmarks_are_good(p: FloatArray, T_Wc: FloatArray, xy: FloatArray, options: VioOptions) -> NDArray[np.bool_]:
    """:func:`landmark_is_good` of N points ``p`` (N, 3) seen at ``xy`` (N, M, 2) from ``T_Wc`` (N, M, 4, 4)."""
    o = options
    ok = np.all(np.isfinite(p), axis=1)
    q = np.where(ok[:, None], p, 0.0)
    rays = q[:, None, :] - T_Wc[..., :3, 3]  # (N, M, 3)
    dist = np.linalg.norm(rays, axis=2)
    ok &= ~np.any((dist > o.max_depth) | (dist < 0.2), axis=1)
    p_c = np.einsum("nmji,nmj->nmi", T_Wc[..., :3, :3], rays)
    ok &= ~np.any(p_c[..., 2] <= 0.1, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.linalg.norm(p_c[..., :2] / p_c[..., 2:3] - xy, axis=2)
        u = rays / dist[..., None]
    ok &= ~(np.max(np.where(np.isfinite(err), err, np.inf), axis=1) > o.triangulation_gate * o.sigma)
    cosang = np.clip(np.einsum("nmi,nki->nmk", u, u), -1.0, 1.0)
    with np.errstate(invalid="ignore"):
        parallax = np.degrees(np.arccos(np.nanmin(cosang.reshape(len(p), -1), axis=1)))
    return ok & (parallax >= o.min_parallax_deg)


def landmark_is_good(p: FloatArray, T_Wc: FloatArray, xy: FloatArray, options: VioOptions) -> bool:
    """Quality checks of a triangulated point ``p`` (W) seen at ``xy`` (M, 2) from ``T_Wc`` (M, 4, 4):
    finite; 0.2 m <= distance <= ``max_depth``; depth > 0.1 m in every camera; reprojection error
    within ``triangulation_gate * sigma``; largest angle between the rays >= ``min_parallax_deg``."""
    return bool(landmarks_are_good(np.asarray(p, float)[None], T_Wc[None], xy[None], options)[0])


def prediction_errors(T_cW: FloatArray, p_W: FloatArray, z: FloatArray) -> FloatArray:
    """Distances (normalized units) of landmarks ``p_W`` (N, 3, in W)'s projections in camera ``T_cW``
    (W -> camera) from their observations ``z`` (N, 2); inf for a landmark behind the camera."""
    p_c = p_W @ T_cW[:3, :3].T + T_cW[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.linalg.norm(p_c[:, :2] / p_c[:, 2:3] - z, axis=1)
    return np.where(p_c[:, 2] <= 0, np.inf, err)


def _attempts(obs: list[Observation], rigid: frozenset[int] = frozenset({0})) -> list[list[Observation]]:
    """The observation sets a track is triangulated from, in order: its observations by cameras rigid to
    the body (``rigid``: run indices, cam0 and rigid further cameras), then all of them (only when they
    add a gimbal view); a set needs two distinct (keyframe, camera) views."""
    static_obs = [ob for ob in obs if ob[1] in rigid]
    out = []
    for use in (static_obs, obs):
        if len({(ob[0], ob[1]) for ob in use}) < 2 or (use is obs and len(use) == len(static_obs)):
            continue
        out.append(use)
    return out


def triangulate_tracks(
    tracks: list[list[Observation]],
    camera_pose: Callable[[int, int], FloatArray],
    options: VioOptions,
    rigid: frozenset[int] = frozenset({0}),
) -> list[tuple[FloatArray, bool]]:
    """:func:`triangulate_track` of many tracks, the DLT and the checks batched over the tracks with the
    same number of observations (the same arithmetic per track, without a Python loop per point).
    ``rigid``: run indices of the cameras rigid to the body (preferred, :func:`_attempts`)."""
    out: list[tuple[FloatArray, bool]] = [(np.full(3, np.nan), False) for _ in tracks]
    attempts = [_attempts(obs, rigid) for obs in tracks]
    for stage in (0, 1):
        # tracks still without a good point that have a set for this stage, grouped by its size
        groups: dict[int, list[int]] = {}
        for n, sets in enumerate(attempts):
            if stage < len(sets) and not out[n][1]:
                groups.setdefault(len(sets[stage]), []).append(n)
        for members in groups.values():
            T_Wc = np.array([[camera_pose(kk, cam) for kk, cam, _ in attempts[n][stage]] for n in members])
            xy = np.array([[z for _, _, z in attempts[n][stage]] for n in members])
            points = triangulate_batch(T_Wc, xy)
            good = landmarks_are_good(points, T_Wc, xy, options)
            for n, point, ok in zip(members, points, good, strict=True):
                out[n] = (point, bool(ok))
    return out


def triangulate_track(
    obs: list[Observation], camera_pose: Callable[[int, int], FloatArray], options: VioOptions
) -> tuple[FloatArray, bool]:
    """Triangulate a track from its static observations, else from both cameras; (point, good).

    Static observations do not depend on the (uncertain) joint angles, so they are preferred; both
    cameras together give a stereo baseline (what gives landmarks while the body stands still).
    ``camera_pose(k, cam)`` is ``T_Wc`` of camera ``cam`` at keyframe ``k``.
    """
    return triangulate_tracks([obs], camera_pose, options)[0]


@dataclass
class Track:
    """Buffered observations of a not-yet-triangulated landmark: (keyframe, camera 0/1, xy)."""

    obs: list[Observation] = field(default_factory=list)


@dataclass
class NewLandmark:
    """A landmark made from a track: its index, position in W (m) and the track's observations."""

    index: int
    p_W: FloatArray
    obs: list[Observation]


class LandmarkMap:
    """Tracks waiting for triangulation and the landmarks in the window.

    ``active`` maps track id -> landmark index, ``position`` landmark index -> Point3 in W,
    ``last_seen_ns`` landmark index -> time of its newest observation; ``count`` landmarks made.
    ``first_ns`` landmark index -> time of the oldest keyframe that saw it when it was made; ``persistent``
    the landmarks that stay in the window while they are seen: every one with ``persist`` ``all``, those a
    camera on a gimbal saw with ``gimbal``; the others leave with that oldest keyframe (:meth:`stamp_ns`).
    ``rigid``: run indices of the cameras rigid to the body. A track seen by two of them in one keyframe
    (a static stereo pair) is ready at once, without waiting for ``min_track_keyframes``: the baseline
    between the cameras makes it metric.
    """

    def __init__(self, rigid: frozenset[int] = frozenset({0}), persist: str = "all") -> None:
        self.rigid = rigid
        self.persist = persist
        self.tracks: dict[int, Track] = {}
        self.active: dict[int, int] = {}
        self.position: dict[int, FloatArray] = {}
        self.last_seen_ns: dict[int, int] = {}
        self.first_ns: dict[int, int] = {}
        self.persistent: set[int] = set()
        self.count = 0

    def clear(self) -> None:
        """Forget every landmark and buffered track (the landmark count continues)."""
        self.active.clear()
        self.position.clear()
        self.tracks.clear()
        self.persistent.clear()

    def stamp_ns(self, lm: int) -> int:
        """The time the smoother's window gives landmark ``lm`` (it is marginalized once that time is more
        than the lag old): its newest observation for a persistent landmark, else the time of the oldest
        keyframe that saw it when it was made, so that it leaves the window with that keyframe and its
        other observations become a prior on the keyframe states instead of tying every landmark the
        leaving keyframe saw into one dense marginal (``VioOptions.persistent_landmarks``)."""
        return self.last_seen_ns[lm] if lm in self.persistent else self.first_ns[lm]

    def buffer(self, track_id: int, k: int, cam: int, z: FloatArray) -> None:
        """Remember an observation of a track that is not a landmark yet."""
        self.tracks.setdefault(track_id, Track()).obs.append((k, cam, z))

    def add(
        self, track_id: int, p_W: FloatArray, t_ns: int, first_ns: int | None = None, persistent: bool = True
    ) -> int:
        """Make track ``track_id`` landmark number :attr:`count` at ``p_W``, seen last at ``t_ns`` and first
        (oldest keyframe of its observations) at ``first_ns`` (default ``t_ns``); returns its index.
        ``persistent``: it stays in the window while it is seen (:meth:`stamp_ns`)."""
        lm = self.count
        self.count += 1
        self.active[track_id] = lm
        self.position[lm] = p_W
        self.last_seen_ns[lm] = t_ns
        self.first_ns[lm] = t_ns if first_ns is None else first_ns
        if persistent:
            self.persistent.add(lm)
        return lm

    def triangulate_ready(
        self,
        k: int,
        t_ns: int,
        keyframe_times: dict[int, int],
        window_start_ns: int,
        camera_pose: Callable[[int, int], FloatArray],
        options: VioOptions,
    ) -> list[NewLandmark]:
        """Landmarks from the tracks seen in keyframe ``k`` (at ``t_ns``) that are ready.

        Observations of keyframes before ``window_start_ns`` are dropped first; a track that ended
        is dropped if it can never become ready, one that never triangulates well after
        ``3 * min_track_keyframes`` keyframes is given up; at most ``max_new_landmarks`` are made.
        """
        o = options
        made: list[NewLandmark] = []
        memo: dict[tuple[int, int], FloatArray] = {}  # camera poses of the window's keyframes

        def pose(kk: int, cam: int) -> FloatArray:
            if (kk, cam) not in memo:
                memo[(kk, cam)] = camera_pose(kk, cam)
            return memo[(kk, cam)]

        ready: list[tuple[int, int]] = []  # (track id, keyframes it spans), in track order
        for tid in list(self.tracks):
            tr = self.tracks[tid]
            tr.obs = [ob for ob in tr.obs if keyframe_times[ob[0]] >= window_start_ns]
            if not tr.obs:
                del self.tracks[tid]
                continue
            kfs = {ob[0] for ob in tr.obs}
            if tr.obs[-1][0] != k:
                # not seen in this keyframe: the track ended; drop it if it can never become ready
                if len(kfs) < o.min_track_keyframes:
                    del self.tracks[tid]
                continue
            if len(kfs) >= o.min_track_keyframes or self._stereo(tr.obs, k):
                ready.append((tid, len(kfs)))
        # every ready track is triangulated at once (batched); in track order, the good ones become
        # landmarks until max_new_landmarks are made; the tracks after that are left as they are
        results = triangulate_tracks([self.tracks[tid].obs for tid, _ in ready], pose, o, self.rigid)
        for (tid, n_kf), (p, ok) in zip(ready, results, strict=True):
            if len(made) >= o.max_new_landmarks:
                break
            if not ok:
                if n_kf > 3 * o.min_track_keyframes:
                    del self.tracks[tid]  # never converges: give up on this track
                continue
            obs = self.tracks[tid].obs
            first_ns = keyframe_times[min(ob[0] for ob in obs)]
            persistent = self.persist == "all" or (
                self.persist == "gimbal" and any(cam not in self.rigid for _, cam, _ in obs)
            )
            made.append(NewLandmark(self.add(tid, p, t_ns, first_ns, persistent), p, obs))
            del self.tracks[tid]
        return made

    def _stereo(self, obs: list[Observation], k: int) -> bool:
        """Whether two rigid cameras saw the track in keyframe ``k``."""
        return len(self.rigid) > 1 and len({ob[1] for ob in obs if ob[0] == k and ob[1] in self.rigid}) >= 2

    def refresh_from(self, positions: dict[int, FloatArray], cutoff_ns: int, missing_leave: bool = False) -> list[int]:
        """Positions (W, m) where ``positions`` has one (structureless landmarks: their factors'
        triangulation); forget (and return) the landmarks last seen before ``cutoff_ns`` and, with
        ``missing_leave``, those without a position."""
        gone = []
        for tid, lm in list(self.active.items()):
            if lm in positions:
                self.position[lm] = positions[lm]
            if self.last_seen_ns[lm] < cutoff_ns or (missing_leave and lm not in positions):
                del self.active[tid]
                self.position.pop(lm, None)
                self.persistent.discard(lm)
                gone.append(lm)
        return gone

    def refresh(self, estimate: gtsam.Values, cutoff_ns: int) -> None:
        """Positions from the smoother's estimate; forget landmarks that left it or were last seen
        before ``cutoff_ns``."""
        positions = {
            lm: estimate.atPoint3(landmark_key(lm)) for lm in self.active.values() if estimate.exists(landmark_key(lm))
        }
        self.refresh_from(positions, cutoff_ns, missing_leave=True)
