"""VIO front end on rendered flights: tracks checked against the renderer's geometry (ground truth),
static RANSAC, static<->gimbal matching and the two-stage gimbal outlier handling."""

from __future__ import annotations

import numpy as np
import pytest

from dcc_fg.sim.flight_render import WorldRenderer, planes_from_world, procedural_texture, render_flight
from dcc_fg.sim.trajectory import FlightConfig, World, default_static_mount, flight_calibration, simulate_flight
from dcc_fg.vio.epipolar import (
    depth_segment_distance,
    epipolar_distance,
    essential,
    rotation_ransac,
    sampson_distance,
)
from dcc_fg.vio.frontend import Frontend, GimbalHint
from dcc_fg.vio.matching import orientation_deg
from factors.chain import inv_se3, rot_x, rot_y, rot_z

N_FRAMES = 36
START = 80  # frame 80 = 4.0 s: moving, and joint 1 starts its first slew (~54 deg/s)


class Flight:
    """Rendered frames of a short flight with their true poses and joint angles."""

    def __init__(self, patch_in: str | None = None) -> None:
        self.cfg = FlightConfig.short(30.0)
        self.truth = simulate_flight(self.cfg, seed=3)
        self.cal = flight_calibration()
        self.T_sI = default_static_mount()
        self.renderer = WorldRenderer(planes_from_world(World.around(self.cfg)), seed=3)
        sl = slice(START, START + N_FRAMES)
        idx = self.truth.index_of(self.truth.frame_t_ns[sl])
        self.T_sW = [self.T_sI @ inv_se3(self.truth.T_WI[i]) for i in idx]
        self.theta = self.truth.theta[idx]
        self.frames = list(render_flight(self.renderer, self.truth, self.cal, self.T_sI, seed=5, frames=sl))
        self.patch = None
        if patch_in is not None:
            self.patch = _paste_moving_patch(self, 0 if patch_in == "static" else 1)

    def T_dW(self, k: int) -> np.ndarray:
        return self.cal.T_ds(self.theta[k]) @ self.T_sW[k]


def _paste_moving_patch(fl: Flight, cam: int, n: int = 16) -> list[tuple[int, int, int]]:
    """Overwrite a 90x90 textured patch in the first ``n`` frames of camera ``cam``: it moves with
    the scene behind it plus 8 px per frame across the epipolar line there (an independently moving
    object, computed from the true geometry); returns its (x0, y0, size) per frame."""
    tex = procedural_texture(90, 90, 0.02, 99)
    camera = fl.cal.static_camera if cam == 0 else fl.cal.dynamic_camera
    pose = fl.T_sW if cam == 0 else [fl.T_dW(k) for k in range(len(fl.frames))]
    c = np.array([220.0, 300.0])
    boxes = []
    for k in range(n):
        c = np.clip(c, 50.0, [camera.resolution[0] - 50.0, camera.resolution[1] - 50.0])
        x0, y0 = int(round(c[0])) - 45, int(round(c[1])) - 45
        t, a, b = fl.frames[k]
        img = (a if cam == 0 else b).copy()
        img[y0 : y0 + 90, x0 : x0 + 90] = tex
        fl.frames[k] = (t, img, b) if cam == 0 else (t, a, img)
        boxes.append((x0, y0, 90))
        P = fl.renderer.raycast(pose[k], camera.undistort_points(c[None]))
        c_next = _project_px(camera, pose[k + 1], P)[0]
        f = c_next - c
        c = c_next + 8.0 * np.array([-f[1], f[0]]) / max(float(np.linalg.norm(f)), 1e-9)
    return boxes


def _inside(pts: np.ndarray, box: tuple[int, int, int], margin: int = 0) -> np.ndarray:
    x0, y0, s = box
    return (
        (pts[:, 0] >= x0 - margin)
        & (pts[:, 0] < x0 + s + margin)
        & (pts[:, 1] >= y0 - margin)
        & (pts[:, 1] < y0 + s + margin)
    )


@pytest.fixture(scope="module")
def flight() -> Flight:
    return Flight()


def _project_px(camera, T_cW: np.ndarray, p_W: np.ndarray) -> np.ndarray:
    p_c = p_W @ T_cW[:3, :3].T + T_cW[:3, 3]
    uv, _ = camera.project(p_c, jacobian=False)
    return uv


