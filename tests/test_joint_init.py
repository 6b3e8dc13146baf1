"""Joint angles from static <-> gimbal correspondences (epipolar fit), against simulated truth."""

from __future__ import annotations

import numpy as np
import pytest

from dcc_fg.sim.trajectory import flight_calibration
from dcc_fg.vio.joint_init import fit_joint_angles

SIGMA = 0.5 / 460.0  # 0.5 px of a 460 px focal length, in normalized units


def _pairs(theta: np.ndarray, n: int, seed: int, outliers: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points 2-15 m in front of the static camera seen by both cameras, 0.5 px noise (+ outliers)."""
    cal = flight_calibration()
    rng = np.random.default_rng(seed)
    T_ds = cal.T_ds(theta)
    p_s = np.column_stack([rng.uniform(-0.6, 0.6, n), rng.uniform(-0.45, 0.45, n), np.ones(n)])
    p_s *= rng.uniform(2.0, 15.0, n)[:, None]
    p_d = p_s @ T_ds[:3, :3].T + T_ds[:3, 3]
    keep = p_d[:, 2] > 0.5
    xy_s = p_s[keep, :2] / p_s[keep, 2:] + rng.normal(0, SIGMA, (keep.sum(), 2))
    xy_d = p_d[keep, :2] / p_d[keep, 2:] + rng.normal(0, SIGMA, (keep.sum(), 2))
    xy_d[:outliers] = rng.uniform(-0.5, 0.5, (outliers, 2))
    return xy_s, xy_d


def test_errors_match_the_reported_covariance() -> None:
    """Over 40 random scenes (0.5 px noise, no outliers) the normalized errors have unit RMS: the
    reported covariance is the estimator's (3-sigma band of an RMS of 40 samples: +-0.34)."""
    cal = flight_calibration()
    z, rms = [], []
    for seed in range(40):
        theta = np.array([np.pi / 2, 0.0]) + np.random.default_rng(seed).uniform(-0.3, 0.3, 2)
        xy_s, xy_d = _pairs(theta, 200, seed)
        fit = fit_joint_angles(cal, xy_s, xy_d, theta + 0.1)
        assert fit.covariance is not None and fit.inliers >= 0.97 * fit.pairs
        z.append((fit.theta - theta) / np.sqrt(np.diag(fit.covariance)))
        rms.append(fit.rms)
    z_rms = np.sqrt(np.mean(np.square(z), axis=0))
    assert np.all((z_rms > 0.66) & (z_rms < 1.34)), z_rms
    # the Sampson error is the 4-D noise (0.5 px per coordinate, both images) projected on the
    # normal of the epipolar constraint: one coordinate's sigma
    assert np.mean(rms) == pytest.approx(SIGMA, rel=0.1)


def test_outliers_are_tolerated() -> None:
    cal = flight_calibration()
    theta = np.array([1.7, 0.2])
    xy_s, xy_d = _pairs(theta, 200, 3, outliers=20)
    fit = fit_joint_angles(cal, xy_s, xy_d, theta - 0.1)
    assert fit.pairs - fit.inliers >= 15
    assert np.max(np.abs(fit.theta - theta)) < 3e-3


def test_grid_search_without_a_guess() -> None:
    cal = flight_calibration()
    theta = np.array([1.9, -0.25])
    xy_s, xy_d = _pairs(theta, 150, 7)
    fit = fit_joint_angles(cal, xy_s, xy_d, None)
    assert np.max(np.abs(fit.theta - theta)) < 5e-3


def test_too_few_pairs() -> None:
    cal = flight_calibration()
    xy_s, xy_d = _pairs(np.array([np.pi / 2, 0.0]), 5, 0)
    with pytest.raises(ValueError, match="cannot determine 2 joint angles"):
        fit_joint_angles(cal, xy_s, xy_d, None)
    with pytest.raises(ValueError, match="differ in shape"):
        fit_joint_angles(cal, np.zeros((10, 2)), np.zeros((9, 2)), None)
