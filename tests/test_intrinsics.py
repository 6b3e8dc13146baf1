"""``dcc-fg intrinsics``: single-camera calibration on simulated corners and real images.

* Simulated corners (known intrinsics, 0.3 px Gaussian corner noise, whole and partial views):
  the estimate is within a few reported sigma of the truth, and the reported sigma is the right
  size (normalized errors of RMS about 1 over several seeds), for both models.
* OpenCV's left stereo images against OpenCV's ``left_intrinsics.yml`` (see the tolerance note in
  ``test_opencv_left_against_reference``); our per-parameter sigma equals
  ``cv2.calibrateCameraExtended``'s.
* Bags and image folders give the same result; bad input raises errors naming the path.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from conftest import shared_data as real

from dcc_fg.cli import main
from dcc_fg.data import Observation
from dcc_fg.intrinsics import (
    MODELS,
    PARAM_NAMES,
    View,
    calibrate_intrinsics,
    detect_views,
    projection_jacobians,
    run_intrinsics,
    select_views,
)
from dcc_fg.intrinsics_health import fold_check, principal_point_check
from dcc_fg.io.bag_writer import write_ros1_bag, write_ros2_bag
from dcc_fg.io.camchain import load_camchain
from dcc_fg.io.folders import FramePair
from dcc_fg.targets import TargetGeometry
from factors.camera import CameraModel

BOARD = TargetGeometry.checkerboard(9, 6, 0.025)
SIM_BOARD = TargetGeometry.checkerboard(9, 6, 0.04)
TRUTH = {
    "pinhole-radtan": CameraModel((500.0, 502.0, 318.0, 243.0), "radtan", (-0.28, 0.09, 0.0008, -0.0004)),
    "pinhole-equidistant": CameraModel((380.0, 381.5, 324.0, 236.0), "equidistant", (0.03, -0.01, 0.004, -0.001)),
}
SIGMA_PX = 0.3


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(axis, float) * angle)[0]


def simulate_views(
    camera: CameraModel, target: TargetGeometry, n_views: int, seed: int, partial: bool = False
) -> list[View]:
    """Views of the whole board from random poses (0.35-0.8 m, tilts up to 40 deg, any roll),
    with every corner inside the image, plus Gaussian pixel noise of SIGMA_PX per axis.
    ``partial`` keeps a random 40-100 % of each view's corners (partial AprilGrid views)."""
    rng = np.random.default_rng(seed)
    P = target.points - target.points.mean(axis=0)
    views: list[View] = []
    while len(views) < n_views:
        tilt_axis = np.r_[rng.normal(size=2), 0.0]
        R = _rot(tilt_axis / np.linalg.norm(tilt_axis), np.deg2rad(rng.uniform(0, 40))) @ _rot(
            [0, 0, 1], rng.uniform(-np.pi, np.pi)
        )
        z = rng.uniform(0.35, 0.8)
        t = np.array([rng.uniform(-0.25, 0.25) * z, rng.uniform(-0.2, 0.2) * z, z])
        p_c = P @ R.T + t
        uv, _ = camera.project(p_c, jacobian=False)
        if not (camera.in_front(p_c).all() and camera.in_image(uv, margin=5).all()):
            continue
        uv = uv + rng.normal(scale=SIGMA_PX, size=uv.shape)
        ids = np.arange(len(P))
        if partial:
            ids = np.sort(rng.choice(len(P), size=rng.integers(int(0.4 * len(P)), len(P) + 1), replace=False))
        views.append(View(len(views), Observation(ids, uv[ids]), f"sim view {len(views)}"))
    return views


