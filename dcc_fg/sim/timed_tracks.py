"""Feature tracks of unsynchronized cameras with time offsets, without rendering (tracks level).

:func:`simulate_timed_tracks` is :func:`dcc_fg.sim.trajectory.simulate_tracks` for the camera timing of
:class:`~dcc_fg.sim.timing.CameraTiming`: each camera has its own rate and phase, every image is
projected from the body pose and joint angles at its *true exposure time* (the analytic trajectory,
:func:`~dcc_fg.sim.trajectory.truth_at`), and carries its header stamp ``exposure - t_offset``
(convention ``t_imu = t_cam_stamp + t_offset``). Each static image is paired with the gimbal image
nearest in stamp (one to one, within half the slower camera's period) as ``dcc-fg vio`` pairs a bag;
a static image without a partner has no gimbal observations. The returned
:class:`~dcc_fg.data.vio.TrackFrame` carries the static stamp and the gimbal stamp.

Frames: ``W`` world, ``I`` body, ``s`` static camera, ``d`` gimbal camera; times in ns from the start
of the flight; observations in normalized coordinates with N(0, pixel_sigma) pixel noise.
"""

from __future__ import annotations

import numpy as np

from dcc_fg.data.vio import TrackFrame
from dcc_fg.io.pairing import pair_timestamps
from dcc_fg.model import GimbalCalibration
from dcc_fg.sim.timing import CameraTiming
from dcc_fg.sim.trajectory import FlightTruth, FloatArray, TrackIds, noisy_normalized, truth_at, visible_points
from factors import chain

NS = 1_000_000_000


def simulate_timed_tracks(
    truth: FlightTruth,
    landmarks_W: FloatArray,
    calibration: GimbalCalibration,
    T_sI: FloatArray,
    timing: CameraTiming,
    pixel_sigma: float = 0.5,
    seed: int = 1,
    max_range: float = 40.0,
    margin_px: float = 5.0,
) -> list[TrackFrame]:
    """Noisy normalized observations of ``landmarks_W`` (N, 3) by both cameras at their own times
    (module docstring), one :class:`TrackFrame` per static image, in stamp order."""
    cam_s, cam_d = calibration.static_camera, calibration.dynamic_camera
    if cam_s is None or cam_d is None:
        raise ValueError("the calibration must carry both camera models")
    rng = np.random.default_rng(seed)
    t0, t1 = int(truth.t_ns[0]), int(truth.t_ns[-1])
    static, gimbal = timing.streams(t1 - t0, rng)
    periods = [NS / r for r in timing.rates]
    pairing = pair_timestamps(static.stamp_ns, gimbal.stamp_ns, int(0.5 * max(periods)))
    partner = dict(pairing.pairs)
    T_WI_s, _ = truth_at(truth, static.exposure_ns + t0)
    T_WI_d, theta_d = truth_at(truth, gimbal.exposure_ns + t0)
    P_h = np.hstack([landmarks_W, np.ones((landmarks_W.shape[0], 1))])
    tracks = TrackIds(landmarks_W.shape[0])
    frames = []
    for i in np.argsort(static.stamp_ns, kind="stable"):
        p_s = P_h @ (T_sI @ chain.inv_se3(T_WI_s[i]))[:3].T
        vis_s, _ = visible_points(cam_s, p_s, max_range, margin_px)
        j = partner.get(int(i))
        vis_d = np.zeros_like(vis_s)
        p_d = np.zeros_like(p_s)
        if j is not None:
            p_d = P_h @ (calibration.T_ds(theta_d[j]) @ T_sI @ chain.inv_se3(T_WI_d[j]))[:3].T
            vis_d, _ = visible_points(cam_d, p_d, max_range, margin_px)
        track_id = tracks.update(vis_s | vis_d)
        xy_s = noisy_normalized(p_s, vis_s, cam_s, pixel_sigma, rng)
        xy_d = noisy_normalized(p_d, vis_d, cam_d, pixel_sigma, rng)
        frames.append(
            TrackFrame(
                t0 + int(static.stamp_ns[i]),
                track_id[vis_s].copy(),
                xy_s,
                track_id[vis_d].copy(),
                xy_d,
                None if j is None else t0 + int(gimbal.stamp_ns[j]),
            )
        )
    return frames
