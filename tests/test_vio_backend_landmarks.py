"""Landmark management of the smoother on synthetic views: quality checks, gating, track bookkeeping."""

from __future__ import annotations

import gtsam
import numpy as np

from dcc_fg.vio.backend.keys import landmark_key
from dcc_fg.vio.backend.landmarks import (
    LandmarkMap,
    landmark_is_good,
    prediction_errors,
    triangulate_track,
    triangulate_tracks,
)
from dcc_fg.vio.backend.options import VioOptions
from factors.chain import inv_se3

OPT = VioOptions(mode="mono")


def _camera(x: float) -> np.ndarray:
    """Camera looking along +z of W from (x, 0, 0)."""
    T = np.eye(4)
    T[0, 3] = x
    return T


def _project(T_Wc: np.ndarray, p_W: np.ndarray) -> np.ndarray:
    T_cW = inv_se3(T_Wc)
    p_c = T_cW[:3, :3] @ p_W + T_cW[:3, 3]
    return p_c[:2] / p_c[2]


def test_quality_checks() -> None:
    p = np.array([0.2, -0.1, 5.0])
    T_Wc = np.array([_camera(x) for x in (0.0, 0.2, 0.4)])
    xy = np.array([_project(T, p) for T in T_Wc])
    assert landmark_is_good(p, T_Wc, xy, OPT)
    assert not landmark_is_good(np.full(3, np.nan), T_Wc, xy, OPT)
    assert not landmark_is_good(p, T_Wc, xy + 10 * OPT.triangulation_gate * OPT.sigma, OPT)  # reprojection
    far = np.array([0.2, -0.1, 80.0])  # beyond max_depth
    assert not landmark_is_good(far, T_Wc, np.array([_project(T, far) for T in T_Wc]), OPT)
    behind = np.array([0.2, -0.1, -5.0])
    assert not landmark_is_good(behind, T_Wc, np.array([_project(T, behind) for T in T_Wc]), OPT)
    narrow = np.array([_camera(x) for x in (0.0, 0.01, 0.02)])  # 0.2 deg of parallax
    assert not landmark_is_good(p, narrow, np.array([_project(T, p) for T in narrow]), OPT)


def _prediction_error(T_cW: np.ndarray, p_W: np.ndarray, z: np.ndarray) -> float:
    """One observation's predicted error, written out (the reference of the batched one)."""
    p_c = T_cW[:3, :3] @ p_W + T_cW[:3, 3]
    return float("inf") if p_c[2] <= 0 else float(np.linalg.norm(p_c[:2] / p_c[2] - z))


def test_observation_gate() -> None:
    p = np.array([0.0, 0.0, 4.0])
    T_cW = inv_se3(_camera(0.0))
    err = prediction_errors(T_cW, np.array([p, p, -p]), np.array([[0.0, 0.0], [0.02, 0.0], [0.0, 0.0]]))
    assert not err[0] > 0.01
    assert err[1] > 0.01
    assert err[2] > 0.01  # behind the camera


def test_batched_prediction_errors_equal_one_at_a_time() -> None:
    """Random camera, landmarks in front and behind, observations with random errors."""
    rng = np.random.default_rng(4)
    for _ in range(20):
        R = gtsam.Rot3.Expmap(rng.normal(0, 1, 3)).matrix()
        T_cW = np.eye(4)
        T_cW[:3, :3], T_cW[:3, 3] = R, rng.normal(0, 1, 3)
        p_W = rng.normal(0, 5, (30, 3))
        z = rng.normal(0, 0.5, (30, 2))
        one = np.array([_prediction_error(T_cW, p, zz) for p, zz in zip(p_W, z, strict=True)])
        batch = prediction_errors(T_cW, p_W, z)
        assert np.isinf(one).any() and np.isfinite(one).any()
        np.testing.assert_array_equal(np.isinf(batch), np.isinf(one))
        np.testing.assert_allclose(batch[np.isfinite(one)], one[np.isfinite(one)], rtol=1e-12, atol=1e-15)
    assert prediction_errors(np.eye(4), np.zeros((0, 3)), np.zeros((0, 2))).shape == (0,)


def test_landmark_persistence_policy() -> None:
    """``all``: a landmark's window time is its newest observation; ``gimbal``: only landmarks a gimbal camera
    saw keep that, a static-only one keeps the time of its oldest keyframe and leaves the window with it."""
    p = np.array([0.3, 0.2, 6.0])
    poses = {(k, cam): _camera(0.3 * k + 0.25 * cam) for k in range(3) for cam in (0, 1)}
    times = {k: 100 * (k + 1) for k in range(3)}

    def camera_pose(k: int, cam: int) -> np.ndarray:
        return poses[(k, cam)]

    for persist, static_only_stamp in (("all", 300), ("gimbal", 100), ("none", 100)):
        lms = LandmarkMap(persist=persist)
        for k in range(3):
            lms.buffer(1, k, 0, _project(poses[(k, 0)], p))  # static camera only
            lms.buffer(2, k, 0, _project(poses[(k, 0)], p))  # both cameras
            lms.buffer(2, k, 1, _project(poses[(k, 1)], p))
        made = {m.index: m for m in lms.triangulate_ready(2, times[2], times, 0, camera_pose, OPT)}
        static_lm, shared_lm = lms.active[1], lms.active[2]
        assert set(made) == {static_lm, shared_lm}
        assert lms.first_ns[static_lm] == 100 and lms.last_seen_ns[static_lm] == 300
        assert lms.stamp_ns(static_lm) == static_only_stamp
        assert lms.stamp_ns(shared_lm) == (100 if persist == "none" else 300)
        lms.refresh_from({}, 10_000)  # both leave: the persistent set forgets them
        assert lms.persistent == set()


