"""Structureless landmarks (``VioOptions(landmarks="smart")``): option checks, the smart-factor
bookkeeping against the fixed-lag smoother, and a simulated flight against the explicit-landmark run."""

from __future__ import annotations

from typing import Any

import gtsam
import numpy as np
import pytest

from dcc_fg.studies.vio_study import StudyConfig, run_mode
from dcc_fg.vio.backend import VioOptions
from dcc_fg.vio.backend.keys import camera_key, pose_key
from dcc_fg.vio.backend.structureless import StructurelessLandmarks
from dcc_fg.vio.backend.window import key_timestamps


@pytest.mark.parametrize(
    "bad",
    [
        {"smoother": "batch"},
        {"estimate_time_offsets": False},
        {"time_offset_freeze_sigma": 2.5e-4},
        {"gimbal_factor": "eq14"},
    ],
)
def test_smart_landmarks_refuse_settings_without_camera_poses(bad: dict[str, Any]) -> None:
    with pytest.raises(ValueError, match="landmarks 'smart' needs"):
        VioOptions(landmarks="smart", **bad)
    VioOptions(landmarks="explicit", **bad)  # the explicit landmarks take them


def test_unknown_landmark_kind_is_refused() -> None:
    with pytest.raises(ValueError, match="landmarks 'structureless' is not one of explicit, smart"):
        VioOptions(landmarks="structureless")


def _camera_poses(n: int) -> list[gtsam.Pose3]:
    """Cameras 0.3 m apart along x looking along +z (camera -> W)."""
    return [gtsam.Pose3(gtsam.Rot3(), np.array([0.3 * k, 0.0, 0.0])) for k in range(n)]


def test_smart_factors_are_replaced_and_restart_after_marginalization() -> None:
    """Each update replaces a landmark's factor (the old slot removed); when its oldest camera pose is
    marginalized the factor goes with it and the landmark starts a new one from its next observation."""
    rng = np.random.default_rng(3)
    points = rng.uniform([-2, -2, 6], [2, 2, 10], size=(20, 3))
    poses = _camera_poses(8)
    smart = StructurelessLandmarks(sigma=1e-3, max_depth=60.0)
    p = gtsam.ISAM2Params()
    smoother = gtsam.IncrementalFixedLagSmoother(2.5, p)  # keeps 3 poses (1 s apart)
    triangulated = 0
    for k, T_Wc in enumerate(poses):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        key = camera_key(k)
        values.insert(key, T_Wc)
        noise = gtsam.noiseModel.Isotropic.Sigma(6, 1e-2 if k else 1e-4)
        graph.add(
            gtsam.PriorFactorPose3(key, T_Wc, noise)
            if k == 0
            else gtsam.BetweenFactorPose3(camera_key(k - 1), key, poses[k - 1].between(T_Wc), noise)
        )
        for lm, p_W in enumerate(points):
            p_c = T_Wc.transformTo(p_W)
            smart.add(lm, key, p_c[:2] / p_c[2])
        held = sorted(smart.slot.values())
        remove = smart.stage(graph)
        assert sorted(remove) == held  # every landmark seen again: its factor of the last update goes
        if k == 2:
            assert len(remove) == len(points)  # the factors built at k = 1 (two views)
        stamps = key_timestamps({key: k * 1_000_000_000})
        smoother.update(graph, values, stamps, remove)
        smart.adopt(list(smoother.getISAM2Result().getNewFactorsIndices()))
        est = smoother.calculateEstimate()
        smart.prune(est)
        live = smoother.getFactors()
        for lm, slot in smart.slot.items():  # every tracked slot holds this landmark's current factor
            assert live.exists(slot) and set(live.at(slot).keys()) == set(smart.keys[lm])
        if k >= 3:  # c(k-3) left: the factors started at it were marginalized, the landmarks started afresh
            assert not est.exists(camera_key(k - 3))
            assert all(est.exists(keys[0]) for keys in smart.keys.values())
        positions = smart.positions(est)
        triangulated += len(positions)
        for lm, p_W in positions.items():  # noise-free views: the triangulation is the point
            np.testing.assert_allclose(p_W, points[lm], atol=1e-6)
    assert triangulated > 0
    assert not est.exists(pose_key(0))


CFG = StudyConfig(duration=20.0, density=0.5, pixel_sigma=0.5, seed=1)


@pytest.mark.slow  # two 20 s tracks-level VIO runs (~40 s)
def test_smart_landmarks_match_explicit_accuracy_on_a_simulated_flight() -> None:
    explicit = run_mode("dcc", CFG)
    smart = run_mode("dcc", CFG, options={"landmarks": "smart"})
    assert smart["failed_updates"] == 0 and smart["result"].stats.get("segments_started", 0) == 0
    e, s = explicit["normalized_translation_rmse_percent"], smart["normalized_translation_rmse_percent"]
    assert s <= 1.0 and s <= 1.5 * e, (s, e)
    assert max(smart["joint_rmse_rad"]) <= 1e-2
    print(f"\nnormalized translation RMSE explicit {e:.4f} %, smart {s:.4f} %; joints {smart['joint_rmse_rad']}")


@pytest.mark.slow  # four 12 s tracks-level VIO runs (~30 s)
@pytest.mark.parametrize("mode", ["scc", "mono"])
def test_smart_landmarks_in_the_locked_and_static_camera_modes(mode: str) -> None:
    """scc (gimbal images on their exposure-time poses) and mono take the structureless landmarks too."""
    cfg = StudyConfig(duration=12.0, density=0.5, pixel_sigma=0.5, seed=2)
    explicit = run_mode(mode, cfg)
    smart = run_mode(mode, cfg, options={"landmarks": "smart"})
    assert smart["failed_updates"] == 0 and smart["result"].stats.get("segments_started", 0) == 0
    e, s = explicit["normalized_translation_rmse_percent"], smart["normalized_translation_rmse_percent"]
    assert s <= 1.0 and s <= 1.5 * e, (s, e)