@pytest.mark.parametrize("model", list(MODELS))
def test_simulated_camera_within_reported_sigma(model: str) -> None:
    truth = TRUTH[model]
    z_all = []
    for seed in range(8):
        views = simulate_views(truth, SIM_BOARD, 25, seed, partial=seed >= 4)
        res = calibrate_intrinsics(views, SIM_BOARD, truth.resolution, model)
        est = np.r_[res.camera.intrinsics, res.camera.distortion_coeffs]
        true = np.r_[truth.intrinsics, truth.distortion_coeffs]
        std = np.array([res.std[n] for n in PARAM_NAMES[truth.distortion_model]])
        z = (est - true) / std
        z_all.append(z)
        # the residual RMS estimates the corner noise: sqrt(2) * 0.3 px per corner
        assert res.rms_per_axis_px == pytest.approx(SIGMA_PX, rel=0.1)
        assert np.all(np.abs(z) < 4.5), f"seed {seed}: normalized errors {np.round(z, 2)}"
    rms_z = float(np.sqrt(np.mean(np.square(z_all))))
    print(f"\n{model}: RMS of (estimate - truth) / reported sigma over 8 seeds x 8 parameters = {rms_z:.2f}")
    assert 0.5 < rms_z < 1.6  # a sigma off by a factor 2 either way fails


@pytest.mark.parametrize("model", list(MODELS))
def test_projection_jacobians_match_finite_differences(model: str) -> None:
    cam = TRUTH[model]
    p_t = SIM_BOARD.points[::7]
    rvec, tvec = np.array([0.2, -0.3, 0.1]), np.array([0.05, -0.02, 0.6])
    uv, J_i, J_p = projection_jacobians(cam, p_t, rvec, tvec)
    assert np.allclose(uv, cam.project(p_t @ cv2.Rodrigues(rvec)[0].T + tvec, jacobian=False)[0], atol=1e-6)

    def f(x: np.ndarray) -> np.ndarray:
        c = CameraModel(tuple(x[:4]), cam.distortion_model, tuple(x[4:8]), cam.resolution)
        return projection_jacobians(c, p_t, x[8:11], x[11:14])[0].ravel()

    x0 = np.r_[cam.intrinsics, cam.distortion_coeffs, rvec, tvec]
    J_num = np.zeros((2 * len(p_t), 14))
    for k in range(14):
        h = 1e-6 * max(1.0, abs(x0[k]))
        e = np.zeros(14)
        e[k] = h
        J_num[:, k] = (f(x0 + e) - f(x0 - e)) / (2 * h)
    assert np.allclose(np.c_[J_i, J_p], J_num, rtol=1e-5, atol=1e-4)


# ------------------------------------------------------------------ real images


@pytest.fixture(scope="module")
def left_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """OpenCV's 13 left images as an image folder cam0/<n>.jpg (symlinks)."""
    src = real("opencv_stereo")
    root = tmp_path_factory.mktemp("left")
    (root / "cam0").mkdir()
    for f in sorted(src.glob("left*.jpg")):
        (root / "cam0" / f"{int(f.stem[4:])}.jpg").symlink_to(f)
    return root


def test_opencv_left_against_reference(left_folder: Path) -> None:
    """Against ``left_intrinsics.yml`` (OpenCV's sample: fx = fy tied, k3 free, corners refined with
    an 11x11 cornerSubPix window: 0.39 px average error, one view at 1.18 px).  Our corners
    (window scaled to the square size) fit to 0.18 px RMS; the different corners and model move f
    by ~3 px (~7 of our sigma: a systematic difference between two corner sets of the same
    images, not noise), so we compare at the level that matters downstream: f within 1 %, the
    principal point within 5 px, and the two models' pixel maps within 4 px over the image
    region the corners cover (typical 1.7 px)."""
    src = real("opencv_stereo")
    fs = cv2.FileStorage(str(src / "left_intrinsics.yml"), cv2.FILE_STORAGE_READ)
    K_ref, D_ref = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat().ravel()
    fs.release()
    res = run_intrinsics(left_folder, BOARD, "cam0", progress=False)
    fx, fy, cx, cy = res.camera.intrinsics
    assert res.n_images == 13 and res.n_detected == 13
    assert res.rms_px < 0.3  # the sample's own calibration reports 0.39 px with its coarser corners
    assert abs(fx - K_ref[0, 0]) < 0.01 * K_ref[0, 0] and abs(fy - K_ref[1, 1]) < 0.01 * K_ref[1, 1]
    assert abs(cx - K_ref[0, 2]) < 5.0 and abs(cy - K_ref[1, 2]) < 5.0
    corners = np.concatenate([v.observation.pixels for v in res.views])
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    xy = cv2.undistortPoints(corners.reshape(-1, 1, 2), K_ref, D_ref, criteria=crit).reshape(-1, 2)
    uv = res.camera.project(np.c_[xy, np.ones(len(xy))], jacobian=False)[0]
    gap = np.linalg.norm(uv - corners, axis=1)
    print(
        f"\nOpenCV left: fx {fx:.2f} fy {fy:.2f} cx {cx:.2f} cy {cy:.2f} (1-sigma {res.std['fx']:.2f} "
        f"{res.std['fy']:.2f} {res.std['cx']:.2f} {res.std['cy']:.2f}) px, RMS {res.rms_px:.3f} px; reference fx=fy "
        f"{K_ref[0, 0]:.2f} cx {K_ref[0, 2]:.2f} cy {K_ref[1, 2]:.2f}; pixel-map gap median {np.median(gap):.2f} "
        f"max {gap.max():.2f} px"
    )
    assert gap.max() < 4.0

    # our 1-sigma is OpenCV's (same Gauss-Newton covariance, same residual variance)
    obj = [BOARD.points[v.observation.ids].astype(np.float32) for v in res.views]
    img = [v.observation.pixels.astype(np.float32) for v in res.views]
    out = cv2.calibrateCameraExtended(obj, img, (640, 480), None, None, flags=cv2.CALIB_FIX_K3)
    assert np.allclose([res.std[n] for n in PARAM_NAMES["radtan"]], out[5].ravel()[:8], rtol=1e-3)


