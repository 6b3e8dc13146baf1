"""Run the smoother over a list of track frames (:func:`run_vio`) and time it (:func:`timing_stats`).

Times in ns (:data:`~.options.NS` per second); ``T_WI`` body/IMU -> W.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Sequence

import numpy as np

from dcc_fg.data.cameras import RunCamera
from dcc_fg.data.vio import ImuConfig, ImuSamples, TrackFrame, check_imu_against_frames, imu_out_of_range
from dcc_fg.io.pairing import stamp_jitter_s
from dcc_fg.model import GimbalCalibration
from dcc_fg.vio.backend.landmarks import validate_frames
from dcc_fg.vio.backend.motion_init import StartSelector, start_sigmas
from dcc_fg.vio.backend.options import NS, SYNCHRONIZED_GAP_MS, InitialState, VioOptions, VioResult
from dcc_fg.vio.backend.smoother import VioSmoother

log = logging.getLogger(__name__)


def run_vio(
    frames: list[TrackFrame],
    imu: ImuSamples,
    imu_config: ImuConfig,
    calibration: GimbalCalibration | None = None,
    options: VioOptions | None = None,
    initial: InitialState | None = None,
    progress: Callable[[int, int], None] | None = None,
    cameras: Sequence[RunCamera] = (),
) -> VioResult:
    """Run the smoother over time-ordered frames; ``initial`` (at the first frame) or standstill.
    ``cameras``: the further cameras of an N-camera run (their tracks in :attr:`TrackFrame.extra`).

    IMU samples with non-finite values or beyond the sensor's range (``imu_config.acc_range``,
    ``gyro_range``) are dropped with a log line; an IMU rate too low for preintegration or frames
    far outside the IMU's time span are refused (:func:`~dcc_fg.data.vio.check_imu_against_frames`).
    """
    options = options or VioOptions()
    validate_frames(frames)
    if not options.is_resolved:
        options = options.resolved(frames_synchronized(frames, options.mode))
    if options.stamp_jitter is None:
        options = dataclasses.replace(options, stamp_jitter=frame_stamp_jitter(frames))
    t_start = time.perf_counter()
    imu, dropped = drop_implausible_imu(imu, imu_config)
    check_imu_against_frames(imu.t_ns, np.array([f.timestamp_ns for f in frames], dtype=np.int64), "imu")
    sm = VioSmoother(imu, imu_config, calibration, options, cameras)
    if frames[0].timestamp_ns < imu.t_ns[0] or frames[-1].timestamp_ns > imu.t_ns[-1] + NS // 10:
        log.warning("camera frames extend beyond the IMU data; clipping to the IMU time span")
    frames = [f for f in frames if imu.t_ns[0] <= f.timestamp_ns <= imu.t_ns[-1]]
    if not frames:
        raise ValueError("no camera frame lies within the IMU time span")
    if initial is not None:
        frames = [f for f in frames if f.timestamp_ns >= initial.t_ns]
    how, detail = ("given", "initial state given") if initial is not None else ("standstill", "")
    selector = StartSelector(imu, imu_config, options)
    if initial is None and options.initialization != "standstill":
        for f in frames:
            initial = selector.push(f)
            if initial is not None:
                how, detail = selector.how, selector.detail
                log.info("VIO start: %s (%s)", how, detail)
                break
    sm.initialize(frames[0], initial, start_sigmas(selector, options))  # None: standstill (or its refusal)
    sm.stats["start"] = {"how": how, "detail": detail}
    for i, f in enumerate(frames[1:], start=1):
        sm.add_frame(f)
        if progress is not None:
            progress(i, len(frames))
    res = sm.result()
    res.stats["imu_samples_dropped"] = dropped
    duration = (frames[-1].timestamp_ns - frames[0].timestamp_ns) / NS
    res.stats.update(timing_stats(time.perf_counter() - t_start, duration, len(frames)))
    return res


def frames_synchronized(frames: Sequence[TrackFrame], mode: str) -> bool:
    """Whether the frames' cameras expose together (:meth:`VioOptions.resolved`): no further camera, and
    no gimbal image (``mono``) or every gimbal image within :data:`~.options.SYNCHRONIZED_GAP_MS` of its
    static image's stamp."""
    if any(f.extra for f in frames):
        return False
    if mode == "mono":
        return True
    return all(f.dynamic_timestamp_ns is None or abs(f.dynamic_gap_s) * 1e3 <= SYNCHRONIZED_GAP_MS for f in frames)


def frame_stamp_jitter(frames: list[TrackFrame]) -> tuple[float, float]:
    """Stamp jitter (s, 1-sigma) of the static and the gimbal images of ``frames``
    (:func:`~dcc_fg.io.pairing.stamp_jitter_s`; the gimbal's 0 when its stamps are the static ones)."""
    static = [f.timestamp_ns for f in frames]
    gimbal = [f.dynamic_timestamp_ns for f in frames if f.dynamic_timestamp_ns is not None]
    return stamp_jitter_s(static), stamp_jitter_s(gimbal) if gimbal else stamp_jitter_s(static)


def drop_implausible_imu(imu: ImuSamples, config: ImuConfig) -> tuple[ImuSamples, int]:
    """``imu`` without the samples that are non-finite or beyond the sensor's range (m/s^2, rad/s
    per axis), and how many were dropped (logged)."""
    bad = imu_out_of_range(imu.acc, imu.gyro, config.acc_range, config.gyro_range)
    n = int(bad.sum())
    if n == 0:
        return imu, 0
    i = int(np.flatnonzero(bad)[0])
    log.warning(
        "dropped %d IMU samples that are non-finite or beyond the sensor's range (|acc| > %.1f m/s^2 or |gyro| > "
        "%.2f rad/s on an axis; first at t_ns %d)",
        n,
        config.acc_range,
        config.gyro_range,
        int(imu.t_ns[i]),
    )
    keep = ~bad
    return ImuSamples(imu.t_ns[keep], imu.acc[keep], imu.gyro[keep]), n


def timing_stats(elapsed_s: float, duration_s: float, frames: int) -> dict[str, float | int]:
    """Processing time, data duration (s), their ratio (the real-time factor) and the frame count."""
    return {
        "processing_time_s": elapsed_s,
        "data_duration_s": duration_s,
        "real_time_factor": elapsed_s / duration_s if duration_s > 0 else float("nan"),
        "frames": frames,
    }
