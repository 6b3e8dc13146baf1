"""Real stereo pairs calibrated as a zero-joint cluster (L = 0), against OpenCV and EuRoC.

With no joints ``T_ds`` is one constant transform (static camera s = left / cam0, dynamic camera
d = right / cam1), so dcc-fg's bundle calibration with the intrinsics held is the same maximum-
likelihood problem ``cv2.stereoCalibrate(..., CALIB_FIX_INTRINSIC)`` solves: both must land on the
same ``T_ds`` when given the same corners.

* OpenCV's stereo sample (13 pairs, 9x6 chessboard, 0.025 m squares): intrinsics of each camera
  from :func:`dcc_fg.intrinsics.calibrate_intrinsics` (``cv2.calibrateCamera`` with k3 fixed at 0:
  our radtan model has 4 coefficients), then
  both calibrations on the same corners; agreement within 1 mrad and 1 % of the baseline.
* EuRoC cam_april (30 stereo frames of yac AprilGrid detections) with EuRoC's published
  intrinsics, against EuRoC's published ``T_c1c0 = inv(T_BS1) T_BS0``: within 2 mrad and 2 mm and
  at least as close as ``cv2.stereoCalibrate`` on the same corners.  The corners only one camera
  sees are *not* used there: with EuRoC's radtan intrinsics the image periphery (where only one
  camera sees the board) has residuals up to ~20 px, and using those corners moves the estimate
  ~6 mrad / 6.6 mm away from the reference.  ``test_euroc_periphery_corners`` documents this.

Run with ``-s`` to see the numbers.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from conftest import shared_data as real
from scipy.spatial.transform import Rotation

from dcc_fg.calibrate import CalibrationOptions, CalibrationResult, calibrate
from dcc_fg.cli import main
from dcc_fg.data import CalibrationDataset, Observation, Snapshot, common_corners
from dcc_fg.detection import detect_checkerboard
from dcc_fg.intrinsics import View, calibrate_intrinsics
from dcc_fg.io.camchain import CamchainEntry, camchain_to_yaml
from dcc_fg.model import GimbalCalibration, load_calibration
from dcc_fg.sources.dataset import load_dataset
from dcc_fg.targets import TargetGeometry
from factors.camera import CameraModel

OPENCV_PAIRS = ("01", "02", "03", "04", "05", "06", "07", "08", "09", "11", "12", "13", "14")
CHESSBOARD = TargetGeometry.checkerboard(9, 6, 0.025)
L0 = GimbalCalibration(np.zeros(12), 0)  # tau_s is the gauge for L = 0; tau_d starts from PnP


def rotation_translation_error(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """Angle of R_b^T R_a (rad) and |t_a - t_b| (m)."""
    # scipy's rotation vector is exact for tiny angles (cv2.Rodrigues returns 0 below 1e-5 rad)
    angle = float(Rotation.from_matrix(T_b[:3, :3].T @ T_a[:3, :3]).magnitude())
    return angle, float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]))


def stereo_calibrate(data: CalibrationDataset) -> np.ndarray:
    """``cv2.stereoCalibrate`` with both cameras' intrinsics fixed on the corners both cameras see.

    Returns T_ds (4x4): points of the first (static) camera into the second (dynamic) camera.
    """
    obj, img_s, img_d = [], [], []
    for s in common_corners(data).snapshots:
        obj.append(data.target_points[s.static.ids].astype(np.float32))
        img_s.append(s.static.pixels.astype(np.float32))
        img_d.append(s.dynamic.pixels.astype(np.float32))
    cs, cd = data.static_camera, data.dynamic_camera
    out = cv2.stereoCalibrate(
        obj,
        img_s,
        img_d,
        cs.K,
        cs.opencv_dist,
        cd.K,
        cd.opencv_dist,
        tuple(cs.resolution),
        flags=cv2.CALIB_FIX_INTRINSIC,
        criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12),
    )
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = out[5], out[6].ravel()
    return T


def T_ds_sigma(res: CalibrationResult) -> tuple[float, float]:
    """Formal 1-sigma of T_ds: RMS rotation (rad) and translation (m) over the three axes."""
    assert res.T_ds_covariances is not None
    d = np.diag(res.T_ds_covariances[0])
    return float(np.sqrt(d[:3].sum())), float(np.sqrt(d[3:].sum()))


# ------------------------------------------------------------------ OpenCV stereo sample


def opencv_stereo_dataset(root: Path) -> CalibrationDataset:
    """Detect the 9x6 board in all 13 pairs; intrinsics of each camera from its own 13 views."""
    obs_l, obs_r = [], []
    for k in OPENCV_PAIRS:
        for side, out in (("left", obs_l), ("right", obs_r)):
            img = cv2.imread(str(root / f"{side}{k}.jpg"), cv2.IMREAD_GRAYSCALE)
            assert img is not None, f"{root}/{side}{k}.jpg does not decode"
            obs = detect_checkerboard(img, CHESSBOARD)
            assert len(obs) == 54, f"{side}{k}.jpg: board not found"
            out.append(obs)
    cams = [
        calibrate_intrinsics([View(k, o, "") for k, o in enumerate(obs)], CHESSBOARD, (640, 480)).camera
        for obs in (obs_l, obs_r)
    ]
    snaps = [Snapshot(i, a, b) for i, (a, b) in enumerate(zip(obs_l, obs_r, strict=True))]
    return CalibrationDataset(cams[0], cams[1], CHESSBOARD.points, snaps, str(root))


def test_opencv_stereo_matches_stereo_calibrate() -> None:
    data = opencv_stereo_dataset(real("opencv_stereo"))
    # corner 0 is the same physical corner in both cameras: left-right disparity keeps the board's
    # orientation, so corner 0 -> corner 8 points the same way (here: +u) in both images
    for s in data.snapshots:
        d_l = s.static.pixels[8] - s.static.pixels[0]
        d_r = s.dynamic.pixels[8] - s.dynamic.pixels[0]
        assert np.dot(d_l, d_r) > 0.9 * np.linalg.norm(d_l) * np.linalg.norm(d_r)
    res = calibrate(data, L0, CalibrationOptions(mode="encoderless"))
    T_dcc, T_cv = res.T_ds(0), stereo_calibrate(data)
    rot, trans = rotation_translation_error(T_dcc, T_cv)
    baseline = float(np.linalg.norm(T_cv[:3, 3]))
    s_rot, s_trans = T_ds_sigma(res)
    print(
        f"\nOpenCV stereo (13 pairs, L=0): baseline {baseline * 1e3:.2f} mm; dcc-fg vs cv2.stereoCalibrate: "
        f"{rot * 1e3:.2e} mrad, {trans * 1e3:.2e} mm ({100 * trans / baseline:.2e} % of the baseline); "
        f"dcc-fg formal 1-sigma {s_rot * 1e3:.3f} mrad, {s_trans * 1e3:.3f} mm; "
        f"RMS reprojection {res.reprojection_stats()['all']['rms_per_axis']:.3f} px/axis"
    )
    assert 0.05 < baseline < 0.2  # a stereo rig, not a degenerate solution
    assert rot < 1e-3
    assert trans < 0.01 * baseline
    # L = 0: tau_s is the whole gauge, so every tau_d entry is reported observable with a 1-sigma
    cal = res.calibration
    assert cal.observable is not None and cal.kin_std is not None
    assert np.all(cal.observable[6:12]) and not np.any(cal.observable[:6])
    assert np.all(np.isfinite(cal.kin_std[6:12]))
    # its translation sigmas are those of T_ds's translation (tau_s = identity here)
    assert np.isclose(np.sqrt(np.mean(cal.kin_std[9:12] ** 2)), s_trans, rtol=0.5)


def test_l0_start_does_not_depend_on_initial_tau_d() -> None:
    """L = 0 starts tau_d from the mean PnP T_ds, so a far-off initial value converges the same."""
    data = opencv_stereo_dataset(real("opencv_stereo"))
    opts = CalibrationOptions(compute_covariance=False)
    ref = calibrate(data, L0, opts).T_ds(0)
    far = GimbalCalibration(np.r_[0.1, -0.2, 0.3, 0.0, 0.0, 0.0, 0.5, -2.5, 1.0, 0.3, 0.0, 0.0], 0)
    got = calibrate(data, far, opts)
    rot, trans = rotation_translation_error(got.T_ds(0), ref)
    assert rot < 1e-6 and trans < 1e-6


# ------------------------------------------------------------------ EuRoC AprilGrid


def euroc_sensor(path: Path) -> tuple[np.ndarray, CameraModel]:
    """T_BS (camera -> body) and the intrinsics from an EuRoC/ASL ``sensor.yaml``."""
    text = path.read_text()
    if text.startswith("%YAML"):  # OpenCV-style directive PyYAML does not accept
        text = text.split("\n", 1)[1]
    d = yaml.safe_load(text)
    T_BS = np.asarray(d["T_BS"]["data"], dtype=float).reshape(4, 4)
    assert d["distortion_model"] == "radial-tangential"
    cam = CameraModel(tuple(d["intrinsics"]), "radtan", tuple(d["distortion_coefficients"]), tuple(d["resolution"]))
    return T_BS, cam


@pytest.fixture(scope="module")
def euroc() -> tuple[CalibrationDataset, np.ndarray]:
    """The 30 cam_april detection frames with EuRoC's intrinsics; the published T_c1c0."""
    mav0 = real("euroc_v1_01_micro") / "MicroEurocDataset" / "mav0"
    T_B0, cam0 = euroc_sensor(mav0 / "cam0" / "sensor.yaml")
    T_B1, cam1 = euroc_sensor(mav0 / "cam1" / "sensor.yaml")
    chain = {"cam0": CamchainEntry(cam0), "cam1": CamchainEntry(cam1)}
    data = load_dataset(real("euroc_aprilgrid") / "calib" / "cam_april", chain, progress=False)
    return data, np.linalg.inv(T_B1) @ T_B0


