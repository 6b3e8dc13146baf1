"""Smoother keys (gtsam symbol_shorthand) and the per-keyframe state record."""

from __future__ import annotations

import gtsam
import numpy as np

from dcc_fg.vio.backend.keys import bias_key, camera_key, landmark_key, pose_key, theta_key, velocity_key
from dcc_fg.vio.backend.state import KeyframeState, result_from_states

KINDS = {"x": pose_key, "v": velocity_key, "b": bias_key, "t": theta_key, "c": camera_key, "l": landmark_key}


def test_keys_are_distinct_and_round_trip() -> None:
    keys = {}
    for char, make in KINDS.items():
        for k in (0, 1, 7, 12345):
            key = make(k)
            sym = gtsam.Symbol(key)
            assert (chr(sym.chr()), sym.index()) == (char, k)
            assert key == gtsam.symbol(char, k)  # the keys the smoother always used
            keys[key] = (char, k)
    assert len(keys) == len(KINDS) * 4


def _values(k: int, theta: np.ndarray | None) -> tuple[gtsam.Values, gtsam.Pose3]:
    pose = gtsam.Pose3(gtsam.Rot3.Rz(0.3), np.array([1.0, 2.0, 3.0]))
    values = gtsam.Values()
    values.insert(pose_key(k), pose)
    values.insert(velocity_key(k), np.array([0.1, -0.2, 0.3]))
    values.insert(bias_key(k), gtsam.imuBias.ConstantBias(np.array([0.01, 0.02, 0.03]), np.array([1e-3, 2e-3, 3e-3])))
    if theta is not None:
        values.insert(theta_key(k), theta)
    return values, pose


def test_keyframe_state_from_values() -> None:
    values, pose = _values(4, np.array([0.5, -0.25]))
    s = KeyframeState.from_values(values, 4, 123, np.zeros(2))
    assert s.t_ns == 123
    np.testing.assert_array_equal(s.T_WI, pose.matrix())
    np.testing.assert_array_equal(s.v_W, [0.1, -0.2, 0.3])
    np.testing.assert_array_equal(s.acc_bias, [0.01, 0.02, 0.03])
    np.testing.assert_array_equal(s.gyro_bias, [1e-3, 2e-3, 3e-3])
    np.testing.assert_array_equal(s.theta, [0.5, -0.25])
    # no joint angles in the values: the default (copied)
    values, _ = _values(2, None)
    default = np.array([0.1, 0.2])
    s = KeyframeState.from_values(values, 2, 5, default)
    np.testing.assert_array_equal(s.theta, default)
    assert s.theta is not default
    assert s.with_theta(np.array([1.0, 2.0])).theta.tolist() == [1.0, 2.0] and s.theta.tolist() == [0.1, 0.2]


def test_keyframe_state_from_prediction_and_result() -> None:
    nav = gtsam.NavState(gtsam.Pose3(gtsam.Rot3(), np.array([1.0, 0.0, 0.0])), np.array([0.0, 2.0, 0.0]))
    bias = gtsam.imuBias.ConstantBias(np.ones(3), np.full(3, 0.5))
    states = {
        1: KeyframeState.from_prediction(20, nav, bias, np.array([0.2])),
        0: KeyframeState.from_prediction(10, nav, bias, np.array([0.1])),
    }
    res = result_from_states(states, "dcc", {"keyframes": 2})
    assert res.timestamps_ns.tolist() == [10, 20] and res.timestamps_ns.dtype == np.int64
    assert res.T_WI.shape == (2, 4, 4) and res.theta.tolist() == [[0.1], [0.2]]
    assert res.mode == "dcc" and res.stats == {"keyframes": 2}
    mono = {0: KeyframeState.from_prediction(10, nav, bias, np.zeros(0))}
    assert result_from_states(mono, "mono", {}).theta.shape == (1, 0)