def test_tracks_follow_the_true_geometry(flight: Flight) -> None:
    """Every static and gimbal observation is compared with the projection of the world point its
    track started on (ray-cast through the renderer's planes): drift and wrong cross-camera
    matches would show as pixel errors.  Image noise is 2 grey levels, so KLT accuracy should
    be a fraction of a pixel; the 95th percentile allows for slow drift over the window.  The
    gimbal camera rolls by 25 deg in 0.7 s here: translation-only KLT drifts by ~1 px over such a
    slew (measured: median error of gimbal tracks against their own start point grows from 0.05 to
    1.3 px during the slew, while static tracks stay at ~0.3 px), hence its looser bounds."""
    cal = flight.cal
    fe = Frontend(cal.static_camera, cal.dynamic_camera, T_ds=cal.T_ds(flight.theta[0]))
    anchor: dict[int, np.ndarray] = {}
    err_s, err_d, shared, lengths = [], [], [], {}
    for k, (t, a, b) in enumerate(flight.frames):
        fr = fe.process(t, a, b, T_ds=cal.T_ds(flight.theta[max(k - 1, 0)]))  # a lagging estimate
        assert len(np.unique(fr.static_ids)) == fr.static_ids.size
        assert len(np.unique(fr.dynamic_ids)) == fr.dynamic_ids.size
        assert np.all(np.isfinite(fr.static_xy)) and np.all(np.isfinite(fr.dynamic_xy))
        new = [i for i, q in enumerate(fr.static_ids) if int(q) not in anchor]
        if new:
            pts = flight.renderer.raycast(flight.T_sW[k], fr.static_xy[new])
            anchor.update({int(fr.static_ids[i]): p for i, p in zip(new, pts, strict=True)})
        for q in fr.static_ids:
            lengths[int(q)] = lengths.get(int(q), 0) + 1
        known_s = np.array([int(q) in anchor for q in fr.static_ids], dtype=bool)
        P = np.array([anchor[int(q)] for q in fr.static_ids[known_s]]).reshape(-1, 3)
        uv_obs = _project_px(cal.static_camera, np.eye(4), np.hstack([fr.static_xy[known_s], np.ones((P.shape[0], 1))]))
        err_s.append(np.linalg.norm(uv_obs - _project_px(cal.static_camera, flight.T_sW[k], P), axis=1))
        common = np.intersect1d(fr.dynamic_ids, list(anchor))
        shared.append(np.intersect1d(fr.static_ids, fr.dynamic_ids).size)
        if common.size:
            j = np.searchsorted(fr.dynamic_ids, common) if np.all(np.diff(fr.dynamic_ids) > 0) else None
            j = np.array([int(np.flatnonzero(fr.dynamic_ids == q)[0]) for q in common]) if j is None else j
            P = np.array([anchor[int(q)] for q in common])
            xy = fr.dynamic_xy[j]
            uv_obs = _project_px(cal.dynamic_camera, np.eye(4), np.hstack([xy, np.ones((xy.shape[0], 1))]))
            err_d.append(np.linalg.norm(uv_obs - _project_px(cal.dynamic_camera, flight.T_dW(k), P), axis=1))
    es, ed = np.concatenate(err_s), np.concatenate(err_d)
    es = es[np.isfinite(es)]
    ed = ed[np.isfinite(ed)]
    assert np.median(es) < 0.5 and np.percentile(es, 95) < 2.0, (np.median(es), np.percentile(es, 95))
    assert np.median(ed) < 1.5 and np.percentile(ed, 95) < 4.0, (np.median(ed), np.percentile(ed, 95))
    assert np.mean(shared) >= 15, shared
    assert np.median(list(lengths.values())) >= 5
    assert fe.stats.ransac_tested > 0 and fe.stats.ransac_rejected < 0.05 * fe.stats.ransac_tested