def test_triangulate_track_prefers_static_and_falls_back_on_both_cameras() -> None:
    p = np.array([0.3, 0.2, 6.0])
    poses = {(k, cam): _camera(0.3 * k + 0.25 * cam) for k in range(3) for cam in (0, 1)}
    obs = [(k, cam, _project(poses[(k, cam)], p)) for k in range(3) for cam in (0, 1)]
    used: list[tuple[int, int]] = []

    def camera_pose(k: int, cam: int) -> np.ndarray:
        used.append((k, cam))
        return poses[(k, cam)]

    q, ok = triangulate_track(obs, camera_pose, OPT)
    assert ok and np.allclose(q, p, atol=1e-9) and {cam for _, cam in used} == {0}
    # one keyframe of static observations only: the stereo pair (both cameras) triangulates
    obs = [(0, 0, _project(poses[(0, 0)], p)), (0, 1, _project(poses[(0, 1)], p))]
    used.clear()
    q, ok = triangulate_track(obs, camera_pose, OPT)
    assert ok and np.allclose(q, p, atol=1e-9) and {cam for _, cam in used} == {0, 1}


def test_track_bookkeeping() -> None:
    """A track seen in three keyframes becomes a landmark; one that ended too short is dropped; old
    observations leave with the window; refresh forgets landmarks out of the estimate."""
    p = np.array([0.3, 0.2, 6.0])
    poses = {k: _camera(0.3 * k) for k in range(4)}
    times = {k: 100 * k for k in range(4)}
    lms = LandmarkMap()
    for k in range(3):
        lms.buffer(7, k, 0, _project(poses[k], p))
    lms.buffer(8, 0, 0, np.zeros(2))  # ends after one keyframe

    def camera_pose(k: int, cam: int) -> np.ndarray:
        return poses[k]

    made = lms.triangulate_ready(2, times[2], times, 0, camera_pose, OPT)
    assert [m.index for m in made] == [0] and np.allclose(made[0].p_W, p, atol=1e-9) and len(made[0].obs) == 3
    assert lms.active == {7: 0} and lms.last_seen_ns[0] == 200 and lms.tracks == {}  # 8 ended too short
    lms.buffer(10, 0, 0, np.zeros(2))
    lms.buffer(10, 3, 0, np.zeros(2))
    assert lms.triangulate_ready(3, times[3], times, 50, camera_pose, OPT) == []
    assert [ob[0] for ob in lms.tracks[10].obs] == [3]  # keyframe 0 left the window
    est = gtsam.Values()
    est.insert(landmark_key(0), p + 0.01)
    lms.refresh(est, 0)
    np.testing.assert_allclose(lms.position[0], p + 0.01)
    lms.refresh(est, 300)  # last seen before the cutoff
    assert lms.active == {} and lms.position == {} and lms.count == 1


def test_batched_triangulation_equals_one_track_at_a_time() -> None:
    """``triangulate_tracks`` (the DLT and the checks batched over tracks) gives every track exactly what
    ``triangulate_track`` gives it alone, over a random mix: good points, noisy ones failing the gate,
    points behind or beyond the cameras, static-only and mixed tracks of 1-5 keyframes."""
    rng = np.random.default_rng(7)
    poses = {(k, cam): _camera(0.35 * k + 0.2 * cam) for k in range(6) for cam in (0, 1)}

    def camera_pose(k: int, cam: int) -> np.ndarray:
        return poses[(k, cam)]

    tracks = []
    for _ in range(200):
        p = rng.uniform([-2, -2, -3], [2, 2, 90])
        kfs = sorted(rng.choice(6, size=rng.integers(1, 6), replace=False))
        cams = [int(c) for c in rng.integers(0, 2, size=len(kfs))]
        noise = rng.choice([0.0, 1.0, 20.0]) * OPT.sigma
        tracks.append(
            [
                (int(k), c, _project(poses[(int(k), c)], p) + rng.normal(0, noise + 1e-12, 2))
                for k, c in zip(kfs, cams, strict=True)
            ]
        )
    batched = triangulate_tracks(tracks, camera_pose, OPT)
    single = [triangulate_track(obs, camera_pose, OPT) for obs in tracks]
    for (pb, okb), (ps, oks) in zip(batched, single, strict=True):
        assert okb == oks and np.array_equal(pb, ps, equal_nan=True)
    assert 20 < sum(ok for _, ok in batched) < 180  # both outcomes are exercised
