"""Per-image corner noise (dcc_fg.noise_floor.relative_image_noise) and the weighting it gives the
calibration: cameras whose detections differ in noise (resolution, blur, lens) are weighted by their
own noise, which the reported covariance then reflects.

The heteroscedastic data are the pinned 2-DOF scene with the static camera's corners at
``SIGMA_STATIC`` px and the dynamic camera's at a random 1.5-3x that (extra Gaussian noise added to
the simulated dynamic pixels)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from conftest import shared_data as real
from scipy.stats import chi2
from test_cluster_calibration import euroc_pair
from test_real_stereo import euroc_sensor

from dcc_fg.calibrate import CalibrationOptions, calibrate, corner_sigma
from dcc_fg.cli import main
from dcc_fg.data import CalibrationDataset
from dcc_fg.model import GimbalCalibration
from dcc_fg.noise_floor import noise_floor, relative_image_noise
from dcc_fg.sim.calibration_scene import SceneConfig, simulate_calibration
from dcc_fg.studies.calibration_accuracy import cramer_rao_bound, evaluate_against_truth, nees_T_ds

SIGMA_STATIC = 0.2  # px


def with_dynamic_noise(data: CalibrationDataset, sigma_from: float, sigma_to: float, seed: int) -> CalibrationDataset:
    """``data`` with Gaussian noise added to the dynamic camera's corners so that their sigma goes
    from ``sigma_from`` to ``sigma_to`` px (per axis)."""
    rng = np.random.default_rng(1000 + seed)
    extra = np.sqrt(sigma_to**2 - sigma_from**2)
    snaps = []
    for s in data.snapshots:
        noisy = s.dynamic.pixels + extra * rng.standard_normal(s.dynamic.pixels.shape)
        snaps.append(replace(s, dynamic=replace(s.dynamic, pixels=noisy)))
    return replace(data, snapshots=snaps)


def heteroscedastic(seed: int):
    """(simulation, data with the dynamic camera at ratio x the static noise, ratio)."""
    ratio = float(np.random.default_rng(seed).uniform(1.5, 3.0))
    sim = simulate_calibration(seed, SceneConfig(n_joints=2, n_validation=1, pixel_sigma=SIGMA_STATIC))
    return sim, with_dynamic_noise(sim.calibration_set, SIGMA_STATIC, ratio * SIGMA_STATIC, seed), ratio


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_relative_image_noise_recovers_the_cameras_noise_ratio(seed: int) -> None:
    _, data, ratio = heteroscedastic(seed)
    floor = noise_floor(data)
    scale = relative_image_noise(floor)
    rms = np.sqrt(np.mean(scale**2, axis=0))
    # each camera's floor has >= 1000 degrees of freedom: its sigma is known to ~2 % (1 sigma)
    assert rms[1] / rms[0] == pytest.approx(ratio, rel=0.08)
    # images are shrunk towards their camera: within a camera the scale varies only by the
    # chi-square scatter of an image's own ~80 degrees of freedom (about 16 % in variance)
    assert np.all(np.abs(scale[:, 0] / np.median(scale[:, 0]) - 1.0) < 0.25)


def test_noiseless_data_weight_every_image_alike() -> None:
    sim = simulate_calibration(0, SceneConfig(n_joints=2, n_validation=1, pixel_sigma=0.0))
    np.testing.assert_array_equal(relative_image_noise(noise_floor(sim.calibration_set)), 1.0)


def test_corner_noise_option_is_checked() -> None:
    with pytest.raises(ValueError, match="corner_noise 'per-camera' is not one of per-image, shared"):
        CalibrationOptions(corner_noise="per-camera")


@pytest.mark.slow
def test_per_image_weighting_is_efficient_and_its_covariance_honest() -> None:
    """Six random seeds: the per-image weighting reaches the Cramer-Rao bound of the actual
    (heteroscedastic) noise and reports each camera's noise and an honest T_ds covariance; the
    shared sigma is printed for comparison (its weights and covariance mix both cameras)."""
    seeds = range(6)
    err2, crb2, nees, nees_shared, err2_shared = np.zeros(2), np.zeros(2), [], [], np.zeros(2)
    for seed in seeds:
        sim, data, ratio = heteroscedastic(seed)
        truth = (sim.truth, sim.joints_calibration)
        res = calibrate(data, sim.initial, CalibrationOptions())
        shared = calibrate(data, sim.initial, CalibrationOptions(corner_noise="shared"))
        sig = corner_sigma(res)
        assert sig["static"] == pytest.approx(SIGMA_STATIC, rel=0.08)
        assert sig["dynamic"] == pytest.approx(ratio * SIGMA_STATIC, rel=0.08)
        crb = cramer_rao_bound(data, *truth, sim.T_st_calibration, (SIGMA_STATIC, ratio * SIGMA_STATIC))
        for r, e2, n in ((res, err2, nees), (shared, err2_shared, nees_shared)):
            err = evaluate_against_truth(r, *truth)
            e2 += [err.rotation_rms**2, err.translation_rms**2]
            n.append(float(np.mean(nees_T_ds(err.T_ds, r.T_ds_covariances))))
        crb2 += [crb.rotation_rms**2, crb.translation_rms**2]
    n = len(seeds)
    ratio_weighted, ratio_shared = np.sqrt(err2 / crb2), np.sqrt(err2_shared / crb2)
    lo, hi = chi2.ppf([0.025, 0.975], 6 * n) / n
    print(
        f"error / CRB per-image {ratio_weighted.round(3)}, shared {ratio_shared.round(3)}; mean NEES per-image "
        f"{np.mean(nees):.2f}, shared {np.mean(nees_shared):.2f} (95 % interval {lo:.2f}-{hi:.2f})"
    )
    limit = np.sqrt(chi2.ppf(0.99, 6 * n) / (6 * n))  # sampling bound of an efficient estimator
    assert np.all(ratio_weighted < limit)
    assert lo < np.mean(nees) < hi


def test_euroc_stereo_per_image_weights_agree_with_euroc_extrinsics(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Real data (EuRoC ``cam_april``, cam0 + cam1 as a rigid pair, L = 0): the per-image floors differ
    (cam1's corners are noisier, and blurred images noisier than sharp ones); weighted by them, the
    baseline agrees with EuRoC's own calibration (sensor.yaml, T_c1c0) better than with one sigma
    (both 30 snapshots)."""
    mav0 = real("euroc_v1_01_micro") / "MicroEurocDataset" / "mav0"
    T_B0, _ = euroc_sensor(mav0 / "cam0" / "sensor.yaml")
    T_B1, _ = euroc_sensor(mav0 / "cam1" / "sensor.yaml")
    t_euroc = (np.linalg.inv(T_B1) @ T_B0)[:3, 3]  # cam0 (static) -> cam1 (dynamic)
    pair, _ = euroc_pair("cam_april", tmp_path).pair("cam0", "cam1")
    start = GimbalCalibration(np.zeros(12), 0)
    per_image = calibrate(pair, start, CalibrationOptions())
    shared = calibrate(pair, start, CalibrationOptions(corner_noise="shared"))
    d_image = np.linalg.norm(per_image.T_ds(0)[:3, 3] - t_euroc)
    d_shared = np.linalg.norm(shared.T_ds(0)[:3, 3] - t_euroc)
    sigma = np.sqrt(np.trace(per_image.T_ds_covariances[0][3:, 3:]))
    mm = 1e3 * np.array([d_image, sigma, d_shared])
    print(f"baseline - EuRoC, mm: per-image {mm[0]:.2f} (1-sigma {mm[1]:.2f}), shared {mm[2]:.2f}")
    # measured: 1.61 mm against 6.56 mm. Not within our 1-sigma (0.32 mm) of EuRoC's value: theirs is
    # another estimate (Kalibr, other images), with an uncertainty of its own that sensor.yaml does not give
    assert d_image < 0.5 * d_shared


def test_cluster_calibration_refuses_corner_noise_by_name(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    """The N-camera calibration whitens every image with one sigma: the option is refused, not ignored."""
    rc = main(["calibrate", str(tmp_path), "--camchain", "c.yaml", "--mounts", "m.yaml", "--corner-noise", "shared"])
    assert rc == 2
    assert "--corner-noise: not available with an N-camera cluster" in capsys.readouterr().err