def test_static_ransac_removes_a_moving_object() -> None:
    fl = Flight(patch_in="static")
    cal = fl.cal
    fe = Frontend(cal.static_camera, cal.dynamic_camera, T_ds=cal.T_ds(fl.theta[0]))
    survivors = on_patch = 0
    for k, (t, a, b) in enumerate(fl.frames[:16]):
        fe.process(t, a, b)
        inside = _inside(fe.static.pts, fl.patch[k], margin=-8)
        on_patch += int(np.sum(inside & (fe.static.ages >= 1)))
        survivors += int(np.sum(inside & (fe.static.ages >= fe.config.ransac_window)))
    # two-frame RANSAC may let a small coherent cluster through for a frame or two (short
    # baseline); the long-baseline RANSAC over ransac_window frames must catch every one of them
    assert fe.stats.ransac_rejected >= 10
    assert survivors == 0, survivors
    assert on_patch <= 100, on_patch


def test_two_stage_gimbal_rejection() -> None:
    """Stage 1 keeps gimbal tracks on a moving object (no rejection with unknown extrinsics);
    stage 2 with the updated (true) extrinsics removes them and almost nothing else, while the
    same test with stale extrinsics (previous frame's joint angles, mid-slew) would have thrown
    away most good tracks: the reason the paper disabled rejection for the gimbal camera."""
    fl = Flight(patch_in="dynamic")
    cal = fl.cal
    fe = Frontend(cal.static_camera, cal.dynamic_camera, T_ds=cal.T_ds(fl.theta[0]))
    kept_stage1 = removed_patch = kept_patch = good_removed = good_total = stale_good_removed = 0
    for k, (t, a, b) in enumerate(fl.frames[:16]):
        fe.process(t, a, b)
        if k == 0:
            continue
        d = fe.dynamic
        assert d is not None
        on_patch = _inside(d.pts, fl.patch[k], margin=-8) & d.tracked()
        off_patch = ~_inside(d.pts, fl.patch[k], margin=12) & d.tracked()
        kept_stage1 += int(on_patch.sum())
        T_s10 = fl.T_sW[k] @ inv_se3(fl.T_sW[k - 1])
        stale = GimbalHint(cal.T_ds(fl.theta[k - 1]), cal.T_ds(fl.theta[k - 1]), T_s10)
        stale_good_removed += int((fe.dynamic_outliers(stale) & off_patch).sum())
        ids_patch, ids_good = d.ids[on_patch].copy(), d.ids[off_patch].copy()
        removed = fe.reject_dynamic(GimbalHint(cal.T_ds(fl.theta[k - 1]), cal.T_ds(fl.theta[k]), T_s10))
        removed_patch += int(np.isin(ids_patch, removed).sum())
        kept_patch += int((~np.isin(ids_patch, removed)).sum())
        good_removed += int(np.isin(ids_good, removed).sum())
        good_total += ids_good.size
    assert kept_stage1 >= 10
    assert removed_patch >= 0.8 * (removed_patch + kept_patch), (removed_patch, kept_patch)
    assert good_removed <= 0.03 * good_total, (good_removed, good_total)
    assert stale_good_removed >= 10 * max(good_removed, 1), (stale_good_removed, good_removed)


def test_matching_a_rolled_gimbal_camera_without_extrinsics(flight: Flight) -> None:
    """Rotation-invariant descriptors and the rotation RANSAC match a camera rolled by 40 deg with
    no T_ds estimate at all; the matches agree with the true geometry."""
    cal = flight.cal
    R = rot_z(np.deg2rad(40.0)) @ rot_y(0.05) @ rot_x(-0.03)
    T_ds = np.eye(4)
    T_ds[:3, :3], T_ds[:3, 3] = R, [-0.08, 0.01, 0.0]
    fe = Frontend(cal.static_camera, cal.static_camera)
    rng = np.random.default_rng(0)
    errs = []
    for k in range(4):
        a = flight.renderer.render(cal.static_camera, flight.T_sW[k], 2.0, rng)
        b = flight.renderer.render(cal.static_camera, T_ds @ flight.T_sW[k], 2.0, rng)
        fr = fe.process(int(flight.frames[k][0]), a, b)
        common, i, j = np.intersect1d(fr.static_ids, fr.dynamic_ids, return_indices=True)
        errs.append(depth_segment_distance(T_ds, fr.static_xy[i], fr.dynamic_xy[j], 0.3) * 460.0)
    assert errs[-1].size >= 20
    assert np.percentile(np.concatenate(errs), 95) < 3.0


