"""Keyframe fixed-lag smoother of the gimbal-aware VIO (paper section IV-C), split by job.

Input: :class:`~dcc_fg.data.vio.TrackFrame` lists (undistorted normalized coordinates, one landmark
id space across both cameras) and :class:`~dcc_fg.data.vio.ImuSamples`; no images.

State per keyframe k (:mod:`.keys`, gtsam ``symbol_shorthand``): ``x(k)`` Pose3 ``T_WI``, ``v(k)``
velocity in W (m/s), ``b(k)`` ``imuBias.ConstantBias`` (accelerometer m/s^2, gyroscope rad/s) and,
in ``dcc`` mode, ``t(k)`` the joint angles (Vector L, rad). Landmarks ``l(n)`` are Point3 in W. W has
gravity along -z. The smoother keeps each keyframe's latest estimate as a :class:`KeyframeState`
(:mod:`.state`).

Factors:

* ``CombinedImuFactor`` between consecutive keyframes (:mod:`.imu`: ``PreintegratedCombinedMeasurements``
  with the Kalibr noise densities of :class:`~dcc_fg.data.vio.ImuConfig`, bias random walk included);
* static camera: gtsam's ``GenericProjectionFactorCal3_S2`` on normalized coordinates with
  ``body_P_sensor = T_Is`` and a Huber loss (:mod:`.cameras`);
* gimbal camera: the paper's eq. 14 (:func:`factors.vio.gimbal_reprojection_factor`, keys pose,
  landmark, joint angles; Huber loss) in ``dcc`` mode, which estimates the joint angles; ``scc``
  holds them at the given fixed angles (gimbal locked: a projection factor with the fixed
  extrinsic ``T_dI``), ``mono`` ignores the gimbal camera;
* joint-angle random walk ``theta_k - theta_{k-1} ~ N(0, q^2 dt)`` between keyframes (``dcc``);
* priors on the first keyframe (pose, velocity, bias, joint angles; :mod:`.window`);
* zero-velocity factors while the static camera's tracks stand still (:mod:`.zupt`).

Landmarks (:mod:`.landmarks`) are triangulated (linear DLT over all buffered observations, both
cameras) once a track has ``min_track_keyframes`` keyframes, enough parallax, positive depths and
small reprojection errors; the smoother (gtsam ``IncrementalFixedLagSmoother`` or
``BatchFixedLagSmoother``, :mod:`.window`) then marginalizes every variable whose window time is more
than ``lag`` seconds old, and restarts the window from the IMU prediction after a failed update. A
keyframe's window time is its own; a persistent landmark's (by default every one) is its newest
observation; a landmark that is not persistent (``persistent_landmarks``) gets the time of the oldest
keyframe that saw it when it was made, so it leaves with that keyframe and its observations become a prior
on keyframe states only (a track that goes on is triangulated afresh; :meth:`.landmarks.LandmarkMap.stamp_ns`).

Gimbal camera outliers use the two-stage scheme the paper proposes as future work (:mod:`.joints`):
the joint angles of a new keyframe are first fitted (Huber, no rejection) to the gimbal observations
of known landmarks with the IMU-predicted pose, then observations are gated with the updated extrinsics.

Initialization: from standstill (gravity from the mean accelerometer reading, yaw 0, gyroscope bias
from the mean rate) or from a given :class:`InitialState` (e.g. ground truth in tests).

Recovery (:mod:`.divergence`, :class:`VioSmoother`): every keyframe is checked against physical
limits (finite, ``max_speed``, position jump within the IMU's acceleration range, velocity
covariance); an IMU gap (sample spacing beyond ``imu_gap_periods`` periods), a divergence or a
failed update starts a new *trajectory segment* (fresh window and landmarks, anchored from
standstill or the last healthy state). ``result.stats`` lists the ``segments`` (start/end stamps,
reason), ``segment_count`` and the ``divergences``; poses of different segments are not in one
frame (evaluate per segment). :func:`dcc_fg.vio.health.vio_health` judges the result.

Modules: :mod:`.options` (settings, initial state, result), :mod:`.keys`, :mod:`.state`, :mod:`.divergence`,
:mod:`.imu`, :mod:`.cameras`, :mod:`.landmarks`, :mod:`.joints`, :mod:`.zupt`, :mod:`.window`,
:mod:`.smoother` (:class:`VioSmoother`, the orchestration), :mod:`.runner` (:func:`run_vio`),
:mod:`.outputs` (:func:`write_vio_outputs`). Frames and conventions: ``docs/architecture.md``.
"""

from dcc_fg.vio.backend.imu import integrate_imu, preintegration_params, standstill_state, validate_imu
from dcc_fg.vio.backend.landmarks import triangulate, validate_frames
from dcc_fg.vio.backend.options import MODES, NS, InitialState, VioOptions, VioResult
from dcc_fg.vio.backend.outputs import write_vio_outputs
from dcc_fg.vio.backend.runner import run_vio, timing_stats
from dcc_fg.vio.backend.smoother import VioSmoother
from dcc_fg.vio.backend.state import KeyframeState

__all__ = [
    "MODES",
    "NS",
    "InitialState",
    "KeyframeState",
    "VioOptions",
    "VioResult",
    "VioSmoother",
    "integrate_imu",
    "preintegration_params",
    "run_vio",
    "standstill_state",
    "timing_stats",
    "triangulate",
    "validate_frames",
    "validate_imu",
    "write_vio_outputs",
]
