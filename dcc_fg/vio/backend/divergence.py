"""Divergence of the smoother's estimate: physical limits a keyframe state must respect.

A keyframe state (:class:`~.state.KeyframeState`: ``T_WI`` body/IMU -> world W, ``v_W`` m/s in W,
biases m/s^2 and rad/s) has diverged when

* any number is not finite;
* its speed exceeds ``max_speed`` (m/s, :class:`~.options.VioOptions`: the platform's top speed);
* its position moved from the previous keyframe's by more than the body can move in the elapsed
  time ``dt`` with the previous speed and the largest acceleration the IMU can sense
  (``|p - p_prev| > |v_prev| dt + a_max dt^2 / 2``, ``a_max`` = accelerometer range + gravity),
  or by more than ``max_speed * dt``;
* the 1-sigma of its velocity (from the smoother's marginal covariance, when available) exceeds
  ``max_velocity_sigma`` (m/s): nothing constrains the velocity any more (vision lost, IMU only).

:func:`divergence` returns the first violated limit in words (None for a healthy state); it is pure
and cheap, so the smoother checks every keyframe.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dcc_fg.data.vio import ImuConfig
from dcc_fg.vio.backend.options import NS, VioOptions
from dcc_fg.vio.backend.state import KeyframeState


@dataclass(frozen=True)
class DivergenceLimits:
    """``max_speed`` m/s, ``max_acceleration`` m/s^2, ``max_velocity_sigma`` m/s."""

    max_speed: float
    max_acceleration: float
    max_velocity_sigma: float

    @classmethod
    def from_options(cls, options: VioOptions, imu: ImuConfig) -> DivergenceLimits:
        """Speed and velocity-sigma limits from the options; acceleration from the IMU's range
        (specific force range per axis, times sqrt(3) for the norm, plus gravity)."""
        return cls(options.max_speed, float(np.sqrt(3.0) * imu.acc_range + imu.gravity), options.max_velocity_sigma)


def state_is_finite(s: KeyframeState) -> bool:
    """True if every number of the state is finite."""
    arrays = (s.T_WI, s.v_W, s.acc_bias, s.gyro_bias, s.theta)
    return all(bool(np.all(np.isfinite(np.asarray(a, float)))) for a in arrays)


def max_jump(previous: KeyframeState, dt_s: float, limits: DivergenceLimits) -> float:
    """Largest distance (m) the body can move in ``dt_s`` seconds after ``previous``."""
    v = min(float(np.linalg.norm(previous.v_W)), limits.max_speed)
    return min(v * dt_s + 0.5 * limits.max_acceleration * dt_s**2, limits.max_speed * dt_s)


def divergence(
    previous: KeyframeState | None,
    current: KeyframeState,
    limits: DivergenceLimits,
    velocity_sigma: float | None = None,
) -> str | None:
    """The first physical limit ``current`` violates (module docstring), or None.

    ``previous`` is the preceding keyframe of the same trajectory segment (None for a segment's
    first keyframe); ``velocity_sigma`` the 1-sigma of the current velocity (m/s) or None.
    """
    if not state_is_finite(current):
        return "non-finite state (NaN/inf in pose, velocity, biases or joint angles)"
    speed = float(np.linalg.norm(current.v_W))
    if speed > limits.max_speed:
        return f"speed {speed:.3g} m/s exceeds max_speed {limits.max_speed:g} m/s"
    if previous is not None and state_is_finite(previous):
        dt = (current.t_ns - previous.t_ns) / NS
        jump = float(np.linalg.norm(current.T_WI[:3, 3] - previous.T_WI[:3, 3]))
        bound = max_jump(previous, dt, limits)
        if jump > bound:
            return (
                f"position jumped {jump:.3g} m in {dt:.3f} s (at most {bound:.3g} m at "
                f"{np.linalg.norm(previous.v_W):.3g} m/s with the IMU's {limits.max_acceleration:.0f} m/s^2 "
                f"and max_speed {limits.max_speed:g} m/s)"
            )
    if velocity_sigma is not None and not velocity_sigma <= limits.max_velocity_sigma:
        return (
            f"velocity 1-sigma {velocity_sigma:.3g} m/s exceeds max_velocity_sigma {limits.max_velocity_sigma:g} m/s "
            "(covariance blow-up: nothing constrains the velocity)"
        )
    return None