def test_reset_starts_new_tracks(flight: Flight) -> None:
    cal = flight.cal
    fe = Frontend(cal.static_camera, cal.dynamic_camera)
    first = fe.process(*flight.frames[0])
    fe.reset()
    t, a, b = flight.frames[20]  # one second later: no track may be carried across
    after = fe.process(t, a, b)
    assert after.static_ids.size > 50
    assert not np.intersect1d(first.static_ids, after.static_ids).size
    assert not np.intersect1d(first.dynamic_ids, after.dynamic_ids).size


def test_missing_gimbal_image_and_bad_images(flight: Flight) -> None:
    cal = flight.cal
    fe = Frontend(cal.static_camera, cal.dynamic_camera)
    t, a, b = flight.frames[0]
    # no gimbal image near this static one (an unsynchronized or stopped gimbal stream): static tracks only
    alone = fe.process(t, a, None)
    assert alone.static_ids.size > 50 and alone.dynamic_ids.size == 0
    assert fe.stats.summary()["frames_without_gimbal"] == 1
    with pytest.raises(ValueError, match="320x240 but the camera model says 640x480"):
        Frontend(cal.static_camera).process(t, a[::2, ::2])


def test_gimbal_tracks_step_through_images_between_frames(flight: Flight) -> None:
    """A gimbal camera faster than the static one: frames take every third rendered image pair and the
    gimbal tracks step through the two gimbal images in between (no static partner). Stepped tracks
    keep their previous-frame positions, history and ages from the last frame (what the gimbal RANSAC
    and the matching use), and follow the true geometry as well as tracks processed frame by frame
    (renderer ray-cast at the track's first frame, projected into the current one)."""
    cal = flight.cal
    fe = Frontend(cal.static_camera, cal.dynamic_camera, T_ds=cal.T_ds(flight.theta[0]))
    anchor: dict[int, np.ndarray] = {}
    errors = []
    for k in range(0, 19, 3):
        if k:
            before = fe.dynamic.xy.copy(), fe.dynamic.ids.copy(), fe.dynamic.ages.copy()
            for kk in (k - 2, k - 1):
                fe.track_gimbal(flight.frames[kk][2])
            ids = fe.dynamic.ids
            kept = np.isin(before[1], ids)
            assert kept.sum() > 0.8 * before[1].size  # the steps lose few tracks
            i_prev = np.searchsorted(before[1], ids) if np.all(np.diff(before[1]) > 0) else None
            i_prev = np.array([int(np.flatnonzero(before[1] == q)[0]) for q in ids]) if i_prev is None else i_prev
            assert np.array_equal(fe.dynamic.ages, before[2][i_prev])  # a step is not a frame
        t, a, b = flight.frames[k]
        fr = fe.process(t, a, b, T_ds=cal.T_ds(flight.theta[k]))
        if k:  # previous-frame positions are those of frame k - 3, not of the image just stepped through
            prev = dict(zip(before[1].tolist(), before[0], strict=True))
            carried = [i for i, q in enumerate(fe.dynamic.ids) if int(q) in prev]
            assert carried and np.allclose(fe.dynamic.prev_xy[carried], [prev[int(fe.dynamic.ids[i])] for i in carried])
        new = [i for i, q in enumerate(fr.dynamic_ids) if int(q) not in anchor]
        if new:
            pts = flight.renderer.raycast(flight.T_dW(k), fr.dynamic_xy[new])
            anchor.update({int(fr.dynamic_ids[i]): p for i, p in zip(new, pts, strict=True)})
        old_ids = [i for i, q in enumerate(fr.dynamic_ids) if int(q) in anchor and i not in new]
        if old_ids:
            P = np.array([anchor[int(fr.dynamic_ids[i])] for i in old_ids])
            xy = fr.dynamic_xy[old_ids]
            uv_obs = _project_px(cal.dynamic_camera, np.eye(4), np.hstack([xy, np.ones((xy.shape[0], 1))]))
            errors.append(np.linalg.norm(uv_obs - _project_px(cal.dynamic_camera, flight.T_dW(k), P), axis=1))
    err = np.concatenate(errors)
    err = err[np.isfinite(err)]
    assert fe.stats.summary()["gimbal_images_between"] == 12
    # same bounds as the frame-by-frame test above (the gimbal camera rolls 25 deg in 0.7 s here)
    assert err.size > 100 and np.median(err) < 1.5 and np.percentile(err, 95) < 4.0, (np.median(err), err.size)