def test_euroc_matches_published_extrinsics(euroc: tuple[CalibrationDataset, np.ndarray]) -> None:
    data, T_ref = euroc
    assert len(data.snapshots) == 30
    common = common_corners(data)
    res = calibrate(common, L0, CalibrationOptions(mode="encoderless"))
    rot_dcc, trans_dcc = rotation_translation_error(res.T_ds(0), T_ref)
    rot_cv, trans_cv = rotation_translation_error(stereo_calibrate(data), T_ref)
    rot_same, trans_same = rotation_translation_error(res.T_ds(0), stereo_calibrate(data))
    s_rot, s_trans = T_ds_sigma(res)
    n = sum(len(s.static) for s in common.snapshots)
    print(
        f"\nEuRoC cam_april (30 frames, {n} common corners per camera, L=0) vs published T_c1c0: "
        f"dcc-fg {rot_dcc * 1e3:.4f} mrad, {trans_dcc * 1e3:.4f} mm; cv2.stereoCalibrate {rot_cv * 1e3:.4f} mrad, "
        f"{trans_cv * 1e3:.4f} mm; dcc-fg vs stereoCalibrate {rot_same * 1e3:.1e} mrad, {trans_same * 1e3:.1e} mm; "
        f"dcc-fg formal 1-sigma {s_rot * 1e3:.3f} mrad, {s_trans * 1e3:.3f} mm; "
        f"RMS reprojection {res.reprojection_stats()['all']['rms_per_axis']:.3f} px/axis"
    )
    assert rot_dcc < 2e-3 and trans_dcc < 2e-3
    # "at least as close": the same cost on the same corners; allow only solver round-off
    assert rot_dcc <= rot_cv + 1e-6 and trans_dcc <= trans_cv + 1e-6


