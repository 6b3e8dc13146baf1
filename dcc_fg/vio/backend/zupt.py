"""Zero-velocity update: standstill seen by the static camera's tracks.

If the static-camera tracks did not move between two keyframes (median displacement of the common
tracks below ``zupt_threshold``, normalized units), the body is at rest: a zero-velocity prior
(m/s) and a no-motion factor between the two body poses ``T_WI`` (rad, m). Without parallax nothing
can be triangulated, so this is what keeps a resting body fixed.
"""

from __future__ import annotations

import gtsam
import numpy as np

from dcc_fg.vio.backend.keys import pose_key, velocity_key
from dcc_fg.vio.backend.options import FloatArray, VioOptions


def static_tracks_at_rest(previous: dict[int, FloatArray], current: dict[int, FloatArray], options: VioOptions) -> bool:
    """True if at least ``zupt_min_tracks`` track ids are in both (id -> normalized xy) maps and
    their median displacement is below ``zupt_threshold``."""
    common = [tid for tid in current if tid in previous]
    if len(common) < options.zupt_min_tracks:
        return False
    disp = float(np.median([np.linalg.norm(current[tid] - previous[tid]) for tid in common]))
    return disp < options.zupt_threshold


def zero_velocity_factors(k_prev: int, k: int, options: VioOptions) -> list[gtsam.NonlinearFactor]:
    """v(k) = 0 and x(k_prev) = x(k), with the ``zupt_*_sigma`` noises."""
    return [
        gtsam.PriorFactorVector(
            velocity_key(k), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, options.zupt_velocity_sigma)
        ),
        gtsam.BetweenFactorPose3(
            pose_key(k_prev), pose_key(k), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, options.zupt_pose_sigma)
        ),
    ]