def test_bag_and_folder_agree(left_folder: Path, tmp_path: Path) -> None:
    src = real("opencv_stereo")
    frames = []
    for k, f in enumerate(sorted(src.glob("left*.jpg"))):
        img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        right = cv2.imread(str(f).replace("left", "right"), cv2.IMREAD_GRAYSCALE)
        frames.append(FramePair(1_000_000_000 * (k + 1), right, img))
    bag1 = write_ros1_bag(tmp_path / "s.bag", frames)
    bag2 = write_ros2_bag(tmp_path / "s2", frames, storage="mcap")
    folder = run_intrinsics(left_folder, BOARD, "cam0", progress=False)
    for bag in (bag1, bag2):
        out = tmp_path / f"camchain_{bag.name}.yaml"
        got = run_intrinsics(bag, BOARD, "cam1", out=out, progress=False)  # left images on /cam1/image_raw
        assert np.allclose(got.camera.intrinsics, folder.camera.intrinsics, atol=1e-6)
        entry = load_camchain(out)["cam1"]
        assert entry.rostopic == "/cam1/image_raw"
        assert np.allclose(entry.camera.intrinsics, got.camera.intrinsics)


def test_cli_writes_and_updates_camchain(left_folder: Path, tmp_path: Path) -> None:
    target = tmp_path / "target.yaml"
    target.write_text(yaml.safe_dump(BOARD.to_kalibr()))
    out = tmp_path / "camchain.yaml"
    out.write_text(
        yaml.safe_dump(
            {
                "cam1": {
                    "camera_model": "pinhole",
                    "intrinsics": [1.0, 1.0, 0.0, 0.0],
                    "distortion_model": "radtan",
                    "distortion_coeffs": [0.0, 0.0, 0.0, 0.0],
                    "resolution": [640, 480],
                    "T_cn_cnm1": np.eye(4).tolist(),
                }
            }
        )
    )
    summary = tmp_path / "summary.json"
    argv = [str(left_folder), "--target", str(target), "--out", str(out), "--summary", str(summary)]
    assert main(["intrinsics", *argv, "--model", "pinhole-equidistant"]) == 0
    chain = load_camchain(out)
    assert set(chain) == {"cam0", "cam1"}  # cam1 kept
    assert chain["cam0"].camera.distortion_model == "equidistant"
    assert chain["cam1"].extra["T_cn_cnm1"] == np.eye(4).tolist()
    assert summary.is_file()


