"""The calibration simulator places the board in view of both cameras for every joint sample."""

from __future__ import annotations

import numpy as np
import pytest

from dcc_fg.sim.calibration_scene import (
    SceneConfig,
    joint_ranges,
    simulate_calibration,
    simulate_snapshots,
    true_kinematics,
)


def all_corners_visible(data, T_st: np.ndarray, thetas: np.ndarray, truth, margin: float) -> bool:  # noqa: ANN001
    """Every corner of every snapshot, noise-free, lies inside both images with the margin."""
    pts = data.target_points
    for T, th in zip(T_st, thetas, strict=True):
        p_s = pts @ T[:3, :3].T + T[:3, 3]
        T_ds = truth.T_ds(th)
        p_d = p_s @ T_ds[:3, :3].T + T_ds[:3, 3]
        for cam, p in ((data.static_camera, p_s), (data.dynamic_camera, p_d)):
            uv, _ = cam.project(p, jacobian=False)
            if not (np.all(cam.in_front(p)) and np.all(cam.in_image(uv, margin))):
                return False
    return True


@pytest.mark.parametrize("seed", [12, 17])
def test_three_joint_seeds_that_ran_out_of_board_draws(seed: int) -> None:
    """L = 3 seeds 12 and 17 raised "could not place the board" with 200 draws per snapshot: near
    the corners of the L = 3 joint ranges only ~0.3% of the random board poses fit both images."""
    cfg = SceneConfig(n_joints=3)
    sim = simulate_calibration(seed, cfg)
    for data, T_st, th in (
        (sim.calibration_set, sim.T_st_calibration, sim.joints_calibration),
        (sim.validation_set, sim.T_st_validation, sim.joints_validation),
    ):
        assert len(data.snapshots) == th.shape[0] == T_st.shape[0]
        assert all_corners_visible(data, T_st, th, sim.truth, cfg.margin_px)
        r = joint_ranges(3)
        assert np.all((th >= r[:, 0]) & (th <= r[:, 1]))


def test_unplaceable_joint_sample_moves_towards_the_centre() -> None:
    """A joint sample at which no board pose fits both images (pan 40 deg outside its range) is
    moved towards the mean of the samples; the returned angles are the ones rendered, the other
    samples and a joint that is the same in every sample (locked) are unchanged."""
    truth = true_kinematics(3)
    cfg = SceneConfig(n_joints=3)
    centre = joint_ranges(3).mean(axis=1)
    joints = np.array([centre, centre + np.deg2rad([5.0, 5.0, 0.0]), centre + np.deg2rad([52.0, 0.0, 0.0])])
    data, used, T_st = simulate_snapshots(truth, joints, cfg, np.random.default_rng(0), "unplaceable")
    np.testing.assert_array_equal(used[:2], joints[:2])
    assert np.all(used[:, 2] == joints[:, 2])
    assert 0.0 < abs(used[2, 0] - joints.mean(axis=0)[0]) < abs(joints[2, 0] - joints.mean(axis=0)[0])
    assert all_corners_visible(data, T_st, used, truth, cfg.margin_px)
