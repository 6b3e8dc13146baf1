"""Continuous motion of a calibration recording: the board and the gimbal keep moving while recording.

``dcc-fg simulate calibration --motion continuous`` records the way a person holding the rig would:
the target pose relative to the static camera ``T_st(t)`` and the joint angles ``theta(t)`` move
smoothly through the scene's snapshots (the waypoints: board poses visible in both cameras at
their joint angles, :mod:`dcc_fg.sim.calibration_scene`), one segment per consecutive pair.

Per segment k -> k+1 of duration ``T_k`` a minimum-jerk profile ``s(u) = 10u^3 - 15u^4 + 6u^5``
(``u = (t - t_k) / T_k``; zero velocity and acceleration at the waypoints, peak rate 1.875x the
mean) moves

* the joint angles linearly in s: ``theta = theta_k + s (theta_{k+1} - theta_k)``;
* the board's rotation along the geodesic ``R_st = R_k exp(s log(R_k^T R_{k+1}))`` and its centre
  (the centroid of the target's corners) along the straight line between the waypoints.

``T_k`` is the shortest duration (at least ``min_segment_s``) at which no peak rate exceeds its
limit: the board's angular rate ``max_target_rate`` (default 30 deg/s), its centre's speed
``max_target_speed`` (0.4 m/s) and every joint's rate ``max_joint_rate`` (20 deg/s). With the pinned
81-snapshot scene (a ~120 s recording) a 15 ms timing error then moves the gimbal camera's corners by
up to 3.3 px (90th percentile over the recording 1.8 px, median 0.8 px: the motion slows to rest at
every waypoint). Frames: ``s`` static camera, ``t`` target,
``T_ab`` maps points from b to a; times in seconds from the start of the recording, angles in rad.
Intermediate poses are not checked for visibility (a board partly out of view at some frames is
part of a hand-held recording); :func:`corners_visible` says which images see every corner.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from factors.camera import CameraModel

FloatArray = NDArray[np.float64]
DEG = np.pi / 180.0


@dataclass(frozen=True)
class MotionLimits:
    """Peak rates of a continuous recording: board rad/s and m/s (its centre), joints rad/s."""

    max_target_rate: float = 30.0 * DEG
    max_target_speed: float = 0.4
    max_joint_rate: float = 20.0 * DEG
    min_segment_s: float = 0.5

    def to_dict(self) -> dict[str, float]:
        return {
            "max_target_rate_deg_s": float(np.rad2deg(self.max_target_rate)),
            "max_target_speed_m_s": float(self.max_target_speed),
            "max_joint_rate_deg_s": float(np.rad2deg(self.max_joint_rate)),
            "min_segment_s": float(self.min_segment_s),
        }


PEAK = 1.875  # peak of ds/du of the minimum-jerk profile


def _min_jerk(u: FloatArray) -> FloatArray:
    return u * u * u * (10.0 - 15.0 * u + 6.0 * u * u)


class ContinuousMotion:
    """``T_st(t)`` and ``theta(t)`` through the waypoints (module docstring).

    Args:
        T_st: (K, 4, 4) waypoint target poses in the static camera, K >= 2.
        theta: (K, L) waypoint joint angles, rad.
        centre_t: (3,) the board point whose path is straight (target frame, m).
        limits: the peak rates.
    """

    def __init__(
        self, T_st: FloatArray, theta: FloatArray, centre_t: FloatArray, limits: MotionLimits | None = None
    ) -> None:
        self.limits = limits or MotionLimits()
        self.T_st = np.asarray(T_st, dtype=float)
        K = self.T_st.shape[0]
        if K < 2:
            raise ValueError("continuous motion needs at least 2 waypoints (--snapshots >= 2)")
        self.theta = np.asarray(theta, dtype=float).reshape(K, -1)
        self.centre_t = np.asarray(centre_t, dtype=float)
        self.R = self.T_st[:, :3, :3]
        self.c = np.einsum("kij,j->ki", self.R, self.centre_t) + self.T_st[:, :3, 3]
        self.rotvec = np.array(
            [Rotation.from_matrix(self.R[k].T @ self.R[k + 1]).as_rotvec() for k in range(K - 1)]
        ).reshape(K - 1, 3)
        lim = self.limits
        durations = []
        for k in range(K - 1):
            d_rot = float(np.linalg.norm(self.rotvec[k]))
            d_pos = float(np.linalg.norm(self.c[k + 1] - self.c[k]))
            d_joint = float(np.max(np.abs(self.theta[k + 1] - self.theta[k]), initial=0.0))
            need = PEAK * max(d_rot / lim.max_target_rate, d_pos / lim.max_target_speed, d_joint / lim.max_joint_rate)
            durations.append(max(lim.min_segment_s, need))
        self.durations = np.array(durations)
        self.t_waypoints = np.concatenate([[0.0], np.cumsum(self.durations)])

    @property
    def duration(self) -> float:
        """Length of the recording, s."""
        return float(self.t_waypoints[-1])

    def _segment(self, t: FloatArray) -> tuple[NDArray[np.int64], FloatArray]:
        t = np.clip(np.atleast_1d(np.asarray(t, dtype=float)), 0.0, self.duration)
        k = np.clip(np.searchsorted(self.t_waypoints, t, side="right") - 1, 0, len(self.durations) - 1)
        u = np.clip((t - self.t_waypoints[k]) / self.durations[k], 0.0, 1.0)
        return k, _min_jerk(u)

    def evaluate(self, t: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``T_st`` (N, 4, 4) and ``theta`` (N, L) at times ``t`` (N,) s (clamped to the recording)."""
        k, s = self._segment(t)
        theta = self.theta[k] + s[:, None] * (self.theta[k + 1] - self.theta[k])
        R = self.R[k] @ Rotation.from_rotvec(s[:, None] * self.rotvec[k]).as_matrix()
        c = self.c[k] + s[:, None] * (self.c[k + 1] - self.c[k])
        T = np.tile(np.eye(4), (k.size, 1, 1))
        T[:, :3, :3] = R
        T[:, :3, 3] = c - np.einsum("nij,j->ni", R, self.centre_t)
        return T, theta


def corners_visible(camera: CameraModel, T_ct: FloatArray, points_t: FloatArray, margin_px: float = 0.0) -> bool:
    """True if every target corner ``points_t`` (N, 3) is in front of ``camera`` at pose ``T_ct``
    (target -> camera) and projects inside its image with ``margin_px``."""
    p = points_t @ T_ct[:3, :3].T + T_ct[:3, 3]
    uv, _ = camera.project(p, jacobian=False)
    return bool(np.all(camera.in_front(p)) and np.all(camera.in_image(uv, margin_px)))