def test_bad_input_names_the_path(left_folder: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=str(left_folder / "cam1")):
        run_intrinsics(left_folder, BOARD, "cam1", progress=False)
    wrong = TargetGeometry.aprilgrid(6, 6, 0.088, 0.3)  # not in these images
    out = tmp_path / "camchain.yaml"
    with pytest.raises(ValueError, match=f"{left_folder / 'cam0'}.*not found"):
        run_intrinsics(left_folder, wrong, "cam0", out=out, every=13, progress=False)  # one image: fast
    assert not out.exists()
    with pytest.raises(ValueError, match="no such file"):
        run_intrinsics(tmp_path / "missing", BOARD, "cam0", progress=False)
    with pytest.raises(ValueError, match="camera model"):
        run_intrinsics(left_folder, BOARD, "cam0", model="omni-radtan", progress=False)
    bag = write_ros1_bag(tmp_path / "x.bag", [FramePair(1, np.zeros((8, 8), np.uint8), np.zeros((8, 8), np.uint8))])
    with pytest.raises(ValueError, match=f"{bag}: topic /left not found"):
        run_intrinsics(bag, BOARD, "cam0", topic="/left", progress=False)


def test_select_views_spreads_over_the_recording() -> None:
    views = [View(k, Observation([0], [[0.0, 0.0]]), "") for k in range(100)]
    picked = [v.timestamp_ns for v in select_views(views, 5)]
    assert picked == [0, 25, 50, 74, 99]
    assert len(select_views(views, 0)) == 100


def test_detect_views_reads_every_nth(left_folder: Path) -> None:
    views, res, n_read, _ = detect_views(left_folder, "cam0", BOARD, every=4, progress=False)
    assert n_read == 4 and len(views) == 4 and res == (640, 480)


# ------------------------------------------------------------------ health checks (issue 13)


def test_real_left_camera_is_healthy(left_folder: Path) -> None:
    res = run_intrinsics(left_folder, BOARD, "cam0", progress=False)
    report = res.extra["health"]
    assert report.healthy and not report.warnings, report.failure_text()
    assert {c.name for c in report.checks} == {
        "finite", "residuals.rms", "residuals.views", "principal_point", "distortion.fold",
    }  # fmt: skip


def test_unhealthy_intrinsics_exit_3_and_write_nothing_unless_accepted(
    left_folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A limit below the real 0.2 px RMS: exit 3 naming the check, no file; accepted: written, marked."""
    target = tmp_path / "target.yaml"
    target.write_text(yaml.safe_dump(BOARD.to_kalibr()))
    out, summary = tmp_path / "camchain.yaml", tmp_path / "summary.json"
    argv = ["intrinsics", str(left_folder), "--target", str(target), "--out", str(out), "--summary", str(summary)]
    assert main([*argv, "--max-rms", "0.05", "-q"]) == 3
    assert "residuals.rms: RMS reprojection error" in capsys.readouterr().err
    assert not out.exists() and not summary.exists()
    assert main([*argv, "--max-rms", "0.05", "--accept-unhealthy", "-q"]) == 0
    health = yaml.safe_load(summary.read_text())["health"]
    assert health["healthy"] is False and health["failures"][0].startswith("residuals.rms")
    assert out.is_file()


def test_distortion_that_folds_inside_the_image_is_caught() -> None:
    good = CameraModel((460.0, 460.0, 320.0, 240.0), "radtan", (-0.28, 0.07, 0.0, 0.0), (640, 480))
    assert fold_check(good).passed
    # r_d = r (1 + k1 r^2) turns back at r^2 = -1 / (3 k1) = 1/3, where r_d = 0.385: the image corners
    # are at distorted radius 0.87, beyond what the model can reach
    folded = CameraModel((460.0, 460.0, 320.0, 240.0), "radtan", (-1.0, 0.0, 0.0, 0.0), (640, 480))
    check = fold_check(folded, observed=0.5)
    assert not check.passed and check.severity == "error"
    assert "folds at distorted normalized radius 0.38" in check.message
    assert fold_check(folded, observed=0.3).severity == "warning"  # only beyond the corners the views saw
    off = CameraModel((460.0, 460.0, 700.0, 240.0), "radtan", (0.0, 0.0, 0.0, 0.0), (640, 480))
    assert not principal_point_check(off).passed and principal_point_check(good).passed
