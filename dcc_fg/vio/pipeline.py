"""Images to trajectory: a recorded bag through the front end and the keyframe smoother (``dcc-fg vio``).

One pass over the bag (:class:`~dcc_fg.io.vio_bag.VioBag` reads the IMU topic first, then decodes
the images one synchronized pair at a time): every frame pair goes through
:class:`~dcc_fg.vio.frontend.Frontend` (KLT tracks, static RANSAC, static <-> gimbal matching with the
current T_ds(theta) estimate) and the resulting :class:`~dcc_fg.vio.types.TrackFrame` into
:class:`~dcc_fg.vio.backend.VioSmoother`.

Gimbal-camera outliers (``dcc`` mode) follow the two stages the paper proposes as future work: the
smoother first estimates the joint angles of a keyframe with *all* gimbal tracks (Huber loss, no
rejection), then the gimbal tracks of that frame that are inconsistent with the epipolar geometry
implied by the *updated* extrinsics T_ds(theta_prev), T_ds(theta_cur) and the static camera's
motion seen by its own tracks are rejected (:meth:`Frontend.dynamic_outliers`): the front end stops
tracking them and the smoother's gate drops their observations from the current keyframe.

The front end runs in a worker thread one frame ahead of the smoother (OpenCV releases the GIL, so
tracking overlaps the smoother's update on the second core); it tracks the next frame with the joint
angles extrapolated linearly from the last two keyframe estimates (the gimbal moves at up to
~60 deg/s: one 20 Hz frame is 3 deg), which only the static <-> gimbal matching uses.

Frames: ``T_WI`` body (IMU) pose in the world W (gravity along -z), ``T_sI`` IMU -> static camera,
``T_ds(theta)`` static -> gimbal camera; times in ns; joint angles in rad.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dcc_fg.io.vio_bag import VioBag, VioFrame
from dcc_fg.model import GimbalCalibration
from dcc_fg.vio.backend import NS, InitialState, VioOptions, VioResult, VioSmoother
from dcc_fg.vio.frontend import DynamicSnapshot, Frontend, FrontendConfig, GimbalHint
from dcc_fg.vio.joint_init import JointFit, fit_joint_angles
from dcc_fg.vio.types import ImuConfig, TrackFrame

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
    handling; ``tolerance_ns`` pairs static and gimbal images; ``frontend`` overrides the front-end
    parameters (default: :meth:`FrontendConfig.for_resolution` of the static camera);
    ``fit_initial_joints`` (``dcc``) starts the joint angles from the first frame's static <-> gimbal
    matches (:func:`~dcc_fg.vio.joint_init.fit_joint_angles`) instead of taking the guess as is;
    ``threaded`` runs the front end in a worker thread one frame ahead of the smoother (OpenCV
    releases the GIL, so tracking overlaps the smoother's update on a second core)."""

    reject_dynamic: bool = True
    fit_initial_joints: bool = True
    threaded: bool = True
    tolerance_ns: int = 5_000_000
    frontend: FrontendConfig | None = None


class _ThetaTrack:
    """Joint angles the front end should assume at a frame time: the smoother's keyframe estimates,
    extrapolated linearly from the last two keyframes (held when there is only one). Thread-safe."""

    def __init__(self, theta0: FloatArray, t0_ns: int) -> None:
        self.hist: list[tuple[int, FloatArray]] = [(t0_ns, np.asarray(theta0, float).copy())]
        self._lock = threading.Lock()

    def push(self, t_ns: int, theta: FloatArray) -> None:
        with self._lock:
            self.hist = [self.hist[-1], (t_ns, np.asarray(theta, float).copy())]

    def at(self, t_ns: int) -> FloatArray:
        with self._lock:
            hist = list(self.hist)
        t1, th1 = hist[-1]
        if len(hist) < 2 or hist[-1][0] <= hist[0][0]:
            return th1.copy()
        t0, th0 = hist[0]
        rate = (th1 - th0) / (t1 - t0)
        return th1 + rate * min(t_ns - t1, t1 - t0)  # extrapolate at most one keyframe interval


@dataclass(frozen=True)
class _Tracked:
    """One frame out of the front end: its index in the bag, tracks, gap flag and gimbal snapshot."""

    index: int
    frame: TrackFrame
    after_gap: bool
    snapshot: DynamicSnapshot | None


