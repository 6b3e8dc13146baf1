"""An L = 3 mechanism with one joint that never moves is refused with the joint named.

Two moving joints already spread the relative rotations over three directions, so the rotation
spread test of ``check_joint_motion`` cannot see a locked joint of an L = 3 mechanism; the
two-joint structure test (``dcc_fg.joint_motion``) does. Pinned pan-tilt-roll scene, 20 snapshots.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from dcc_fg.auto_init import auto_initialize, pnp_T_ds
from dcc_fg.calibrate import CalibrationOptions, calibrate
from dcc_fg.data import CalibrationDataset
from dcc_fg.joint_motion import MAX_CHI2_PER_DOF, check_joint_motion, two_axis_fit
from dcc_fg.sim.calibration_scene import SceneConfig, SimulatedCalibration, simulate_calibration, simulate_snapshots
from factors import chain

FAST = CalibrationOptions(compute_covariance=False)


@pytest.fixture(scope="module")
def sim3() -> SimulatedCalibration:
    return simulate_calibration(2, SceneConfig(n_joints=3, n_calibration=20, n_validation=1))


def locked_data(sim: SimulatedCalibration, joint: int, guesses: bool) -> CalibrationDataset:
    """The scene's joint samples with ``joint`` (1-based) held at its mean; snapshot joints are the
    exact (locked) angles when ``guesses``, else None (angles fitted from PnP and the gimbal.yaml)."""
    th = sim.joints_calibration.copy()
    th[:, joint - 1] = th[:, joint - 1].mean()
    data, used, _ = simulate_snapshots(sim.truth, th, sim.config, np.random.default_rng(0), f"locked joint {joint}")
    assert np.ptp(used[:, joint - 1]) == 0.0
    snaps = [replace(s, joints=t if guesses else None) for s, t in zip(data.snapshots, th, strict=True)]
    return replace(data, snapshots=snaps)


@pytest.mark.parametrize("joint", [1, 2, 3])
@pytest.mark.parametrize("guesses", [True, False], ids=["with_guesses", "pnp_fit"])
def test_locked_joint_of_three_is_named_with_gimbal_yaml(sim3: SimulatedCalibration, joint: int, guesses: bool) -> None:
    data = locked_data(sim3, joint, guesses)
    with pytest.raises(ValueError, match=f"only two joints.*joint {joint} never moves.*joint {joint} is unobservable"):
        calibrate(data, sim3.initial, FAST)


@pytest.mark.parametrize("joint", [1, 2, 3])
def test_locked_joint_of_three_is_refused_without_gimbal_yaml(sim3: SimulatedCalibration, joint: int) -> None:
    """Automatic initialization: the images alone do not tell which joint is locked, and it says so."""
    data = locked_data(sim3, joint, guesses=False)
    with pytest.raises(ValueError, match="only two joints.*images alone do not tell which"):
        auto_initialize(data, 3)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_three_moving_joints_pass(seed: int) -> None:
    """The full pan-tilt-roll motion is far from any two-joint chain (chi-square ~1000 per degree of
    freedom against ~1 for a locked joint), and passes the check."""
    sim = simulate_calibration(seed, SceneConfig(n_joints=3, n_calibration=20, n_validation=1))
    fit = two_axis_fit(sim.calibration_set)
    assert fit.chi2 / fit.dof > 30 * MAX_CHI2_PER_DOF
    check_joint_motion(sim.calibration_set, pnp_T_ds(sim.calibration_set), 3)


def test_two_moving_joints_fit_the_two_joint_structure() -> None:
    """An L = 2 mechanism is a two-joint chain: chi-square about 1 per degree of freedom, and the
    fitted axes are joint 1's (in s) and joint 2's (in d; the +-12 deg range of joint 2 leaves the
    tilt of the plane about its chord weakly determined, hence the looser bound)."""
    sim = simulate_calibration(0, SceneConfig(n_calibration=30, n_validation=1))
    fit = two_axis_fit(sim.calibration_set)
    assert fit.chi2 / fit.dof < 2.0
    kin = sim.truth.kin
    w1 = chain.inv_se3(chain.se3_from_tau(kin[0:6]))[:3, 2]  # joint 1's axis in s
    # joint 2's axis in d: z of frame 1, = T_de A_2^-1 z (last link d, a, alpha of joint 2 in tau_d)
    R_de = chain.se3_from_tau(kin[6:12])[:3, :3]
    b2 = R_de @ chain.rot_x(-kin[17]) @ np.array([0.0, 0.0, 1.0])
    assert abs(fit.u @ w1) > np.cos(np.deg2rad(1.0))
    assert abs(fit.b @ b2) > np.cos(np.deg2rad(10.0))
