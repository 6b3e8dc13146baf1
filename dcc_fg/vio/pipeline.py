"""Images to trajectory: a recorded bag through the front end and the keyframe smoother (``dcc-fg vio``).

One pass over the bag (:class:`~dcc_fg.sources.vio_bag.VioBag` reads the IMU topic first, then decodes
the images one synchronized pair at a time): every frame pair goes through
:class:`~dcc_fg.vio.frontend.Frontend` (KLT tracks, static RANSAC, static <-> gimbal matching with the
current T_ds(theta) estimate) and the resulting :class:`~dcc_fg.data.vio.TrackFrame` into
:class:`~dcc_fg.vio.backend.VioSmoother`.

Gimbal-camera outliers (``dcc`` mode) follow the two stages the paper proposes as future work: the
smoother first estimates the joint angles of a keyframe with *all* gimbal tracks (Huber loss, no
rejection), then the gimbal tracks of that frame that are inconsistent with the epipolar geometry
implied by the *updated* extrinsics T_ds(theta_prev), T_ds(theta_cur) and the static camera's
motion seen by its own tracks are rejected (:meth:`Frontend.dynamic_outliers`): the front end stops
tracking them and the smoother's gate drops their observations from the current keyframe.

The front end runs inline or, optionally, in a child process ``keyframe_every + 1`` frames ahead of the
smoother, on the second core (:mod:`dcc_fg.vio.worker`; GTSAM holds the GIL, so a thread would
not overlap); it tracks each frame with the joint angles extrapolated linearly from the last two keyframe estimates
(the gimbal moves at up to ~60 deg/s: one 20 Hz frame is 3 deg), which only the static <-> gimbal
matching uses.

Frames: ``T_WI`` body (IMU) pose in the world W (gravity along -z), ``T_sI`` IMU -> static camera,
``T_ds(theta)`` static -> gimbal camera; times in ns; joint angles in rad.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dcc_fg.data.cameras import RunCamera, ignored_cameras, run_cameras
from dcc_fg.data.vio import ImuConfig, ImuSamples, TrackFrame
from dcc_fg.io.bags import ImuImageStamps
from dcc_fg.model import GimbalCalibration
from dcc_fg.sources.vio_bag import VioBag
from dcc_fg.util.allocator import reuse_large_buffers
from dcc_fg.vio.backend import NS, InitialState, VioOptions, VioResult, VioSmoother, timing_stats
from dcc_fg.vio.backend.motion_init import StartSelector, start_sigmas
from dcc_fg.vio.backend.options import SYNCHRONIZED_GAP_MS
from dcc_fg.vio.frontend import FrontendConfig, GimbalHint, gimbal_outliers
from dcc_fg.vio.joint_init import JointFit, fit_joint_angles
from dcc_fg.vio.worker import (
    FrontendWorker,
    Tracked,
    WorkerSpec,
    resolve_mode,
    spawn_frontend_process,
    stop_process,
)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BagTopics:
    """Topics of a VIO bag: ``sensor_msgs/Imu`` and the two image topics (``dynamic`` None: static only)."""

    imu: str = "/imu0"
    static: str = "/cam0/image_raw"
    dynamic: str | None = "/cam1/image_raw"


@dataclass(frozen=True)
class PipelineOptions:
    """Front-end side of a run: ``reject_dynamic`` enables the second stage of the gimbal outlier
    handling; ``tolerance_ns`` pairs static and gimbal images by exposure time (None: half the slower
    camera's frame period, :class:`~dcc_fg.sources.vio_bag.VioBag`); ``frontend`` overrides the front-end
    parameters (default: :meth:`FrontendConfig.for_resolution` of the static camera);
    ``fit_initial_joints`` (``dcc``) starts the joint angles from the first frame's static <-> gimbal
    matches (:func:`~dcc_fg.vio.joint_init.fit_joint_angles`) instead of taking the guess as is;
    ``worker`` runs the front end ``inline`` or in a child ``process`` ``keyframe_every + 1`` frames
    ahead of the smoother, on a second core (deterministic: the same tracks on every run,
    :mod:`dcc_fg.vio.worker`); ``auto`` (default) picks ``process`` when this process may use at least two
    cores (see :func:`~dcc_fg.vio.worker.resolve_mode`;
    ``benchmarks/bench_vio.py`` measures both on a given machine). ``start_s``: skip the first seconds of
    the bag (from its first IMU sample), e.g. to start in motion. ``cameras``: the further cameras of an
    N-camera cluster to use (names; None: every camera the mode can use, :func:`~dcc_fg.data.cameras.run_cameras`);
    ``max_further_gap_ms``: the largest median stamp gap (ms) between a further camera's images and
    cam0's that is accepted (:func:`check_further_sync`).
    """

    reject_dynamic: bool = True
    fit_initial_joints: bool = True
    worker: str = "auto"
    tolerance_ns: int | None = None
    frontend: FrontendConfig | None = None
    start_s: float = 0.0
    cameras: tuple[str, ...] | None = None
    max_further_gap_ms: float = 2.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.start_s) and self.start_s >= 0):
            raise ValueError(f"start_s must be a number of seconds >= 0, got {self.start_s!r}")
        if not (np.isfinite(self.max_further_gap_ms) and self.max_further_gap_ms >= 0):
            raise ValueError(f"max_further_gap_ms must be a number of ms >= 0, got {self.max_further_gap_ms!r}")


def check_bag_inputs(calibration: GimbalCalibration, options: VioOptions, topics: BagTopics) -> None:
    """ValueError unless the calibration has the camera models and the topics the mode needs (the further
    cameras' models are checked by :func:`~dcc_fg.data.cameras.run_cameras`)."""
    if calibration.static_camera is None:
        raise ValueError("the calibration has no static camera model (cam0 intrinsics are needed for VIO)")
    if options.mode == "mono":
        return
    if calibration.dynamic_camera is None:
        raise ValueError(f"mode '{options.mode}' needs the gimbal camera model (cam1 intrinsics)")
    if topics.dynamic is None:
        raise ValueError(f"mode '{options.mode}' needs the gimbal camera's image topic")


def time_offsets_ns(options: VioOptions) -> tuple[int, int]:
    """The start values of the time offsets ``(t_s, t_d)``, ns."""
    t = options.offsets
    return int(round(t[0] * NS)), int(round(t[1] * NS))


def check_time_offsets(vb: VioBag, options: VioOptions) -> None:
    """Refuse start values of the time offsets the exposure model cannot bridge (before any work).

    The smoother moves each image from its keyframe to its exposure with the keyframe's twist over
    ``|stamp gap + offset|`` (:mod:`dcc_fg.vio.backend.exposure`); beyond one frame period of the camera
    that first-order model no longer holds (and a wrong sign or unit, ms given as s, is the usual
    cause). Offsets beyond half a period are accepted with a warning: images are paired by exposure time.

    Raises:
        ValueError: naming the camera, its measured period and the offset.
    """
    names = ("static", "gimbal")
    topics = (vb.static_topic, vb.dynamic_topic)
    for c, (name, topic) in enumerate(zip(names, topics, strict=True)):
        if topic is None:
            continue
        period = vb.period_s(topic)
        if period is None:
            continue
        off = float(options.offsets[c])
        if abs(off) > period:
            raise ValueError(
                f"{vb.path}: topic {topic}: the start value of the {name} camera's time offset is {off * 1e3:g} ms, "
                f"more than one frame period ({period * 1e3:.1f} ms): the exposure model between keyframes does not "
                "hold that far. Check the sign (t_imu = t_cam_stamp + t_offset) and the unit (seconds), or shift "
                "the stamps of the topic by the known delay and start from 0"
            )
        if abs(off) > 0.5 * period:
            log.warning(
                "%s: topic %s: the start value of the %s camera's time offset (%g ms) is more than half a frame "
                "period (%.1f ms); images are paired by stamp + offset",
                vb.path,
                topic,
                name,
                off * 1e3,
                period * 1e3,
            )


def bag_synchronized(vb: VioBag, mode: str, cameras: tuple[RunCamera, ...]) -> bool:
    """Whether the bag's cameras expose together (:meth:`VioOptions.resolved`): no further camera, and no
    gimbal topic (``mono``) or every gimbal image paired with a static image within
    :data:`~dcc_fg.vio.backend.options.SYNCHRONIZED_GAP_MS`."""
    if cameras:
        return False
    if mode == "mono":
        return True
    stats = vb.pairing_statistics
    if stats is None:
        return False
    gap = stats.get("gap_max_ms")
    unpaired = int(stats.get("unpaired_dynamic") or 0)
    return not unpaired and (gap is None or float(gap) <= SYNCHRONIZED_GAP_MS)


def warn_persistence_on_unsynchronized(vb: VioBag, options: VioOptions, synchronized: bool) -> bool:
    """Warn (and return True) when landmarks do not all persist (``persistent_landmarks`` given as ``none``
    or ``gimbal``; ``auto`` picks ``all`` there) while the gimbal camera runs on its own clock
    (:func:`bag_synchronized` False): on the unsynchronized flight of
    ``benchmarks/bench_unsynchronized_vio.py`` (20 / 30 Hz, offsets 5 / 15 ms) ``persistent_landmarks='none'``
    with a 2.5 s window gave 1.19x the translation RMSE of ``all`` (0.032 % against 0.027 %; on the
    synchronized flight 0.79x) and 1.56x its own synchronized flight's, where the issue asks for at most
    1.2x (README, VIO throughput)."""
    if options.persistent_landmarks in ("all", "auto") or options.mode == "mono" or synchronized:
        return False
    stats = vb.pairing_statistics or {}
    gap = stats.get("gap_max_ms")
    log.warning(
        "%s: the gimbal camera is not synchronized with the static camera (%d gimbal images without a partner, "
        "largest pairing gap %s ms) and persistent_landmarks is '%s': on the benchmark's unsynchronized flight "
        "that gave 1.2x the translation error of 'all' (--persistent-landmarks all or auto)",
        vb.path,
        int(stats.get("unpaired_dynamic") or 0),
        "-" if gap is None else f"{float(gap):.1f}",
        options.persistent_landmarks,
    )
    return True


def check_further_sync(vb: VioBag, cameras: tuple[RunCamera, ...], max_gap_ms: float) -> None:
    """Refuse further cameras whose images are not taken with cam0's (before any work).

    A further camera's image is used as exposed at the static image's time (no time offset of its own:
    the cameras of a cluster are triggered together). Its median stamp gap to the static image it is
    paired with must be at most ``max_gap_ms``: a free-running camera's phase would put its observations
    at the wrong body pose (5 m/s and 10 ms: 5 cm) with nothing in the estimate to show it.

    Raises:
        ValueError: naming the bag, topic, camera and the measured gap, and what to do.
    """
    for c in cameras:
        stats = vb.extra_pairing_statistics.get(c.topic) or {}
        gap = stats.get("gap_median_ms")
        if gap is not None and float(gap) > max_gap_ms:
            raise ValueError(
                f"{vb.path}: topic {c.topic} ({c.name}): its images are {float(gap):.2f} ms (median) from cam0's, "
                f"more than {max_gap_ms:g} ms: N-camera VIO takes a further camera as triggered with cam0 (exposed at "
                f"cam0's stamp). Trigger the cameras together or correct the stamps, leave the camera out "
                f"(--cameras), or accept the gap with --max-further-gap (run.max_further_gap_ms)"
            )


def joint_angle_guess(options: VioOptions, initial: InitialState | None) -> FloatArray | None:
    """Joint angles (rad) to start from: the locked ones (scc), the initial state's, ``theta_initial``, or None."""
    if options.mode == "scc":
        return np.asarray(options.theta_fixed, float)
    if initial is not None and initial.theta.size:
        return np.asarray(initial.theta, float)
    if options.theta_initial is not None:
        return np.asarray(options.theta_initial, float)
    return None


class SmootherDriver:
    """Feeds the front end's frames to the smoother: starts it on the first frame (joint angles from
    that frame's static <-> gimbal pairs in ``dcc``), passes joint-angle measurements while the gimbal
    camera sees few landmarks, pushes each keyframe's joint angles to the front end and runs stage
    two of the gimbal outlier handling (module docstring). Times in ns, angles in rad."""

    def __init__(
        self,
        imu: ImuSamples,
        imu_config: ImuConfig,
        calibration: GimbalCalibration,
        options: VioOptions,
        pipeline: PipelineOptions,
        initial: InitialState | None,
        guess: FloatArray | None,
        worker: FrontendWorker,
        cameras: tuple[RunCamera, ...] = (),
    ) -> None:
        self.imu, self.imu_config, self.cal = imu, imu_config, calibration
        self.cameras = cameras
        self.options, self.pipeline, self.initial, self.worker = options, pipeline, initial, worker
        self.guess = guess
        self.theta0 = self.guess if self.guess is not None else np.zeros(calibration.n_joints)
        assert calibration.static_camera is not None
        # the outlier test of stage two runs here, on the worker's snapshots, with the worker's settings
        self.fe_config = pipeline.frontend or FrontendConfig.for_resolution(*calibration.static_camera.resolution)
        self.smoother: VioSmoother | None = None
        self.joint_fit: JointFit | None = None
        self.t_start_data = 0
        self.t_prev = 0
        self.kf_prev: tuple[int, FloatArray] | None = None  # last keyframe's time and joint angles (dcc)
        self.kf_prev_chains: dict[int, FloatArray] = {}  # further chains' angles at that keyframe (slot ->)
        self.further_rejected = 0  # tracks of further gimbal cameras stage two rejected
        self.rejected = np.zeros(0, np.int64)  # gimbal track ids stage two rejected after the last frame
        self.pending: list[Tracked] = []  # frames waiting for the start decision
        self.observer: Callable[[FrameEvent], None] | None = None
        self.selector = StartSelector(imu, imu_config, options)
        self.start: dict[str, str] = {"how": "standstill", "detail": ""}

    def feed(self, item: Tracked) -> list[tuple[Tracked, bool]]:
        """Process one tracked frame; returns the frames the smoother took in this call, each with
        whether it became a keyframe: none while the start is being decided (the frames wait), then
        the waiting ones and this one (:mod:`~dcc_fg.vio.backend.motion_init`). ``observer`` (if set)
        gets each frame's :class:`FrameEvent` right after the smoother took it."""
        if self.smoother is None:
            if not self.pending and self.options.mode == "dcc":
                self._first_frame_joints(item.frame)
            self.pending.append(item)
            state = None
            if self.initial is None and self.options.initialization != "standstill":
                state = self.selector.push(item.frame)
                if state is None:
                    return []
                self.start = {"how": self.selector.how, "detail": self.selector.detail}
                log.info("VIO start: %s (%s)", self.selector.how, self.selector.detail)
            return self._start_with(state)
        return [(item, self._take(item))]

    def finish(self) -> list[tuple[Tracked, bool]]:
        """At the end of the data: frames still waiting for the start decision start from standstill
        (which refuses a body that is not at rest)."""
        return self._start_with(None) if self.smoother is None and self.pending else []

    def _start_with(self, state: InitialState | None) -> list[tuple[Tracked, bool]]:
        first, rest = self.pending[0], self.pending[1:]
        self.pending = []
        self._start(first.frame, state)
        self.t_prev = first.frame.timestamp_ns
        self.rejected = np.zeros(0, np.int64)
        self._emit(first, True)
        return [(first, True)] + [(it, self._take(it)) for it in rest]

    def _emit(self, item: Tracked, keyframe: bool) -> None:
        if self.observer is not None:
            self.observer(frame_event(item, self.smoother, keyframe, self.rejected))

    def _take(self, item: Tracked) -> bool:
        """The smoother takes one frame; True if it became a keyframe."""
        assert self.smoother is not None
        frame = item.frame
        self.rejected = np.zeros(0, np.int64)
        measurement = _theta_measurement(self.smoother, self.cal, frame, self.kf_prev)
        keyframe = self.smoother.add_frame(frame, measurement)
        if keyframe and self.options.mode == "dcc":
            self._keyframe_added(item)
        self.t_prev = frame.timestamp_ns
        self._emit(item, keyframe)
        return keyframe

    def _first_frame_joints(self, frame: TrackFrame) -> None:
        """dcc: the joint angles at the first frame from its static <-> gimbal pairs."""
        self.joint_fit = _initial_joint_angles(self.cal, frame, self.guess, self.pipeline.fit_initial_joints)
        self.theta0 = self.joint_fit.theta
        self.options = dataclasses.replace(self.options, theta_initial=tuple(float(x) for x in self.theta0))

    def _start(self, frame: TrackFrame, state: InitialState | None) -> None:
        """Initialize the smoother at the first frame: from the given initial state, the start the
        selector chose (``state``), or standstill."""
        t = frame.timestamp_ns
        mono = self.options.mode == "mono"
        start = self.initial
        if start is not None:
            start = InitialState(t, start.T_WI, start.v_W, start.acc_bias, start.gyro_bias, self.theta0)
            self.start = {"how": "given", "detail": "initial state given"}
        elif state is not None:
            start = InitialState(t, state.T_WI, state.v_W, state.acc_bias, state.gyro_bias, np.zeros(0))
        cal = None if mono and not self.cameras else self.cal  # mono: the cameras' models only (residual check)
        self.smoother = VioSmoother(self.imu, self.imu_config, cal, self.options, self.cameras)
        self.smoother.initialize(frame, start, start_sigmas(self.selector, self.options))
        self.smoother.stats["start"] = self.start
        self.t_start_data = t
        if self.options.mode == "dcc":
            self.kf_prev = (t, self.smoother.theta.copy())
            self.worker.push_theta(t, self._all_theta())

    def _all_theta(self) -> FloatArray:
        """The newest joint angles of every chain the run follows, flat in slot order (primary first)."""
        assert self.smoother is not None
        chains = self.smoother.chains
        return np.concatenate([self.smoother.theta, *(chains.theta[ch.slot] for ch in chains.chains)])

    def _keyframe_added(self, item: Tracked) -> None:
        """dcc keyframe: push its joint angles to the front end; stage two: the joint angles were
        estimated with every gimbal track, reject with the updated extrinsics (previous frame:
        interpolated between the keyframes)."""
        assert self.kf_prev is not None and self.smoother is not None
        t = item.frame.timestamp_ns
        theta_k = self.smoother.theta.copy()
        self.worker.push_theta(t, self._all_theta())
        if item.snapshot is not None and not item.after_gap:
            t_k0, theta_k0 = self.kf_prev
            w = (self.t_prev - t_k0) / max(t - t_k0, 1)
            hint = GimbalHint(self.cal.T_ds(theta_k0 + w * (theta_k - theta_k0)), self.cal.T_ds(theta_k))
            assert self.cal.dynamic_camera is not None
            bad = gimbal_outliers(item.snapshot, hint, self.cal.dynamic_camera, self.fe_config)
            self.rejected = np.asarray(item.snapshot.ids[bad], np.int64)
            self.worker.drop(self.rejected)
            self._further_stage_two(item, w, theta_k0, theta_k)
        self.kf_prev = (t, theta_k)
        self.kf_prev_chains = {
            ch.slot: self.smoother.chains.theta[ch.slot].copy() for ch in self.smoother.chains.chains
        }

    def _further_stage_two(self, item: Tracked, w: float, theta_k0: FloatArray, theta_k: FloatArray) -> None:
        """Stage two for the further cameras on a gimbal: each one's tracks against the epipolar geometry of
        its own ``T_cs`` at the previous frame's (interpolated) and this keyframe's angles of its chain."""
        assert self.smoother is not None
        cams = {c.index: c for c in self.cameras}
        for index, snap in item.further_snapshots:
            c = cams[index]
            if c.slot == 0:
                th0, th1 = theta_k0, theta_k
            else:
                th1 = self.smoother.chains.theta[c.slot]
                th0 = self.kf_prev_chains.get(c.slot, th1)
            hint = GimbalHint(c.T_cs_at(th0 + w * (th1 - th0)), c.T_cs_at(th1))
            ids = np.asarray(snap.ids[gimbal_outliers(snap, hint, c.model, self.fe_config)], np.int64)
            self.worker.drop(ids, camera=index)
            self.further_rejected += int(ids.size)


@dataclass(frozen=True)
class FrameEvent:
    """What the pipeline did with one frame, for an observer of :func:`run_vio_bag` (e.g. a Rerun
    recording): the front end's tracks (normalized image coordinates of each camera, ids shared by the
    static <-> gimbal matches), whether the frame became a keyframe, the gimbal track ids rejected by
    stage two after it, and at a keyframe the body pose ``T_WI`` (4x4, I -> W), the joint angles (rad)
    and the window's landmarks (track id -> point in W, m)."""

    index: int
    frame: TrackFrame
    keyframe: bool
    rejected_ids: NDArray[np.int64]
    T_WI: NDArray[np.float64] | None = None
    theta: NDArray[np.float64] | None = None
    landmarks: dict[int, NDArray[np.float64]] | None = None


def frame_event(item: Tracked, smoother: VioSmoother | None, keyframe: bool, rejected: NDArray[np.int64]) -> FrameEvent:
    """The :class:`FrameEvent` of ``item`` after the smoother took it."""
    if smoother is None or not keyframe:
        return FrameEvent(item.index, item.frame, keyframe, rejected)
    lms = smoother.landmarks
    points = {int(tid): np.asarray(lms.position[lm], float) for tid, lm in lms.active.items() if lm in lms.position}
    T = np.asarray(smoother.state.pose().matrix(), float)
    theta = np.asarray(smoother.theta, float).copy()
    return FrameEvent(item.index, item.frame, True, rejected, T, theta, points)


def frontend_spec(
    bag: str | Path,
    calibration: GimbalCalibration,
    options: VioOptions,
    topics: BagTopics,
    pipeline: PipelineOptions,
    theta0: FloatArray,
    t_range: tuple[int, int],
    cameras: tuple[RunCamera, ...] = (),
    scan: ImuImageStamps | None = None,
) -> WorkerSpec:
    """What the front-end worker needs: bag, topics (no gimbal topic in ``mono``), calibration,
    starting joint angles (rad), the time range (ns) of frames to track and the further cameras."""
    mono = options.mode == "mono"
    return WorkerSpec(
        str(bag),
        topics.imu,
        topics.static,
        None if mono else topics.dynamic,
        pipeline.tolerance_ns,
        time_offsets_ns(options),
        calibration,
        pipeline.frontend,
        tuple(float(x) for x in theta0),
        t_range,
        snapshots=options.mode == "dcc" and pipeline.reject_dynamic,
        extra=cameras,
        lead_frames=options.keyframe_every + 1,
        scan=scan,
    )


def run_statistics(
    bag: str | Path, topics: BagTopics, vb: VioBag, worker: FrontendWorker, driver: SmootherDriver
) -> dict[str, Any]:
    """Run statistics of :func:`run_vio_bag`: inputs, gaps, front-end counters, initial joint angles."""
    joint_fit, cal = driver.joint_fit, driver.cal
    mono = driver.options.mode == "mono"
    return {
        "bag": str(bag),
        "topics": {
            "imu": topics.imu,
            "static": topics.static,
            "dynamic": None if mono else topics.dynamic,
            **{c.name: c.topic for c in driver.cameras},
        },
        "cameras": {
            "used": [
                "cam0",
                *([] if mono else [cal.cluster().primary_gimbal_camera]),
                *(c.name for c in driver.cameras),
            ],
            "further": {c.name: "gimbal" if c.on_gimbal else "rigid" for c in driver.cameras},
            "left_out": ignored_cameras(cal, driver.options.mode, driver.cameras),
        },
        "frames_in_bag": len(vb),
        "pairing": {
            "tolerance_ms": None if vb.tolerance_ns is None else vb.tolerance_ns / 1e6,
            "time_offsets_start_s": list(driver.options.offsets),
            **(vb.pairing_statistics or {}),
            "gimbal_images_between_frames": vb.gimbal_images_between,
            "further": {c.name: vb.extra_pairing_statistics.get(c.topic) for c in driver.cameras},
        },
        "frames_outside_imu": worker.counters["skipped"],
        "image_gaps": len(vb.image_gaps),
        "imu_gaps": len(vb.imu_gaps),
        "imu_samples_dropped": vb.imu_check.non_finite + vb.imu_check.out_of_range + vb.imu_check.out_of_order,
        "imu_samples_out_of_range": vb.imu_check.out_of_range,
        "duplicate_messages_dropped": vb.imu_check.duplicates + vb.duplicate_images,
        "frontend_resets": worker.counters["resets"],
        "frontend_worker": worker.mode,
        "frontend_process_cpu_s": worker.counters["cpu_s"] if worker.mode == "process" else None,
        "initial_joint_angles": None
        if joint_fit is None
        else {
            "theta_rad": joint_fit.theta,
            "sampson_rms_px": joint_fit.rms * float(cal.dynamic_camera.intrinsics[0]),  # type: ignore[union-attr]
            "inlier_pairs": joint_fit.inliers,
            "pairs": joint_fit.pairs,
        },
        "dynamic_tracks_rejected": worker.counters["dynamic_rejected"],
        "further_tracks_rejected": driver.further_rejected,
        "frontend": worker.counters["stats"],
    }


def _open_run(
    bag: str | Path,
    calibration: GimbalCalibration,
    imu_config: ImuConfig,
    options: VioOptions,
    topics: BagTopics,
    pipeline: PipelineOptions,
    initial: InitialState | None,
    cameras: tuple[RunCamera, ...],
) -> tuple[VioBag, VioOptions, WorkerSpec, FloatArray | None]:
    """Read the bag's first pass and check it: the bag, the options with the stamp jitter filled in,
    the front end's spec (with that first pass, so its process does not read it again) and the
    joint-angle guess (rad, or None)."""
    mono = options.mode == "mono"
    vb = VioBag(
        bag,
        topics.imu,
        topics.static,
        None if mono else topics.dynamic,
        extra_topics=tuple(c.topic for c in cameras),
        tolerance_ns=pipeline.tolerance_ns,
        time_offsets_ns=time_offsets_ns(options),
        acc_range=imu_config.acc_range,
        gyro_range=imu_config.gyro_range,
    )
    check_time_offsets(vb, options)
    check_further_sync(vb, cameras, pipeline.max_further_gap_ms)
    synchronized = bag_synchronized(vb, options.mode, cameras)
    warn_persistence_on_unsynchronized(vb, options, synchronized)
    options = options.resolved(synchronized)
    window = options.persistent_landmarks, options.window_s
    log.info("landmarks persistent: %s, window %g s (cameras %ssynchronized)", *window, "" if synchronized else "not ")
    if options.stamp_jitter is None:
        options = dataclasses.replace(options, stamp_jitter=vb.stamp_jitter())
    t_first, t_last = int(vb.imu.t_ns[0]), int(vb.imu.t_ns[-1])
    t_min = t_first + int(pipeline.start_s * NS) if initial is None else max(t_first, int(initial.t_ns))
    if t_min >= t_last:
        raise ValueError(
            f"{bag}: start {pipeline.start_s:g} s is after the end of the IMU data ({(t_last - t_first) / NS:.1f} s)"
        )
    guess = joint_angle_guess(options, initial)
    theta0 = guess if guess is not None else np.zeros(calibration.n_joints)
    spec = frontend_spec(bag, calibration, options, topics, pipeline, theta0, (t_min, t_last), cameras, vb.scan)
    return vb, options, spec, guess


def run_vio_bag(
    bag: str | Path,
    calibration: GimbalCalibration,
    imu_config: ImuConfig,
    options: VioOptions,
    topics: BagTopics | None = None,
    pipeline: PipelineOptions | None = None,
    initial: InitialState | None = None,
    progress: Callable[[int, int, float, float], None] | None = None,
    observer: Callable[[FrameEvent], None] | None = None,
) -> tuple[VioResult, dict[str, Any]]:
    """Run the VIO over a ROS1/ROS2 bag (module docstring).

    Args:
        bag: ROS1 ``.bag`` file or ROS2 bag folder.
        calibration: the gimbal chain and both cameras (``static_camera`` and, unless ``mono``,
            ``dynamic_camera`` must be set).
        imu_config: ``T_sI`` and the IMU noise.
        options: smoother settings; ``mode`` decides whether the gimbal topic is read.
        topics: bag topics (default ``/imu0``, ``/cam0/image_raw``, ``/cam1/image_raw``).
        pipeline: front-end options.
        initial: state at (or before) the first frame to start from; default: standstill
            initialization from the first ``options.standstill_window`` seconds of IMU.
        progress: called after each frame with (frames done, frames total, seconds elapsed, seconds of
            data processed).
        observer: called after each frame with its :class:`FrameEvent` (tracks, keyframe, rejections,
            and at keyframes the pose, joint angles and landmarks).

    Returns:
        the smoother's result (per keyframe) and run statistics (front end, timing, gaps).
    """
    topics = topics or BagTopics()
    pipeline = pipeline or PipelineOptions()
    check_bag_inputs(calibration, options, topics)
    cameras = run_cameras(calibration, options.mode, options.theta_fixed, pipeline.cameras)
    primary = calibration.cluster().primary_gimbal_camera  # left out by mono's definition: not worth a warning
    left_out = [c for c in ignored_cameras(calibration, options.mode, cameras) if c != primary]
    if left_out:
        how = log.info if pipeline.cameras is not None else log.warning  # asked for, or the mode's limit
        how("%s mode leaves out camera(s) %s of the cluster", options.mode, ", ".join(left_out))
    mode = resolve_mode(pipeline.worker)
    reuse_large_buffers()  # per-frame OpenCV scratch buffers stay on the heap (dcc_fg.util.allocator)
    t_wall = time.perf_counter()
    # the front end's process starts now and imports its modules while this one reads the bag
    early = spawn_frontend_process() if mode == "process" else None
    try:
        vb, options, spec, guess = _open_run(bag, calibration, imu_config, options, topics, pipeline, initial, cameras)
    except BaseException:
        if early is not None:
            stop_process(early)
        raise
    worker = FrontendWorker(spec, mode, process=early)
    n_total = len(vb)
    try:
        driver = SmootherDriver(vb.imu, imu_config, calibration, options, pipeline, initial, guess, worker, cameras)
        driver.observer = observer
        for item in worker:
            driver.feed(item)
            if progress is not None:
                data_s = (item.frame.timestamp_ns - driver.t_start_data) / NS
                progress(item.index + 1, n_total, time.perf_counter() - t_wall, data_s)
        driver.finish()
    finally:
        worker.close()
    if driver.smoother is None:
        raise ValueError(f"{bag}: no camera frame lies within the IMU time span of topic {topics.imu}")
    result = driver.smoother.result()
    duration = (int(result.timestamps_ns[-1]) - int(result.timestamps_ns[0])) / NS
    result.stats.update(timing_stats(time.perf_counter() - t_wall, duration, worker.counters["processed"]))
    return result, run_statistics(bag, topics, vb, worker, driver)


def _shared_pairs(frame: TrackFrame) -> tuple[FloatArray, FloatArray]:
    """Normalized coordinates (N, 2) in s and in d of the tracks both cameras see in ``frame``."""
    _, i_s, i_d = np.intersect1d(frame.static_ids, frame.dynamic_ids, return_indices=True)
    return frame.static_xy[i_s], frame.dynamic_xy[i_d]


def _initial_joint_angles(cal: GimbalCalibration, frame: TrackFrame, guess: FloatArray | None, fit: bool) -> JointFit:
    """Joint angles at the first frame: fitted to its static <-> gimbal pairs (starting from
    ``guess``, or from a grid without one); the guess itself when fitting is off or impossible."""
    xy_s, xy_d = _shared_pairs(frame)
    L = cal.n_joints
    if fit and len(xy_s) >= 2 * L + 2:
        result = fit_joint_angles(cal, xy_s, xy_d, guess)
        if result.inliers >= max(2 * L + 2, result.pairs // 2):
            log.info(
                "initial joint angles %s rad from %d of %d static/gimbal pairs",
                np.round(result.theta, 4),
                result.inliers,
                result.pairs,
            )
            return result
        log.warning("initial joint-angle fit: only %d of %d pairs agree", result.inliers, result.pairs)
    if guess is None:
        raise ValueError(
            f"dcc mode: the first frame has {len(xy_s)} static/gimbal matches, too few to find the joint angles; "
            "give a starting guess (--initial-joints, rad)"
        )
    return JointFit(np.asarray(guess, float), float("nan"), 0, len(xy_s))


def _theta_measurement(
    smoother: VioSmoother, cal: GimbalCalibration, frame: TrackFrame, kf_prev: tuple[int, FloatArray] | None
) -> tuple[FloatArray, FloatArray] | None:
    """dcc keyframes whose gimbal camera sees few mapped landmarks: the joint angles measured from
    the frame's static <-> gimbal pairs (epipolar fit started at the last keyframe's angles), with
    covariance."""
    if smoother.opt.mode != "dcc" or kf_prev is None or not smoother.next_is_keyframe():
        return None
    if smoother.gimbal_landmarks(frame) >= smoother.opt.min_gimbal_landmarks:
        return None
    xy_s, xy_d = _shared_pairs(frame)
    if len(xy_s) < max(8, 2 * cal.n_joints + 2):
        return None
    fit = fit_joint_angles(cal, xy_s, xy_d, kf_prev[1], grid=0)
    if fit.covariance is None or fit.inliers < max(8, fit.pairs // 2):
        return None
    return fit.theta, fit.covariance
