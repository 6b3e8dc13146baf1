"""Unit tests of the calibration health checks' pieces (dcc_fg.calibration_health).

The end-to-end behaviour (healthy runs stay healthy, wrong models and pairings are caught) is in
tests/test_health.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from dcc_fg.calibrate import CalibrationOptions
from dcc_fg.calibration_health import circular_span, pairing_stamp_check
from dcc_fg.io.pairing import Pairing
from dcc_fg.noise_floor import noise_floor, pose_residual_jacobian, refine_poses
from dcc_fg.sim.calibration_scene import SceneConfig, default_cameras, simulate_calibration


def test_pose_jacobian_matches_numerical_differentiation() -> None:
    cam = default_cameras()[0]
    rng = np.random.default_rng(3)
    p_c = rng.uniform([-0.3, -0.2, 0.6], [0.3, 0.2, 1.2], size=(7, 3))
    _, J = pose_residual_jacobian(cam, p_c)
    eps = 1e-7
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        # left perturbation p -> Exp(omega) p + v, to first order p + omega x p + v
        plus = p_c + np.cross(d[:3], p_c) + d[3:]
        minus = p_c - np.cross(d[:3], p_c) - d[3:]
        num = (cam.project(plus, jacobian=False)[0] - cam.project(minus, jacobian=False)[0]) / (2 * eps)
        np.testing.assert_allclose(J[:, :, k], num, rtol=1e-5, atol=1e-4)


def test_noise_floor_recovers_the_pixel_noise() -> None:
    """The per-image floor's variance over its 2N - 6 degrees of freedom estimates the simulated
    corner noise (0.4 px) without any kinematic model, even from perturbed PnP starts."""
    sim = simulate_calibration(5, SceneConfig(n_calibration=30, n_validation=2))
    floor = noise_floor(sim.calibration_set)
    for c in range(2):
        assert abs(np.sqrt(floor.variance(c)) - 0.4) < 0.02
    # the refinement only lowers each image's sum of squares, and it converges from a rough start
    rng = np.random.default_rng(0)
    T0 = floor.T_st.copy()
    T0[:, :3, 3] += rng.normal(scale=0.01, size=(len(T0), 3))
    data = sim.calibration_set
    p_t = [data.target_points[s.static.ids] for s in data.snapshots]
    uv = [s.static.pixels for s in data.snapshots]
    _, ss, _ = refine_poses(data.static_camera, p_t, uv, T0, iterations=15)
    np.testing.assert_allclose(ss, floor.ss[:, 0], rtol=1e-3)


def test_max_iterations_below_one_is_refused() -> None:
    for bad in (0, -3):
        with pytest.raises(ValueError, match="max_iterations"):
            CalibrationOptions(max_iterations=bad)
    with pytest.raises(ValueError, match="pixel_sigma"):
        CalibrationOptions(pixel_sigma=float("nan"))


def test_stamp_gap_check() -> None:
    """The reader's pairing statistics (io.pairing.Pairing.statistics): synchronized cameras pass,
    cameras whose pairs are 20 ms apart at 50 ms frame periods (free-running) fail."""
    assert pairing_stamp_check(None) is None
    assert pairing_stamp_check({"pairing": {}}) is None
    static = [i * 50_000_000 for i in range(40)]
    synced = Pairing([(i, i) for i in range(40)], static_ns=static, dynamic_ns=[t + 100_000 for t in static])
    ok = pairing_stamp_check({"pairing": synced.statistics()})
    assert ok is not None and ok.passed and ok.threshold == pytest.approx(12.5)
    late = Pairing([(i, i) for i in range(40)], static_ns=static, dynamic_ns=[t + 20_000_000 for t in static])
    bad = pairing_stamp_check({"pairing": late.statistics()})
    assert bad is not None and not bad.passed and bad.value == pytest.approx(20.0)
    assert "synchroniz" in bad.message and "--sync-tolerance" in bad.hint


def test_circular_span_treats_whole_turns_as_the_same_angle() -> None:
    theta = np.array([[-3.2, 0.0], [3.1, 0.5], [3.0, 1.0]])
    span = circular_span(theta)
    assert span[0] == pytest.approx(0.1)  # -3.2 rad is 3.083 rad: the arc from 3.0 to 3.1
    assert span[1] == pytest.approx(1.0)
