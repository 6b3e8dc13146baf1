"""Unsynchronized camera streams of the simulators: rates, phase, time offsets and stamp jitter.

Both simulators (``dcc-fg simulate flight`` and ``dcc-fg simulate calibration --motion
continuous``) take the same four flags, held in :class:`CameraTiming`:

* ``--rates R_STATIC,R_GIMBAL`` (Hz): each camera's frame rate;
* ``--phase SECONDS``: the start of the gimbal camera's stream relative to the static one's (true
  exposure times; any finite value, the stream is the grid ``phase + k / R_GIMBAL``);
* ``--time-offsets T_S,T_D`` (s): a constant offset of each camera's header stamps from its true
  exposure time on the reference clock (the IMU clock in a flight, the simulation clock in a
  calibration recording), with the OpenVINS / Kalibr convention

      ``t_imu = t_cam_stamp + t_offset``

  (OpenVINS' ``calib_camimu_dt``, Kalibr's ``timeshift_cam_imu``): an image exposed at true time
  ``t`` is stamped ``t - t_offset``, so a positive offset means the stamps are *early*;
* ``--stamp-jitter SECONDS``: the standard deviation of zero-mean Gaussian noise added to every
  header stamp (independently per image; the true exposure times stay on the grid).

True exposure times of camera c (0 static, 1 gimbal) are ``phase_c + k / rate_c`` (``phase_0 =
0``, ``phase_1 = --phase``) in nanoseconds rounded to integers; stamps are ``exposure -
round(offset_c * 1e9) + round(jitter * 1e9)`` (jitter drawn per image). Only frames whose true
exposure time and stamp both lie inside the recording ``[0, t_end]`` are kept, so every image
stamp is covered by the IMU of a flight.

Pure numpy; frames and units: seconds and int64 nanoseconds relative to the start of the
simulation.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

IntArray = NDArray[np.int64]
NS = 1_000_000_000
#: The time-offset convention, written with the truth.
CONVENTION = "t_imu = t_cam_stamp + t_offset (OpenVINS calib_camimu_dt, Kalibr timeshift_cam_imu)"
#: Largest accepted |time offset|, seconds.
MAX_OFFSET_S = 0.5
CAMERA_NAMES = ("static", "dynamic")

log = logging.getLogger("dcc_fg.sim.timing")


@dataclass(frozen=True)
class FrameTimes:
    """The frames of one camera: ``camera`` 0 (static) or 1 (gimbal), true exposure times
    ``exposure_ns`` (F,) and header stamps ``stamp_ns`` (F,), both int64 ns from the start of the
    simulation, in exposure order."""

    camera: int
    exposure_ns: IntArray
    stamp_ns: IntArray

    def __len__(self) -> int:
        return int(self.exposure_ns.size)


@dataclass(frozen=True)
class CameraTiming:
    """Rates (Hz), phase (s), time offsets (s) and stamp jitter (s) of the two cameras (module docstring).

    The default is today's synchronized recording: both cameras at 20 Hz with identical stamps.
    """

    rates: tuple[float, float] = (20.0, 20.0)
    phase: float = 0.0
    time_offsets: tuple[float, float] = (0.0, 0.0)
    stamp_jitter: float = 0.0

    def __post_init__(self) -> None:
        check_rates(self.rates)
        check_phase(self.phase)
        check_offsets(self.time_offsets)
        check_jitter(self.stamp_jitter)

    @property
    def is_default(self) -> bool:
        """True for the synchronized default (both 20 Hz, no phase, offsets or jitter)."""
        return self == CameraTiming()

    def streams(self, t_end_ns: int, rng: np.random.Generator | None = None) -> tuple[FrameTimes, FrameTimes]:
        """The static and the gimbal camera's frames within ``[0, t_end_ns]`` (module docstring).

        ``rng`` draws the stamp jitter (needed when ``stamp_jitter > 0``); one warning per camera
        whose jittered stamps do not increase strictly.
        """
        if self.stamp_jitter > 0 and rng is None:
            raise ValueError("stamp jitter needs a random generator")
        out = []
        for c in (0, 1):
            rate = self.rates[c]
            phase = 0.0 if c == 0 else self.phase
            k0 = math.ceil(-phase * rate - 1e-9)
            k1 = math.floor((t_end_ns / NS - phase) * rate + 1e-9)
            k = np.arange(k0, k1 + 1, dtype=np.float64)
            exposure = np.round(phase * NS + k * (NS / rate)).astype(np.int64)
            stamp = exposure - int(round(self.time_offsets[c] * NS))
            if self.stamp_jitter > 0:
                assert rng is not None
                stamp = stamp + np.round(rng.normal(0.0, self.stamp_jitter * NS, size=stamp.size)).astype(np.int64)
            keep = (exposure >= 0) & (exposure <= t_end_ns) & (stamp >= 0) & (stamp <= t_end_ns)
            s = FrameTimes(c, exposure[keep], stamp[keep])
            back = int(np.count_nonzero(np.diff(s.stamp_ns) <= 0))
            if back:
                log.warning(
                    "--stamp-jitter %g s: %d of the %s camera's %d header stamps do not increase (jitter comparable "
                    "to the frame period 1/%g s); written as drawn (bag order follows the true exposure times)",
                    self.stamp_jitter, back, CAMERA_NAMES[c], len(s), rate,
                )  # fmt: skip
            out.append(s)
        return out[0], out[1]

    def to_dict(self) -> dict[str, object]:
        """The ``timing`` record written with the truth (seconds, Hz)."""
        return {
            "convention": CONVENTION,
            "rates_hz": {"static": float(self.rates[0]), "dynamic": float(self.rates[1])},
            "phase_s": float(self.phase),
            "time_offsets_s": {"static": float(self.time_offsets[0]), "dynamic": float(self.time_offsets[1])},
            "stamp_jitter_s": float(self.stamp_jitter),
        }


def check_rates(rates: tuple[float, float]) -> None:
    if len(rates) != 2 or not all(math.isfinite(r) and r > 0 for r in rates):
        raise ValueError(f"--rates must be two finite rates > 0 Hz (static,gimbal), got {rates}")


def check_phase(phase: float) -> None:
    if not math.isfinite(phase):
        raise ValueError(f"--phase must be a finite number of seconds, got {phase}")


def check_offsets(offsets: tuple[float, float]) -> None:
    if len(offsets) != 2 or not all(math.isfinite(t) and abs(t) < MAX_OFFSET_S for t in offsets):
        raise ValueError(
            f"--time-offsets must be two finite offsets of less than {MAX_OFFSET_S} s in magnitude (static,gimbal), "
            f"got {offsets}"
        )


def check_jitter(jitter: float) -> None:
    if not (math.isfinite(jitter) and jitter >= 0):
        raise ValueError(f"--stamp-jitter must be a finite standard deviation >= 0 s, got {jitter}")


def parse_pair(text: str, flag: str) -> tuple[float, float]:
    """``"A,B"`` as two floats (ValueError naming ``flag`` otherwise)."""
    parts = text.split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        a, b = float(parts[0]), float(parts[1])
    except ValueError:
        raise ValueError(f"{flag} expects two comma-separated numbers (static,gimbal), got {text!r}") from None
    return a, b
