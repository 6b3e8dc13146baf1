"""Per-keyframe state of the smoother as a named record, and the result built from the records.

A :class:`KeyframeState` is the latest estimate of one keyframe: its time (ns), the body pose
``T_WI`` (4x4, body/IMU frame I -> world W), the velocity ``v_W`` (m/s, in W), the IMU biases
(accelerometer m/s^2, gyroscope rad/s) and the joint angles ``theta`` (rad; empty without a gimbal).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

from dcc_fg.vio.backend.keys import bias_key, pose_key, theta_key, velocity_key
from dcc_fg.vio.backend.options import FloatArray, VioResult


@dataclass(frozen=True)
class KeyframeState:
    """Estimate of keyframe state (see module docstring for frames and units)."""

    t_ns: int
    T_WI: FloatArray
    v_W: FloatArray
    acc_bias: FloatArray
    gyro_bias: FloatArray
    theta: FloatArray

    @classmethod
    def from_prediction(
        cls, t_ns: int, nav: gtsam.NavState, bias: gtsam.imuBias.ConstantBias, theta: FloatArray
    ) -> KeyframeState:
        """State from a (predicted) navigation state and bias; ``theta`` is stored as given."""
        return cls(t_ns, nav.pose().matrix(), nav.velocity(), bias.accelerometer(), bias.gyroscope(), theta)

    @classmethod
    def from_values(cls, values: gtsam.Values, k: int, t_ns: int, theta_default: FloatArray) -> KeyframeState:
        """State of keyframe ``k`` read from smoother values; joint angles from ``theta_key(k)`` when
        the values hold it, else ``theta_default`` (a copy is stored either way)."""
        theta = values.atVector(theta_key(k)) if values.exists(theta_key(k)) else theta_default
        bias = values.atConstantBias(bias_key(k))
        return cls(
            t_ns,
            values.atPose3(pose_key(k)).matrix(),
            values.atVector(velocity_key(k)),
            bias.accelerometer(),
            bias.gyroscope(),
            np.asarray(theta, float).copy(),
        )

    def with_theta(self, theta: FloatArray) -> KeyframeState:
        """The same state with other joint angles."""
        return dataclasses.replace(self, theta=theta)


def result_from_states(
    states: dict[int, KeyframeState],
    mode: str,
    stats: dict[str, Any],
    theta_sigma: dict[int, FloatArray] | None = None,
) -> VioResult:
    """:class:`VioResult` of the keyframes in index order (``theta`` shaped (N, L), L may be 0); with
    ``theta_sigma`` (keyframe -> joint-angle 1-sigma, rad) also ``theta_sigma`` (N, L), NaN where missing."""
    keys = sorted(states)
    ordered = [states[k] for k in keys]
    sigma = None
    if theta_sigma is not None:
        L = ordered[0].theta.shape[0] if ordered else 0
        sigma = np.array([theta_sigma.get(k, np.full(L, np.nan)) for k in keys], float).reshape(len(keys), L)
    return VioResult(
        timestamps_ns=np.array([s.t_ns for s in ordered], dtype=np.int64),
        T_WI=np.array([s.T_WI for s in ordered]),
        v_W=np.array([s.v_W for s in ordered]),
        acc_bias=np.array([s.acc_bias for s in ordered]),
        gyro_bias=np.array([s.gyro_bias for s in ordered]),
        theta=np.array([s.theta for s in ordered]).reshape(len(ordered), -1),
        mode=mode,
        stats=dict(stats),
        theta_sigma=sigma,
    )
