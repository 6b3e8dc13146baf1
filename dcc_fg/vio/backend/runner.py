"""Run the smoother over a list of track frames (:func:`run_vio`) and time it (:func:`timing_stats`).

Times in ns (:data:`~.options.NS` per second); ``T_WI`` body/IMU -> W.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from dcc_fg.data.vio import ImuConfig, ImuSamples, TrackFrame
from dcc_fg.model import GimbalCalibration
from dcc_fg.vio.backend.landmarks import validate_frames
from dcc_fg.vio.backend.options import NS, InitialState, VioOptions, VioResult
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
) -> VioResult:
    """Run the smoother over time-ordered frames; ``initial`` (at the first frame) or standstill."""
    options = options or VioOptions()
    validate_frames(frames)
    t_start = time.perf_counter()
    sm = VioSmoother(imu, imu_config, calibration, options)
    if frames[0].timestamp_ns < imu.t_ns[0] or frames[-1].timestamp_ns > imu.t_ns[-1] + NS // 10:
        log.warning("camera frames extend beyond the IMU data; clipping to the IMU time span")
    frames = [f for f in frames if imu.t_ns[0] <= f.timestamp_ns <= imu.t_ns[-1]]
    if not frames:
        raise ValueError("no camera frame lies within the IMU time span")
    if initial is not None:
        frames = [f for f in frames if f.timestamp_ns >= initial.t_ns]
    sm.initialize(frames[0], initial)
    for i, f in enumerate(frames[1:], start=1):
        sm.add_frame(f)
        if progress is not None:
            progress(i, len(frames))
    res = sm.result()
    duration = (frames[-1].timestamp_ns - frames[0].timestamp_ns) / NS
    res.stats.update(timing_stats(time.perf_counter() - t_start, duration, len(frames)))
    return res


def timing_stats(elapsed_s: float, duration_s: float, frames: int) -> dict[str, float | int]:
    """Processing time, data duration (s), their ratio (the real-time factor) and the frame count."""
    return {
        "processing_time_s": elapsed_s,
        "data_duration_s": duration_s,
        "real_time_factor": elapsed_s / duration_s if duration_s > 0 else float("nan"),
        "frames": frames,
    }
