"""The fixed-lag window: gtsam's fixed-lag smoother, its anchor priors and the restart after a failure.

Every variable carries the time (ns) of its newest keyframe; gtsam
(``IncrementalFixedLagSmoother`` or ``BatchFixedLagSmoother``) marginalizes the variables older
than ``lag`` seconds at each update. The first keyframe is anchored by priors on pose, velocity,
biases (and joint angles); after a failed update (indeterminant system etc.) a fresh window is
anchored the same way, with moderate priors, at the newest keyframe's predicted state.
Poses ``T_WI`` body -> W; sigmas in rad, m, m/s, m/s^2, rad/s.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

from dcc_fg.vio.backend.keys import bias_key, pose_key, theta_key, velocity_key
from dcc_fg.vio.backend.options import NS, FloatArray, VioOptions


def new_fixed_lag_smoother(options: VioOptions) -> Any:
    """gtsam's incremental (ISAM2, relinearizing every update) or batch fixed-lag smoother."""
    if options.smoother == "incremental":
        p = gtsam.ISAM2Params()
        p.setRelinearizeThreshold(options.relinearize_threshold)
        p.relinearizeSkip = 1
        return gtsam.IncrementalFixedLagSmoother(options.window_s, p)
    return gtsam.BatchFixedLagSmoother(options.window_s)


def key_timestamps(stamps: dict[int, int]) -> gtsam.FixedLagSmootherKeyTimestampMap:
    """gtsam's key -> time (s) map from key -> time (ns)."""
    ts = gtsam.FixedLagSmootherKeyTimestampMap()
    for key, t in stamps.items():
        ts.insert((key, t / NS))
    return ts


def window_start_ns(now_ns: int, previous_keyframe_ns: int | None, lag: float) -> int:
    """Oldest keyframe time that survives the update at ``now_ns`` (not marginalized): the lag,
    shortened by the interval since the previous keyframe."""
    dt_kf = now_ns - previous_keyframe_ns if previous_keyframe_ns is not None else 0
    return now_ns - int(lag * NS) + dt_kf


@dataclass(frozen=True)
class AnchorSigmas:
    """Standard deviations of the anchor priors (rad, m, m/s, m/s^2, rad/s, rad)."""

    rotation: float
    position: float
    velocity: float
    acc_bias: float
    gyro_bias: float
    theta: float

    @classmethod
    def first_keyframe(cls, o: VioOptions) -> AnchorSigmas:
        """The priors on the first keyframe."""
        return cls(
            o.prior_rotation_sigma,
            o.prior_position_sigma,
            o.prior_velocity_sigma,
            o.prior_acc_bias_sigma,
            o.prior_gyro_bias_sigma,
            o.theta_prior_sigma,
        )

    @classmethod
    def motion_start(cls, o: VioOptions, gravity_sigma: float, velocity_sigma: float) -> AnchorSigmas:
        """The priors on a first keyframe from the visual-inertial alignment in motion: rotation and
        velocity at twice the alignment's 1-sigma (rad, m/s; its gravity direction and velocity), at
        least the first keyframe's usual priors."""
        return cls(
            max(o.prior_rotation_sigma, 2.0 * gravity_sigma),
            o.prior_position_sigma,
            max(o.prior_velocity_sigma, 2.0 * velocity_sigma),
            o.prior_acc_bias_sigma,
            o.prior_gyro_bias_sigma,
            o.theta_prior_sigma,
        )

    @classmethod
    def recovery(cls, o: VioOptions) -> AnchorSigmas:
        """The moderate priors of a restarted window."""
        return cls(
            o.recovery_rotation_sigma,
            o.recovery_position_sigma,
            10 * o.prior_velocity_sigma,
            o.prior_acc_bias_sigma,
            o.prior_gyro_bias_sigma,
            o.theta_prior_sigma,
        )


def anchor_factors(
    k: int,
    t_ns: int,
    pose: gtsam.Pose3,
    velocity: FloatArray,
    bias: gtsam.imuBias.ConstantBias,
    theta: FloatArray | None,
    sigmas: AnchorSigmas,
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, dict[int, int]]:
    """Priors on keyframe ``k``'s pose, velocity, bias (and joint angles unless ``theta`` is None),
    the values they start from and the keys' times."""
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    s = sigmas
    pose_noise = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, s.rotation), np.full(3, s.position)])
    graph.add(gtsam.PriorFactorPose3(pose_key(k), pose, pose_noise))
    graph.add(gtsam.PriorFactorVector(velocity_key(k), velocity, gtsam.noiseModel.Isotropic.Sigma(3, s.velocity)))
    bias_noise = gtsam.noiseModel.Diagonal.Sigmas(np.r_[np.full(3, s.acc_bias), np.full(3, s.gyro_bias)])
    graph.add(gtsam.PriorFactorConstantBias(bias_key(k), bias, bias_noise))
    values.insert(pose_key(k), pose)
    values.insert(velocity_key(k), velocity)
    values.insert(bias_key(k), bias)
    stamps = {pose_key(k): t_ns, velocity_key(k): t_ns, bias_key(k): t_ns}
    if theta is not None:
        n = theta.shape[0]
        graph.add(gtsam.PriorFactorVector(theta_key(k), theta, gtsam.noiseModel.Isotropic.Sigma(n, s.theta)))
        values.insert(theta_key(k), theta)
        stamps[theta_key(k)] = t_ns
    return graph, values, stamps


class FixedLagWindow:
    """The gtsam fixed-lag smoother of a run, replaced by a fresh one on :meth:`restart`; options not yet
    resolved (:meth:`VioOptions.resolved`) are resolved as for unsynchronized cameras, as the smoother does."""

    def __init__(self, options: VioOptions) -> None:
        self.opt = options if options.is_resolved else options.resolved(synchronized=False)
        self.smoother = new_fixed_lag_smoother(self.opt)

    def update(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        stamps: dict[int, int],
        remove: list[int] | None = None,
    ) -> str | None:
        """Add new factors and values (keys timed by ``stamps``, ns), remove the factors in slots ``remove``
        and run ``extra_iterations`` more; returns None, or the first line of gtsam's error if the update
        failed."""
        try:
            self.smoother.update(graph, values, key_timestamps(stamps), remove or [])
            for _ in range(self.opt.extra_iterations):
                self.smoother.update()
        except RuntimeError as err:  # indeterminant system etc.: the first sentence (it names the variable)
            return " ".join(str(err).strip().split("\n\n")[0].split())
        return None

    def restart(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, stamps: dict[int, int]) -> None:
        """A fresh smoother started with ``graph`` and ``values`` (errors propagate)."""
        self.smoother = new_fixed_lag_smoother(self.opt)
        self.smoother.update(graph, values, key_timestamps(stamps))

    def new_factor_slots(self) -> list[int]:
        """The smoother slots of the factors the last update added, in the order they were given."""
        return list(self.smoother.getISAM2Result().getNewFactorsIndices())

    def estimate(self) -> gtsam.Values:
        """The current estimate of every variable in the window."""
        return self.smoother.calculateEstimate()