# ------------------------------------------------------------------ geometry helpers
def _random_scene(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    T = np.eye(4)
    T[:3, :3] = rot_z(0.3) @ rot_y(-0.2) @ rot_x(0.1)
    T[:3, 3] = [0.1, -0.02, 0.03]
    p_a = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(2, 10, n)])
    p_b = p_a @ T[:3, :3].T + T[:3, 3]
    return T, p_a[:, :2] / p_a[:, 2:], p_b[:, :2] / p_b[:, 2:]


def test_epipolar_distances_vanish_on_true_correspondences() -> None:
    rng = np.random.default_rng(1)
    T, xa, xb = _random_scene(rng, 50)
    E = essential(T)
    assert np.max(epipolar_distance(E, xa, xb)) < 1e-12
    assert np.max(sampson_distance(E, xa, xb)) < 1e-12
    assert np.max(depth_segment_distance(T, xa, xb, 1.0)) < 1e-12
    # a point nearer than min_depth is off the segment, a shifted one off the line
    assert np.all(depth_segment_distance(T, xa, xb, 12.0) > 0)
    assert np.all(epipolar_distance(E, xa, xb + [0.0, 0.01]) > 1e-4)


def test_rotation_ransac_with_outliers() -> None:
    rng = np.random.default_rng(2)
    T, xa, xb = _random_scene(rng, 60)
    xb_far = (xa @ T[:2, :2].T + T[:2, 2]) / (xa @ T[2, :2] + T[2, 2])[:, None]  # infinite depth
    bad = rng.random(60) < 0.3
    xb_far[bad] += rng.uniform(-0.3, 0.3, (int(bad.sum()), 2))
    R, inl = rotation_ransac(xa, xb_far, 0.01, seed=0)
    assert R is not None
    assert np.linalg.norm(R - T[:3, :3]) < 1e-9
    assert np.array_equal(inl, ~bad)
    # with the translation known, true (finite-depth) correspondences are all inliers
    R2, inl2 = rotation_ransac(xa, xb, 0.005, T[:3, 3], 1.0, seed=0)
    assert R2 is not None and inl2.all()


def test_orientation_follows_image_rotation() -> None:
    img = procedural_texture(200, 200, 0.02, 4)
    pts = np.array([[60.0, 80.0], [120.0, 100.0], [90.0, 140.0]])
    rot = np.ascontiguousarray(np.rot90(img))  # counter-clockwise: (x, y) -> (y, W - 1 - x)
    pts_r = np.column_stack([pts[:, 1], 199 - pts[:, 0]])
    d = (orientation_deg(rot, pts_r) - orientation_deg(img, pts)) % 360.0
    assert np.allclose(d, 270.0, atol=1.0), d


def test_orientation_is_the_intensity_centroid_of_the_disc() -> None:
    """Against a per-point reference: the angle of (m10, m01) over the 31-pixel disc around the rounded
    pixel, the image reflected (101) beyond its border; points near and beyond the border included."""
    rng = np.random.default_rng(7)
    img = procedural_texture(160, 120, 0.03, 5)
    pts = np.vstack([rng.uniform([0, 0], [159, 119], (40, 2)), [[-2.0, 3.0], [158.6, 119.4], [3.2, 60.0]]])
    h = 15
    padded = np.pad(img.astype(np.float64), h, mode="reflect")  # numpy's "reflect" is OpenCV's REFLECT_101
    yy, xx = np.mgrid[-h : h + 1, -h : h + 1]
    disc = xx**2 + yy**2 <= h**2
    expected = []
    for x, y in pts:
        cx = int(np.clip(np.rint(x), 0, img.shape[1] - 1)) + h
        cy = int(np.clip(np.rint(y), 0, img.shape[0] - 1)) + h
        patch = padded[cy - h : cy + h + 1, cx - h : cx + h + 1] * disc
        expected.append(np.degrees(np.arctan2((patch * yy).sum(), (patch * xx).sum())) % 360.0)
    got = orientation_deg(img, pts)
    diff = (got - np.array(expected) + 180.0) % 360.0 - 180.0
    assert np.abs(diff).max() < 1e-3, diff