class _FrontendWorker:
    """Runs the front end over the bag's frames, in a thread one frame ahead of the consumer
    (``threaded``) or inline. Frames outside ``t_range`` (ns) are skipped; the first frame after a
    gap resets the tracks; :meth:`drop` removes gimbal tracks before the next frame is tracked."""

    _END = object()

    def __init__(
        self,
        frames: Iterator[VioFrame],
        frontend: Frontend,
        calibration: GimbalCalibration,
        thetas: _ThetaTrack,
        t_range: tuple[int, int],
        snapshots: bool,
        threaded: bool,
    ) -> None:
        self.frames, self.frontend, self.cal, self.thetas = frames, frontend, calibration, thetas
        self.t_range, self.snapshots = t_range, snapshots
        self.skipped = self.resets = self.processed = 0
        self._drops: list[IntArray] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=2)
        self._thread = threading.Thread(target=self._run, name="dcc-fg-frontend", daemon=True) if threaded else None

    def drop(self, ids: IntArray) -> None:
        if len(ids):
            with self._lock:
                self._drops.append(np.asarray(ids, dtype=np.int64))

    def _frames(self) -> Iterator[_Tracked]:
        fe, mono = self.frontend, self.frontend.dynamic is None
        started = False
        for index, vf in enumerate(self.frames):
            if self._stop.is_set():
                return
            t = int(vf.timestamp_ns)
            if not self.t_range[0] <= t <= self.t_range[1]:
                self.skipped += 1
                continue
            with self._lock:
                drops, self._drops = self._drops, []
            for ids in drops:
                fe.drop_dynamic(ids)
            if vf.after_gap and started:
                fe.reset()
                self.resets += 1
            T_ds = None if mono else self.cal.T_ds(self.thetas.at(t))
            frame = fe.process(t, vf.static, vf.dynamic, T_ds=T_ds)
            started = True
            self.processed += 1
            yield _Tracked(index, frame, vf.after_gap, fe.dynamic_snapshot() if self.snapshots else None)

    def _run(self) -> None:
        try:
            for item in self._frames():
                while not self._stop.is_set():
                    try:
                        self._queue.put(item, timeout=0.1)
                        break
                    except queue.Full:
                        continue
            self._queue.put(self._END)
        except BaseException as exc:  # handed to the consumer, raised there
            self._queue.put(exc)

    def __iter__(self) -> Iterator[_Tracked]:
        if self._thread is None:
            yield from self._frames()
            return
        self._thread.start()
        while True:
            item = self._queue.get()
            if item is self._END:
                return
            if isinstance(item, BaseException):
                raise item
            yield item

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread.is_alive():
            while self._thread.is_alive():  # unblock a producer waiting on a full queue
                try:
                    self._queue.get(timeout=0.1)
                except queue.Empty:
                    pass
            self._thread.join()