def test_euroc_periphery_corners(euroc: tuple[CalibrationDataset, np.ndarray]) -> None:
    """Why the corners only one camera sees are left out above: with EuRoC's intrinsics they sit
    in the image periphery, where the radtan model fits badly, and they pull T_ds away."""
    data, T_ref = euroc
    res = calibrate(data, L0, CalibrationOptions(mode="encoderless", compute_covariance=False))
    rot, trans = rotation_translation_error(res.T_ds(0), T_ref)
    cam = data.dynamic_camera
    pix = np.concatenate([s.dynamic.pixels for s in data.snapshots])
    err = np.linalg.norm(np.concatenate(res.residuals_dynamic), axis=1)
    radius = np.linalg.norm(pix - np.asarray(cam.intrinsics[2:]), axis=1)
    inner, outer = np.median(err[radius < 250]), np.median(err[radius > 350])
    print(
        f"\nEuRoC, all {err.size + sum(len(s.static) for s in data.snapshots)} corners (incl. one-camera ones): "
        f"{rot * 1e3:.3f} mrad, {trans * 1e3:.3f} mm from the published T_c1c0; cam1 median residual "
        f"{inner:.2f} px within 250 px of the principal point, {outer:.2f} px beyond 350 px, max {err.max():.1f} px"
    )
    assert outer > 2.0 * inner  # the residuals grow towards the periphery: an intrinsics model error
    assert err.max() > 10.0  # ... large enough (> 10 px) to explain the shift


def test_common_corners_keeps_ids_aligned() -> None:
    s = Snapshot(7, Observation([1, 2, 5, 9], np.arange(8.0).reshape(4, 2)), Observation([9, 2, 3], np.ones((3, 2))))
    data = common_corners(
        CalibrationDataset(CameraModel((1, 1, 0, 0)), CameraModel((1, 1, 0, 0)), np.zeros((10, 3)), [s])
    )
    out = data.snapshots[0]
    assert out.static.ids.tolist() == [2, 9] and out.dynamic.ids.tolist() == [2, 9]
    assert out.static.pixels.tolist() == [[2.0, 3.0], [6.0, 7.0]]
    assert out.timestamp_ns == 7


