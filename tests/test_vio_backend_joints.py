"""Joint-angle pieces of the smoother: the fit to known landmarks, the measurement prior, the start."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from dcc_fg.sim.trajectory import default_static_mount, flight_calibration
from dcc_fg.vio.backend.joints import fit_joint_angles_to_landmarks, joint_measurement_prior, start_joint_angles
from dcc_fg.vio.backend.keys import theta_key
from dcc_fg.vio.backend.options import InitialState, VioOptions
from factors.calibration import RobustLoss
from factors.chain import inv_se3

SIGMA = 0.5 / 460.0


def _scene(theta: np.ndarray, n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Body pose, landmarks in front of the gimbal camera and their noisy observations."""
    cal, T_sI = flight_calibration(), default_static_mount()
    rng = np.random.default_rng(seed)
    T_WI = np.eye(4)
    T_WI[:3, :3] = gtsam.Rot3.RzRyRx(0.1, 0.05, 0.3).matrix()
    T_WI[:3, 3] = [1.0, 2.0, 2.5]
    T_Wd = T_WI @ inv_se3(cal.T_ds(theta) @ T_sI)
    p_d = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(3, 10, n)])
    p_W = p_d @ T_Wd[:3, :3].T + T_Wd[:3, 3]
    z = p_d[:, :2] / p_d[:, 2:] + rng.normal(0.0, SIGMA, (n, 2))
    return T_WI, p_W, z, T_sI


def test_fit_recovers_known_joint_angles() -> None:
    cal = flight_calibration()
    theta = np.array([0.3, -0.2])
    T_WI, p_W, z, T_sI = _scene(theta, 40, 0)
    robust = RobustLoss("huber", 2.0)
    fit = fit_joint_angles_to_landmarks(T_WI, p_W, z, theta + 0.05, 1.0, cal.kin, T_sI, SIGMA, robust)
    np.testing.assert_allclose(fit, theta, atol=2e-3)
    z_bad = z.copy()
    z_bad[:3] += 0.05  # three gross outliers: the Huber weights keep them from dragging the fit
    fit_bad = fit_joint_angles_to_landmarks(T_WI, p_W, z_bad, theta + 0.05, 1.0, cal.kin, T_sI, SIGMA, robust)
    np.testing.assert_allclose(fit_bad, theta, atol=5e-3)
    # fewer than three observations: the start, as a copy
    theta0 = theta + 0.05
    out = fit_joint_angles_to_landmarks(T_WI, p_W[:2], z[:2], theta0, 1.0, cal.kin, T_sI, SIGMA, robust)
    assert np.array_equal(out, theta0) and out is not theta0


def test_joint_measurement_prior() -> None:
    cov = np.diag([1e-4, 4e-4])
    start, factor = joint_measurement_prior(theta_key(3), (np.array([0.1, 0.2]), cov), 2, 3.0)  # type: ignore[misc]
    np.testing.assert_array_equal(start, [0.1, 0.2])
    assert factor.keys() == [theta_key(3)]
    # whitened error of a 1-sigma (inflated) offset is 1
    values = gtsam.Values()
    values.insert(theta_key(3), np.array([0.1 + 3.0 * 1e-2, 0.2]))
    assert factor.error(values) == pytest.approx(0.5, rel=1e-5)
    assert joint_measurement_prior(theta_key(3), (np.zeros(3), cov), 2, 3.0) is None
    assert joint_measurement_prior(theta_key(3), (np.zeros(2), cov * np.nan), 2, 3.0) is None


def test_start_joint_angles() -> None:
    init = InitialState(0, np.eye(4), np.zeros(3), theta=np.array([0.1, 0.2]))
    np.testing.assert_array_equal(start_joint_angles(init, VioOptions(mode="dcc"), 2), [0.1, 0.2])
    np.testing.assert_array_equal(start_joint_angles(init, VioOptions(mode="scc", theta_fixed=(1.0, 2.0)), 2), [1, 2])
    with pytest.raises(ValueError, match="3 joint angles"):
        start_joint_angles(init, VioOptions(mode="dcc"), 3)