def run_vio_bag(
    bag: str | Path,
    calibration: GimbalCalibration,
    imu_config: ImuConfig,
    options: VioOptions,
    topics: BagTopics | None = None,
    pipeline: PipelineOptions | None = None,
    initial: InitialState | None = None,
    progress: Callable[[int, int, float, float], None] | None = None,
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

    Returns:
        the smoother's result (per keyframe) and run statistics (front end, timing, gaps).
    """
    topics = topics or BagTopics()
    pipeline = pipeline or PipelineOptions()
    if calibration.static_camera is None:
        raise ValueError("the calibration has no static camera model (cam0 intrinsics are needed for VIO)")
    mono = options.mode == "mono"
    if not mono and calibration.dynamic_camera is None:
        raise ValueError(f"mode '{options.mode}' needs the gimbal camera model (cam1 intrinsics)")
    if not mono and topics.dynamic is None:
        raise ValueError(f"mode '{options.mode}' needs the gimbal camera's image topic")
    t_wall = time.perf_counter()
    vb = VioBag(bag, topics.imu, topics.static, None if mono else topics.dynamic, tolerance_ns=pipeline.tolerance_ns)
    L = calibration.n_joints
    guess: FloatArray | None = None
    if options.mode == "scc":
        guess = np.asarray(options.theta_fixed, float)
    elif initial is not None and initial.theta.size:
        guess = np.asarray(initial.theta, float)
    elif options.theta_initial is not None:
        guess = np.asarray(options.theta_initial, float)
    theta0 = guess if guess is not None else np.zeros(L)
    frontend = Frontend(
        calibration.static_camera,
        None if mono else calibration.dynamic_camera,
        pipeline.frontend,
        T_ds=None if mono else calibration.T_ds(theta0),
    )
    t_first, t_last = int(vb.imu.t_ns[0]), int(vb.imu.t_ns[-1])
    t_min = t_first if initial is None else max(t_first, int(initial.t_ns))
    thetas = _ThetaTrack(theta0, t_min)
    worker = _FrontendWorker(
        vb.frames(),
        frontend,
        calibration,
        thetas,
        (t_min, t_last),
        snapshots=options.mode == "dcc" and pipeline.reject_dynamic,
        threaded=pipeline.threaded,
    )
    smoother: VioSmoother | None = None
    joint_fit: JointFit | None = None
    n_total = len(vb)
    done = 0
    t_start_data = 0
    t_prev = 0
    kf_prev: tuple[int, FloatArray] | None = None  # last keyframe's time and joint angles (dcc)
    try:
        for item in worker:
            done = item.index + 1
            frame, t = item.frame, item.frame.timestamp_ns
            if smoother is None:
                if options.mode == "dcc":
                    joint_fit = _initial_joint_angles(calibration, frame, guess, pipeline.fit_initial_joints)
                    theta0 = joint_fit.theta
                    options = dataclasses.replace(options, theta_initial=tuple(float(x) for x in theta0))
                start = initial
                if start is not None:
                    start = InitialState(t, start.T_WI, start.v_W, start.acc_bias, start.gyro_bias, theta0)
                smoother = VioSmoother(vb.imu, imu_config, None if mono else calibration, options)
                smoother.initialize(frame, start)
                t_start_data = t
                if options.mode == "dcc":
                    kf_prev = (t, smoother.theta.copy())
                    thetas.push(t, smoother.theta)
            elif smoother.add_frame(frame, _theta_measurement(smoother, calibration, frame, thetas.at(t))) and (
                options.mode == "dcc"
            ):
                assert kf_prev is not None
                theta_k = smoother.theta.copy()
                thetas.push(t, theta_k)
                if item.snapshot is not None and not item.after_gap:
                    # stage two: the joint angles were estimated with every gimbal track; reject with
                    # the updated extrinsics (previous frame: interpolated between the keyframes)
                    t_k0, theta_k0 = kf_prev
                    w = (t_prev - t_k0) / max(t - t_k0, 1)
                    hint = GimbalHint(calibration.T_ds(theta_k0 + w * (theta_k - theta_k0)), calibration.T_ds(theta_k))
                    bad = frontend.dynamic_outliers(hint, item.snapshot)
                    worker.drop(item.snapshot.ids[bad])
                kf_prev = (t, theta_k)
            t_prev = t
            if progress is not None:
                progress(done, n_total, time.perf_counter() - t_wall, (t - t_start_data) / NS)
    finally:
        worker.close()
    if smoother is None:
        raise ValueError(f"{bag}: no camera frame lies within the IMU time span of topic {topics.imu}")
    result = smoother.result()
    elapsed = time.perf_counter() - t_wall
    duration = (int(result.timestamps_ns[-1]) - int(result.timestamps_ns[0])) / NS
    fe = frontend.stats.summary()
    result.stats.update(
        {
            "processing_time_s": elapsed,
            "data_duration_s": duration,
            "real_time_factor": elapsed / duration if duration > 0 else float("nan"),
            "frames": worker.processed,
        }
    )
    run = {
        "bag": str(bag),
        "topics": {"imu": topics.imu, "static": topics.static, "dynamic": None if mono else topics.dynamic},
        "frame_pairs_in_bag": n_total,
        "frames_outside_imu": worker.skipped,
        "image_gaps": len(vb.image_gaps),
        "imu_gaps": len(vb.imu_gaps),
        "imu_samples_dropped": vb.imu_check.non_finite + vb.imu_check.out_of_order,
        "frontend_resets": worker.resets,
        "frontend_thread": pipeline.threaded,
        "initial_joint_angles": None
        if joint_fit is None
        else {
            "theta_rad": joint_fit.theta,
            "sampson_rms_px": joint_fit.rms * float(calibration.dynamic_camera.intrinsics[0]),  # type: ignore[union-attr]
            "inlier_pairs": joint_fit.inliers,
            "pairs": joint_fit.pairs,
        },
        "dynamic_tracks_rejected": int(frontend.stats.dynamic_rejected),
        "frontend": fe,
    }
    return result, run


def _initial_joint_angles(cal: GimbalCalibration, frame: TrackFrame, guess: FloatArray | None, fit: bool) -> JointFit:
    """Joint angles at the first frame: fitted to its static <-> gimbal pairs (starting from
    ``guess``, or from a grid without one); the guess itself when fitting is off or impossible."""
    common, i_s, i_d = np.intersect1d(frame.static_ids, frame.dynamic_ids, return_indices=True)
    L = cal.n_joints
    if fit and common.size >= 2 * L + 2:
        result = fit_joint_angles(cal, frame.static_xy[i_s], frame.dynamic_xy[i_d], guess)
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
            f"dcc mode: the first frame has {common.size} static/gimbal matches, too few to find the joint angles; "
            "give a starting guess (--initial-joints, rad)"
        )
    return JointFit(np.asarray(guess, float), float("nan"), 0, int(common.size))


def _theta_measurement(
    smoother: VioSmoother, cal: GimbalCalibration, frame: TrackFrame, theta_pred: FloatArray
) -> tuple[FloatArray, FloatArray] | None:
    """dcc keyframes whose gimbal camera sees few mapped landmarks: the joint angles measured from
    the frame's static <-> gimbal pairs (epipolar fit started at the prediction), with covariance."""
    if smoother.opt.mode != "dcc" or not smoother.next_is_keyframe():
        return None
    if smoother.gimbal_landmarks(frame) >= smoother.opt.min_gimbal_landmarks:
        return None
    common, i_s, i_d = np.intersect1d(frame.static_ids, frame.dynamic_ids, return_indices=True)
    if common.size < max(8, 2 * cal.n_joints + 2):
        return None
    fit = fit_joint_angles(cal, frame.static_xy[i_s], frame.dynamic_xy[i_d], theta_pred, grid=0)
    if fit.covariance is None or fit.inliers < max(8, fit.pairs // 2):
        return None
    return fit.theta, fit.covariance
