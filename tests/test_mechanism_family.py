"""The randomized mechanism family (dcc_fg.sim.mechanism_family) and ``simulate calibration --random-mechanism``."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest

from dcc_fg.cli import main
from dcc_fg.io.camchain import load_camchain
from dcc_fg.sim import mechanism_family as mf
from dcc_fg.sim.mechanism_family import FamilyMember, distortion_is_monotonic, family_member, simulate_member
from dcc_fg.sim.write_dataset import load_ground_truth
from dcc_fg.targets import load_target
from factors import chain
from factors.camera import CameraModel

N_MEMBERS = 150
DEG = np.pi / 180.0


@lru_cache(maxsize=1)
def members() -> tuple[FamilyMember, ...]:
    return tuple(family_member(s) for s in range(N_MEMBERS))


def binomial_ok(count: int, n: int, p: float) -> bool:
    """``count`` within 4 standard deviations of n p (false alarm ~6e-5 per check)."""
    return abs(count - n * p) <= 4.0 * np.sqrt(n * p * (1.0 - p))


def test_same_seed_same_member() -> None:
    a, b = family_member(11), family_member(11)
    assert np.array_equal(a.truth.kin, b.truth.kin) and np.array_equal(a.ranges, b.ranges)
    assert a.truth.static_camera == b.truth.static_camera and a.truth.dynamic_camera == b.truth.dynamic_camera
    assert a.scene == b.scene and a.description == b.description
    c = family_member(12)
    assert not np.array_equal(a.truth.kin, c.truth.kin)
    # fixing L changes only the kinematics: cameras and target stay with the seed
    for L in (1, 2, 3):
        m = family_member(11, L, 5)
        assert m.truth.n_joints == L and m.ranges.shape == (L, 2) and m.scene.n_calibration == 5
        assert m.truth.static_camera == a.truth.static_camera and m.scene.target == a.scene.target


def test_family_covers_its_promised_variety() -> None:
    ms = members()
    n = len(ms)
    joints = np.array([m.truth.n_joints for m in ms])
    for L in (1, 2, 3):
        assert binomial_ok(int(np.sum(joints == L)), n, 1.0 / 3.0)
    assert binomial_ok(sum(m.description["intersecting_axes"] for m in ms), n, mf.P_INTERSECTING)
    assert binomial_ok(sum(m.target_kind == "aprilgrid" for m in ms), n, 0.5)
    near = {m.seed for m in ms if m.description["twists"] == "near 90 deg"}
    assert binomial_ok(len(near), n, mf.P_NEAR_90)
    for m in ms:
        tw = np.abs(m.truth.dh[:, 2]) / DEG
        assert np.allclose(tw, np.abs(m.description["twists_deg"]))
        if m.seed in near:
            assert np.all(np.abs(tw - 90.0) <= 5.0)
        else:
            assert np.all((tw >= 20.0) & (tw <= 160.0))
        half = 0.5 * (m.ranges[:, 1] - m.ranges[:, 0]) / DEG
        assert np.all((half >= 8.0) & (half <= 60.0))
        offsets = np.abs(m.truth.dh[:, :2])
        assert np.all((offsets == 0.0) | ((offsets >= 1e-3) & (offsets <= 0.1)))
    general = np.concatenate([np.abs(m.truth.dh[:, 2]) / DEG for m in ms if m.seed not in near])
    assert general.min() < 40.0 and general.max() > 140.0 and np.mean(np.abs(general - 90.0) > 5.0) > 0.8
    halves = np.concatenate([0.5 * np.ptp(m.ranges, axis=1) / DEG for m in ms])
    assert halves.min() < 10.0 and halves.max() > 58.0
    cams = [c for m in ms for c in (m.truth.static_camera, m.truth.dynamic_camera) if c is not None]
    assert binomial_ok(sum(c.distortion_model == "equidistant" for c in cams), len(cams), 0.5)
    assert {c.resolution for c in cams} == set(mf.RESOLUTIONS)
    for m in ms:
        for name, c in m.description["cameras"].items():
            cam = m.truth.static_camera if name == "static" else m.truth.dynamic_camera
            assert cam is not None and 50.0 <= c["hfov_deg"] <= 90.0
            w, h = cam.resolution
            fx, fy, cx, cy = cam.intrinsics
            assert (
                abs(fy / fx - 1.0) <= 0.01
                and abs(cx - 0.5 * (w - 1)) <= 0.03 * w
                and abs(cy - 0.5 * (h - 1)) <= 0.03 * h
            )
            assert distortion_is_monotonic(cam)
    kinds = [m.scene.target for m in ms]
    for tg in kinds:
        if tg.target_type == "checkerboard":
            assert (tg.cols % 2) != (tg.rows % 2)  # odd x even: no 180 deg symmetry
            assert 0.03 <= tg.col_spacing <= 0.08
        else:
            assert 4 <= tg.cols <= 7 and 4 <= tg.rows <= 7 and 0.03 <= tg.tag_size <= 0.08 and tg.tag_spacing == 0.3


def test_folding_distortion_is_refused() -> None:
    fold = CameraModel((320.0, 320.0, 319.5, 239.5), "radtan", (-0.3, 0.0, 0.0, 0.0), (640, 480))
    assert not distortion_is_monotonic(fold)  # 90 deg HFOV with k1 = -0.3 folds before the corners
    mild = CameraModel((320.0, 320.0, 319.5, 239.5), "radtan", (-0.05, 0.0, 0.0, 0.0), (640, 480))
    assert distortion_is_monotonic(mild)


def _axes(dh: np.ndarray, theta: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """(point, unit direction) of every joint axis in the base frame: axis l is z of DH frame l-1."""
    T = np.eye(4)
    out = []
    for (d, a, alpha), th in zip(dh, theta, strict=True):
        out.append((T[:3, 3].copy(), T[:3, 2].copy()))
        T = T @ chain.dh_link(th, d, a, alpha)
    return out


def _line_distance(p1: np.ndarray, u1: np.ndarray, p2: np.ndarray, u2: np.ndarray) -> float:
    n = np.cross(u1, u2)
    return float(abs(np.dot(p2 - p1, n)) / np.linalg.norm(n))  # non-parallel: twists >= 20 deg


def test_intersecting_members_have_intersecting_axes() -> None:
    rng = np.random.default_rng(0)
    checked = 0
    for seed in range(40):
        m = family_member(seed, 3, 5)
        th = rng.uniform(-np.pi, np.pi, size=3)
        axes = _axes(m.truth.dh, th)
        dist = [_line_distance(*axes[i], *axes[j]) for i in range(3) for j in range(i + 1, 3)]
        if m.description["intersecting_axes"]:
            assert max(dist) < 1e-12, (seed, dist)
            checked += 1
        else:
            assert max(dist) > 1e-4
    assert checked >= 3


def test_dynamic_camera_placement_at_range_centre() -> None:
    for m in members():
        T = m.truth.T_ds(m.ranges.mean(axis=1))
        c_s = -T[:3, :3].T @ T[:3, 3]  # dynamic camera centre in s, m
        angle = np.arccos(np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))
        assert angle <= 5.0 * DEG + 1e-9
        assert 0.05 - 1e-9 <= np.hypot(c_s[0], c_s[1]) <= 0.20 + 1e-9 and abs(c_s[2]) <= 0.02 + 1e-9
        # the untilted board fits both images at the range centre at both ends of the distance range
        z0, z1 = m.scene.distance_range
        cams = (m.truth.static_camera, m.truth.dynamic_camera)
        assert cams[0] is not None and cams[1] is not None
        for z in (z0, z1):
            assert mf._board_fits(T, m.scene.target.points, (cams[0], cams[1]), z, m.scene.margin_px)


@pytest.mark.parametrize("n_joints, seeds", [(1, range(6)), (2, range(2)), (3, range(2))])
def test_simulate_member_places_every_board(n_joints: int, seeds: range) -> None:
    for seed in seeds:
        m = family_member(seed, n_joints, 6)
        sim = simulate_member(m)
        assert sim.joints_calibration.shape == (6, n_joints)
        assert sim.truth is m.truth and sim.config.target == m.scene.target
        # every simulated corner is inside both images
        for snap in sim.calibration_set.snapshots:
            for cam, obs in ((m.truth.static_camera, snap.static), (m.truth.dynamic_camera, snap.dynamic)):
                assert cam is not None and np.all(cam.in_image(obs.pixels, 0.0))
        # true angles stay inside the requested ranges (the fallback only moves towards the centre)
        th = sim.joints_calibration
        assert np.all(th >= m.ranges[:, 0] - 1e-9) and np.all(th <= m.ranges[:, 1] + 1e-9)


@pytest.mark.slow  # ~10 s CPU: the ray tables of two random cameras (undistortion of every sub-pixel)
def test_cli_random_mechanism_writes_the_member(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "sim"
    assert main(["simulate", "calibration", "--random-mechanism", "7", "--snapshots", "3", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed.startswith("mechanism 7: L=")
    m = family_member(7, None, 3)
    chain_ = load_camchain(out / "camchain.yaml")
    for name, cam in (("cam0", m.truth.static_camera), ("cam1", m.truth.dynamic_camera)):
        got = chain_[name].camera
        assert cam is not None
        assert got.distortion_model == cam.distortion_model and tuple(got.resolution) == cam.resolution
        assert np.allclose(got.intrinsics, cam.intrinsics, rtol=1e-12)
        assert np.allclose(got.distortion_coeffs, cam.distortion_coeffs, rtol=1e-12)
    assert load_target(out / "target.yaml") == m.scene.target
    gt = load_ground_truth(out / "ground_truth.yaml")
    assert np.allclose(gt.kinematics.kin, m.truth.kin, rtol=0.0, atol=1e-12)
    assert gt.raw["random_mechanism"] == 7 and gt.raw["mechanism"]["joints"] == m.truth.n_joints
    assert gt.raw["mechanism"]["cameras"] == m.description["cameras"]
    assert len(gt.raw["mechanism"]["achieved_half_range_deg"]) == m.truth.n_joints
    assert len(sorted((out / "images" / "cam0").glob("*.png"))) == 3
    # an explicit --target cannot be combined with the family's target
    code = main(["simulate", "calibration", "--random-mechanism", "7", "--target", "aprilgrid", "--out",
                 str(tmp_path / "x")])  # fmt: skip
    assert code == 2 and "--target cannot be combined" in capsys.readouterr().err
