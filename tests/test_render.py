"""Rendered images: corners land where the true (distorted) camera projects them; the simulate command."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import yaml

from dcc_fg.cli import build_parser, main
from dcc_fg.detection import detect_target
from dcc_fg.io.camchain import load_camchain
from dcc_fg.model import load_calibration
from dcc_fg.sim.calibration_scene import simulate_calibration
from dcc_fg.sim.mechanism_family import family_member, simulate_member
from dcc_fg.sim.render import RenderConfig, make_texture, render_view
from dcc_fg.sim.write_dataset import _rendered_poses, default_target, load_ground_truth, scene_config
from dcc_fg.targets import load_target
from factors.camera import CameraModel


@pytest.mark.parametrize("kind", ["checkerboard", "aprilgrid"])
def test_detected_corners_match_true_projection(kind: str) -> None:
    """Render 5 snapshots per camera and detect: every corner found with the right id, sub-pixel accurate.

    The bounds are those of the detector on sharp 8-bit images (cornerSubPix: a few hundredths of
    a pixel); a wrong pixel-centre convention (0.5 px), a mirrored tag or a wrong distortion would
    exceed them by an order of magnitude, which the undistorted check below shows.
    """
    tg = default_target(kind)
    sim = simulate_calibration(7, scene_config(tg, 5))
    T_st = _rendered_poses(sim)
    tex = make_texture(tg)
    rng = np.random.default_rng(0)
    cams = (sim.truth.static_camera, sim.truth.dynamic_camera)
    errors, shifts = [], []
    for k in range(5):
        T_ds = sim.truth.T_ds(sim.joints_calibration[k])
        for cam, T in ((cams[0], T_st[k]), (cams[1], T_ds @ T_st[k])):
            img = render_view(cam, T, tex, RenderConfig(), rng)
            assert img.shape == (480, 640) and img.dtype == np.uint8
            obs = detect_target(img, tg)
            assert len(obs) == tg.points.shape[0]  # the whole board, every corner
            p = tg.points[obs.ids] @ T[:3, :3].T + T[:3, 3]
            uv = cam.project(p, jacobian=False)[0]
            errors.append(obs.pixels - uv)
            pinhole = CameraModel(cam.intrinsics, "none", (), cam.resolution)
            shifts.append(np.linalg.norm(pinhole.project(p, jacobian=False)[0] - uv, axis=1))
    e = np.concatenate(errors)
    assert np.sqrt(np.mean(e**2)) < 0.06
    assert np.abs(e).max() < 0.3
    assert np.all(np.abs(e.mean(axis=0)) < 0.01)  # no bias (pixel-centre convention)
    assert np.concatenate(shifts).max() > 3.0  # the distortion moves corners by far more than the error


def test_render_config_rejects_bad_values() -> None:
    with pytest.raises(ValueError, match="supersample"):
        RenderConfig(supersample=0)


def test_simulate_command_writes_a_complete_data_set(tmp_path, capsys) -> None:  # noqa: ANN001
    out = tmp_path / "sim"
    argv = ["simulate", "calibration", "--target", "aprilgrid", "--format", "ros2", "--storage", "mcap"]
    assert main([*argv, "--out", str(out), "--snapshots", "3", "--seed", "4"]) == 0
    assert "dcc-fg calibrate" in capsys.readouterr().out
    assert (out / "images_bag" / "metadata.yaml").is_file() and list((out / "images_bag").glob("*.mcap"))
    chain = load_camchain(out / "camchain.yaml")
    assert chain["cam0"].rostopic == "/cam0/image_raw" and chain["cam1"].rostopic == "/cam1/image_raw"
    assert load_target(out / "target.yaml") == default_target("aprilgrid")
    gt = load_ground_truth(out / "ground_truth.yaml")
    assert gt.theta.shape == (3, 2) and gt.T_ds.shape == (3, 4, 4) and gt.T_st.shape == (3, 4, 4)
    for k in range(3):
        np.testing.assert_allclose(gt.kinematics.T_ds(gt.theta[k]), gt.T_ds[k], atol=1e-12)
    guess = load_calibration(out / "gimbal.yaml")
    assert guess.n_joints == 2 and not np.allclose(guess.kin, gt.kinematics.kin)  # perturbed initial guess
    # the data path is never overwritten
    assert main([*argv, "--out", str(out), "--snapshots", "3"]) == 2
    assert "already exists" in capsys.readouterr().err


def test_simulate_help_states_units() -> None:
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command").choices["simulate"]
    text = next(a for a in sub._actions if a.dest == "what").choices["calibration"].format_help()
    for word in ("metres", "rad", "ns", "pixels", "grey levels", "deg"):
        assert word in text


def test_ground_truth_reader_rejects_other_files(tmp_path) -> None:  # noqa: ANN001
    p = tmp_path / "x.yaml"
    p.write_text(yaml.safe_dump({"joints": 2}))
    with pytest.raises(ValueError, match="not a dcc-fg ground truth"):
        load_ground_truth(p)


def test_equidistant_camera() -> None:
    """The inverse mapping works for any camera model: a fisheye (equidistant) lens, 5 views."""
    cam = CameraModel((380.0, 380.0, 319.5, 239.5), "equidistant", (0.02, -0.01, 0.004, -0.001), (640, 480))
    tg = default_target("checkerboard")
    sim = simulate_calibration(3, scene_config(tg, 5))
    tex = make_texture(tg)
    errors = []
    for k, T in enumerate(_rendered_poses(sim)):
        obs = detect_target(render_view(cam, T, tex, RenderConfig(), np.random.default_rng(k)), tg)
        assert len(obs) == tg.points.shape[0]
        p = tg.points[obs.ids] @ T[:3, :3].T + T[:3, 3]
        errors.append(obs.pixels - cam.project(p, jacobian=False)[0])
    e = np.concatenate(errors)
    assert np.sqrt(np.mean(e**2)) < 0.06 and np.abs(e).max() < 0.3


@pytest.mark.parametrize(("seed", "camera"), [(2, 0), (3, 1)])
def test_family_camera_corners_unbiased_at_large_radii(seed: int, camera: int) -> None:
    """Noise-free renders of random-mechanism members put every checkerboard corner at its true projection.

    Member 2's static camera is equidistant (640x480, the family seeds whose calibrations were
    3-8x the Cramer-Rao bound: not the renderer, the detector's ``findChessboardCornersSB`` fallback,
    whose corners are not refined), member 3's dynamic one radtan (1280x720, the reference).  The
    image saddle points are found with ``cornerSubPix`` started 0.5 px off the true projections
    (the renderer's check, without the detector's grid search).  On a noise-free 8-bit render the
    per-corner error is quantization and the refinement's own error (measured 0.024-0.027 px RMS
    equidistant, 0.021 radtan); a mean over the outer third of the corners (~140) has a scatter of
    a few thousandths, so a wrong ray at large radii shows in its radial mean: k1 off by 0.002 in
    the rendering camera gives +0.036 px there, 0.005 gives +0.09 px (measured 0.0003 and 0.0004).
    """
    member = family_member(seed, 1, 6)
    sim = simulate_member(member)
    tg = sim.config.target
    assert tg.target_type == "checkerboard"
    cam = sim.truth.static_camera if camera == 0 else sim.truth.dynamic_camera
    assert cam is not None and cam.distortion_model == ("equidistant" if seed == 2 else "radtan")
    cfg = RenderConfig(noise_sigma=0.0)
    tex = make_texture(tg, cfg.texel_m)
    rng = np.random.default_rng(0)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    errors, radial, radii = [], [], []
    for k, T_st in enumerate(_rendered_poses(sim)):
        T = T_st if camera == 0 else sim.truth.T_ds(sim.joints_calibration[k]) @ T_st
        img = render_view(cam, T, tex, cfg, rng)
        uv = cam.project(tg.points @ T[:3, :3].T + T[:3, 3], jacobian=False)[0]
        grid = uv.reshape(tg.rows, tg.cols, 2)
        side = float(np.median(np.linalg.norm(np.diff(grid, axis=1), axis=2)))
        win = int(min(11, max(3, round(0.25 * side))))
        start = (uv + rng.uniform(-0.5, 0.5, uv.shape)).astype(np.float32).reshape(-1, 1, 2)
        found = cv2.cornerSubPix(img, start, (win, win), (-1, -1), criteria).reshape(-1, 2).astype(float)
        e = found - uv
        d = uv - np.asarray(cam.intrinsics[2:])
        r = np.linalg.norm(d, axis=1)
        errors.append(e)
        radial.append(np.sum(e * d, axis=1) / np.maximum(r, 1e-9))
        radii.append(r)
    e, er, r = np.concatenate(errors), np.concatenate(radial), np.concatenate(radii)
    outer = r > np.quantile(r, 2.0 / 3.0)
    assert np.sqrt(np.mean(e**2)) < 0.04
    assert np.abs(e).max() < 0.12
    assert np.all(np.abs(e.mean(axis=0)) < 0.01)
    assert abs(er[outer].mean()) < 0.01  # no radius-dependent scale error of the rays
    assert r.max() > 0.4 * np.hypot(*cam.resolution) / 2.0  # the corners do reach large radii


def test_undistort_round_trip_over_a_wide_fisheye() -> None:
    """Every sub-pixel ray of a 90 deg equidistant 1280x720 camera projects back onto its pixel."""
    f = 640.0 / np.radians(45.0)
    cam = CameraModel((f, f, 639.5, 359.5), "equidistant", (-0.02, 0.01, -0.004, 0.001), (1280, 720))
    uu, vv = np.meshgrid(np.linspace(-0.5, 1279.5, 321), np.linspace(-0.5, 719.5, 181))
    uv = np.stack([uu.ravel(), vv.ravel()], axis=1)
    xy = cam.undistort_points(uv)
    back = cam.project(np.column_stack([xy, np.ones(len(xy))]), jacobian=False)[0]
    assert np.abs(back - uv).max() < 1e-9
    assert np.hypot(xy[:, 0], xy[:, 1]).max() > 1.2  # rays beyond 50 deg off the axis