def _cli_calibrate_cam_april(data: CalibrationDataset, tmp_path: Path, *options: str) -> Path:
    """``dcc-fg calibrate`` on the EuRoC cam_april folder with ``data``'s intrinsics as camchain and
    ``--joints 0`` plus ``options``; returns the output folder."""
    chain = {name: CamchainEntry(cam) for name, cam in (("cam0", data.static_camera), ("cam1", data.dynamic_camera))}
    camchain = tmp_path / "camchain.yaml"
    camchain.write_text(camchain_to_yaml(chain))
    folder = real("euroc_aprilgrid") / "calib" / "cam_april"
    out = tmp_path / "out"
    args = ["calibrate", str(folder), "--camchain", str(camchain), "--joints", "0", *options, "--out", str(out)]
    assert main(args) == 0
    return out


def test_cli_calibrates_l0_without_gimbal_yaml(euroc: tuple[CalibrationDataset, np.ndarray], tmp_path: Path) -> None:
    """``dcc-fg calibrate DATA --camchain C --joints 0`` needs no gimbal.yaml and gives calibrate()'s T_ds."""
    data, _ = euroc
    out = _cli_calibrate_cam_april(data, tmp_path)
    got = load_calibration(out / "calibration.yaml")
    ref = calibrate(data, L0, CalibrationOptions(compute_covariance=False)).T_ds(0)
    rot, trans = rotation_translation_error(got.T_ds(np.zeros(0)), ref)
    assert rot < 1e-7 and trans < 1e-7


def test_euroc_imu_april_diverse_views(tmp_path: Path) -> None:
    """The cam_april frames span only 1.5 s.  100 frames spread over the 72 s imu_april recording
    (same rig, same intrinsics) bring both estimators closer to the published T_c1c0, and the
    corners only one camera sees no longer pull the bundle away (the cam_april shift above is a
    property of those 30 views, not of the estimator)."""
    src = real("euroc_aprilgrid") / "calib" / "imu_april"
    mav0 = real("euroc_v1_01_micro") / "MicroEurocDataset" / "mav0"
    (T_B0, cam0), (T_B1, cam1) = (euroc_sensor(mav0 / c / "sensor.yaml") for c in ("cam0", "cam1"))
    T_ref = np.linalg.inv(T_B1) @ T_B0
    names = sorted(p.name for p in (src / "cam0").glob("*.csv"))
    for cam in ("cam0", "cam1"):
        (tmp_path / cam).mkdir()
        for k in np.linspace(0, len(names) - 1, 100).round().astype(int):
            (tmp_path / cam / names[k]).symlink_to(src / cam / names[k])
    data = load_dataset(tmp_path, {"cam0": CamchainEntry(cam0), "cam1": CamchainEntry(cam1)}, progress=False)
    opts = CalibrationOptions(compute_covariance=False)
    err_all = rotation_translation_error(calibrate(data, L0, opts).T_ds(0), T_ref)
    err_common = rotation_translation_error(calibrate(common_corners(data), L0, opts).T_ds(0), T_ref)
    err_cv = rotation_translation_error(stereo_calibrate(data), T_ref)
    print(
        f"\nEuRoC imu_april, {len(data.snapshots)} frames over 72 s, vs published T_c1c0: dcc-fg all corners "
        f"{err_all[0] * 1e3:.3f} mrad, {err_all[1] * 1e3:.3f} mm; dcc-fg common corners {err_common[0] * 1e3:.3f} "
        f"mrad, {err_common[1] * 1e3:.3f} mm; cv2.stereoCalibrate {err_cv[0] * 1e3:.3f} mrad, {err_cv[1] * 1e3:.3f} mm"
    )
    assert len(data.snapshots) >= 90
    for rot, trans in (err_all, err_common, err_cv):
        assert rot < 2e-3 and trans < 2e-3
    assert err_common[0] <= err_cv[0] + 1e-6 and err_common[1] <= err_cv[1] + 1e-6


def test_cli_common_corners_matches_published_extrinsics(
    euroc: tuple[CalibrationDataset, np.ndarray], tmp_path: Path
) -> None:
    """``dcc-fg calibrate ... --corners common`` is the common-corner calibration above, so on the
    EuRoC cam_april frames it lands within 2 mrad / 2 mm of the published T_c1c0 from the CLI."""
    data, T_ref = euroc
    out = _cli_calibrate_cam_april(data, tmp_path, "--corners", "common", "--quiet")
    got = load_calibration(out / "calibration.yaml").T_ds(np.zeros(0))
    ref = calibrate(common_corners(data), L0, CalibrationOptions(compute_covariance=False)).T_ds(0)
    assert max(rotation_translation_error(got, ref)) < 1e-7
    rot, trans = rotation_translation_error(got, T_ref)
    assert rot < 2e-3 and trans < 2e-3
    summary = json.loads((out / "summary.json").read_text())
    assert summary["input"]["corners"] == "common"
