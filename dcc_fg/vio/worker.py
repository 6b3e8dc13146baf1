"""Where the VIO front end runs: inline, or in a child process a fixed number of frames ahead of the smoother.

The smoother (GTSAM) holds the GIL through its updates, so a thread cannot overlap the front end
with it; a child process can (a fresh interpreter, ``python -m dcc_fg.vio.worker``, talking
length-prefixed pickles over its stdin/stdout), started before the parent reads the bag so that its
imports (about 0.6 s) overlap the parent's first pass; the parent then sends that first pass (IMU and
image stamps) with the :class:`WorkerSpec`, so the child does not read it again (on the 60 s flight
its first frame is tracked 0.76-1.10 s after the start instead of 2.06-2.34 s, three runs alternated
with the code before). The child opens the bag itself (:class:`~dcc_fg.sources.vio_bag.VioBag`),
decodes and tracks every frame pair (:class:`~dcc_fg.vio.frontend.Frontend`) and sends the tracks
to the parent; the parent sends back the joint angles of each new keyframe (the front end's
T_ds(theta) guess for the static <-> gimbal matching) and the ids of gimbal tracks to drop (the second
stage of the gimbal outlier handling).

Determinism. The child tracks frame ``n`` only after the parent has finished frame ``n - lead``
(:attr:`WorkerSpec.lead_frames`; the parent says so with a ``("done", n)`` message when it asks for the
next frame) and applies exactly the messages the parent sent up to then, in order: so every run of a
bag gives the same tracks and the same trajectory, whatever the machine's load (before, the child
took whatever had arrived, and the first joint's RMSE of one 60 s flight varied by 18 % between two
runs). Inline, frame ``n`` sees the messages of frame ``n - 1`` (the same rule with a lead of 1, but
no overlap). The lead must span a keyframe: the smoother's update on a keyframe takes several frames'
worth of tracking time, and with a lead of 2 or 3 (``keyframe_every`` 3) the child waited through it
(1.5x the wall time of the free-running child on the 60 s flight); ``keyframe_every + 1`` frames
keep the overlap. A longer lead delays when a rejected track stops being tracked and how fresh the
joint-angle guess is, and that costs accuracy: over eight 60 s flights (``keyframe_every`` 3,
``benchmarks/bench_vio_revision.py``) ``keyframe_every + 2`` had 1.09x / 1.14x the joint RMSE and
1.01x the translation RMSE of ``keyframe_every + 1``, in 1.05x the wall time.

Both modes have the same interface (:class:`FrontendWorker`): iterate for :class:`Tracked`
frames, :meth:`~FrontendWorker.push_theta`, :meth:`~FrontendWorker.drop`, and after the
iteration the counters and the front end's statistics. Times in ns, angles in rad.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import pickle
import queue
import signal
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from dcc_fg.data.cameras import RunCamera
from dcc_fg.data.vio import TrackFrame
from dcc_fg.io.bags import ImuImageStamps
from dcc_fg.model import GimbalCalibration
from dcc_fg.sources.vio_bag import VioBag
from dcc_fg.util.allocator import reuse_large_buffers
from dcc_fg.vio.frontend import DynamicSnapshot, Frontend, FrontendConfig

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
MODES = ("process", "inline")


def usable_cores() -> int:
    """How many cores this process may run on (its CPU affinity where the OS reports it)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def resolve_mode(mode: str) -> str:
    """``inline`` or ``process`` for a requested worker mode: ``auto`` is ``process`` when at least
    two cores are usable (the front end then overlaps the smoother: on an idle 2-core machine,
    ``benchmarks/bench_vio.py`` measured 1.41x the inline speed for ``dcc``), else ``inline``."""
    if mode == "auto":
        return "process" if usable_cores() >= 2 else "inline"
    if mode not in MODES:
        raise ValueError(f"front-end worker mode '{mode}' is not one of auto, {', '.join(MODES)}")
    return mode


class ThetaTrack:
    """Joint angles the front end should assume at a frame time: the smoother's keyframe estimates,
    extrapolated linearly from the last two keyframes (held when there is only one)."""

    def __init__(self, theta0: FloatArray, t0_ns: int) -> None:
        self.hist: list[tuple[int, FloatArray]] = [(t0_ns, np.asarray(theta0, float).copy())]

    def push(self, t_ns: int, theta: FloatArray) -> None:
        self.hist = [self.hist[-1], (int(t_ns), np.asarray(theta, float).copy())]

    def at(self, t_ns: int) -> FloatArray:
        t1, th1 = self.hist[-1]
        if len(self.hist) < 2 or self.hist[-1][0] <= self.hist[0][0]:
            return th1.copy()
        t0, th0 = self.hist[0]
        rate = (th1 - th0) / (t1 - t0)
        return th1 + rate * min(t_ns - t1, t1 - t0)  # extrapolate at most one keyframe interval


def chain_sizes(primary_joints: int, extra: Sequence[RunCamera]) -> list[int]:
    """Joint counts of the chains a run follows, slot order: the primary chain, then the further ones."""
    sizes = {0: primary_joints}
    for c in extra:
        if c.on_gimbal and c.slot >= 1:
            sizes[c.slot] = c.n_joints
    return [sizes[s] for s in sorted(sizes)]


def split_theta(flat: FloatArray, sizes: Sequence[int]) -> list[FloatArray]:
    """The flat joint-angle vector (chains in slot order, :func:`chain_sizes`) split per chain."""
    return np.split(np.asarray(flat, float), np.cumsum(sizes)[:-1])


@dataclass(frozen=True)
class Tracked:
    """One frame out of the front end: its index among the bag's frame pairs, its tracks, whether it
    follows a gap, and the gimbal-track snapshot for the outlier test (None unless requested)."""

    index: int
    frame: TrackFrame
    after_gap: bool
    snapshot: DynamicSnapshot | None
    further_snapshots: tuple[tuple[int, DynamicSnapshot], ...] = ()


@dataclass(frozen=True)
class WorkerSpec:
    """Everything the front end needs, picklable for a child process. ``extra``: the further cameras
    of an N-camera run (run index >= 2); their topics are read from the bag, paired with the static
    images, and tracked. ``lead_frames``: the child tracks frame n once the parent has finished frame
    n - lead_frames (module docstring). ``scan``: the bag's first pass (IMU and image stamps) as the parent
    read it, so the child does not read it again (None: the child reads it)."""

    bag: str
    imu_topic: str
    static_topic: str
    dynamic_topic: str | None
    tolerance_ns: int | None
    time_offsets_ns: tuple[int, int]
    calibration: GimbalCalibration
    config: FrontendConfig | None
    theta0: tuple[float, ...]
    t_range: tuple[int, int]
    snapshots: bool
    extra: tuple[RunCamera, ...] = ()
    lead_frames: int = 3  # what the pipeline gives the default keyframe_every (2): keyframe_every + 1
    scan: ImuImageStamps | None = None


class _Tracker:
    """The front end over a frame stream: skips frames outside ``t_range``, resets after gaps,
    applies drops and joint-angle pushes, and counts (``cpu_s``: the process's CPU time, s, which in
    a child process is the front end's own)."""

    def __init__(self, spec: WorkerSpec) -> None:
        self.spec = spec
        cal = spec.calibration
        assert cal.static_camera is not None
        mono = spec.dynamic_topic is None
        # the joint angles the front end follows: the primary chain's, then each further chain's (slot order)
        self.sizes = chain_sizes(cal.n_joints, spec.extra)
        theta0 = np.asarray(spec.theta0, float)
        if theta0.size < sum(self.sizes):
            theta0 = np.r_[theta0, np.zeros(sum(self.sizes) - theta0.size)]
        self.frontend = Frontend(
            cal.static_camera,
            None if mono else cal.dynamic_camera,
            spec.config,
            T_ds=None if mono else cal.T_ds(theta0[: self.sizes[0]]),
            extra=spec.extra,
        )
        self.thetas = ThetaTrack(theta0, spec.t_range[0])
        self.skipped = self.resets = self.processed = 0

    def counters(self) -> dict[str, Any]:
        return {
            "cpu_s": time.process_time(),
            "skipped": self.skipped,
            "resets": self.resets,
            "processed": self.processed,
            "dynamic_rejected": int(self.frontend.stats.dynamic_rejected),
            "stats": self.frontend.stats.summary(),
        }

    def frames(self, bag: VioBag) -> Iterator[Tracked]:
        fe, spec = self.frontend, self.spec
        mono = fe.dynamic is None
        started = False
        for index, vf in enumerate(bag.frames()):
            t = int(vf.timestamp_ns)
            if not spec.t_range[0] <= t <= spec.t_range[1]:
                self.skipped += 1
                continue
            if vf.after_gap and started:
                fe.reset()
                self.resets += 1
            theta = split_theta(self.thetas.at(t), self.sizes)
            T_ds = None if mono else spec.calibration.T_ds(theta[0])
            for image in vf.dynamic_between:
                fe.track_gimbal(image)
            # the further cameras follow their chain's extrapolated joint angles (rigid ones ignore them)
            extra_T_cs = [c.T_cs_at(theta[c.slot]) for c in spec.extra] if spec.extra else None
            frame = fe.process(t, vf.static, vf.dynamic, T_ds=T_ds, extra_images=vf.extra, extra_T_cs=extra_T_cs)
            if vf.dynamic is not None:
                frame = dataclasses.replace(frame, dynamic_timestamp_ns=int(vf.dynamic_timestamp_ns))
            started = True
            self.processed += 1
            further = ()
            if spec.snapshots:  # further cameras on a gimbal, with an image this frame
                seen = {c.camera for c in frame.extra}
                further = tuple(
                    (c.index, fe.camera_snapshot(c.index)) for c in spec.extra if c.on_gimbal and c.index in seen
                )
            yield Tracked(index, frame, vf.after_gap, fe.dynamic_snapshot() if spec.snapshots else None, further)


def _open_bag(spec: WorkerSpec) -> VioBag:
    return VioBag(
        spec.bag,
        spec.imu_topic,
        spec.static_topic,
        spec.dynamic_topic,
        tolerance_ns=spec.tolerance_ns,
        time_offsets_ns=spec.time_offsets_ns,
        extra_topics=tuple(c.topic for c in spec.extra),
        scan=spec.scan,
    )


def _send(stream: Any, obj: Any) -> None:
    """Length-prefixed pickle on a binary stream."""
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(struct.pack("<Q", len(data)))
    stream.write(data)
    stream.flush()


def _recv(stream: Any) -> Any:
    """The next length-prefixed pickle (EOFError at the end of the stream)."""
    head = stream.read(8)
    if len(head) < 8:
        raise EOFError
    (n,) = struct.unpack("<Q", head)
    data = stream.read(n)
    if len(data) < n:
        raise EOFError
    return pickle.loads(data)


def _apply_until(ctrl: queue.Queue[Any], tracker: _Tracker, done: int) -> bool:
    """Apply the parent's messages in order, blocking, up to its ``("done", done)`` (nothing when
    ``done`` < 0); False when the parent has stopped."""
    if done < 0:
        return True
    while True:
        msg = ctrl.get()
        if msg[0] == "stop":
            return False
        if msg[0] == "done":
            if msg[1] >= done:
                return True
        elif msg[0] == "theta":
            tracker.thetas.push(msg[1], msg[2])
        elif msg[0] == "drop":
            tracker.frontend.drop_camera(msg[2], msg[1])


def child_main() -> None:
    """Entry of the front-end process (``python -m dcc_fg.vio.worker``): the spec, then control
    messages on stdin; :class:`Tracked` items and a final ``("end", counters)`` on stdout."""
    logging.disable(logging.WARNING)  # the parent has read the same bag and reported its problems
    # Ctrl-C reaches the whole process group: the parent reports it in one line and closes the pipes,
    # which ends this process (EOF / BrokenPipeError); a traceback of its own would only add noise.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    cv2.setNumThreads(1)  # one core for the front end, the other for the smoother
    reuse_large_buffers()  # the per-frame OpenCV buffers stay on the heap (dcc_fg.util.allocator)
    inp, out = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # nothing else may write to the data stream
    try:
        spec: WorkerSpec = _recv(inp)
        ctrl: queue.Queue[Any] = queue.Queue()

        def read_control() -> None:
            try:
                while True:
                    ctrl.put(_recv(inp))
            except EOFError:
                ctrl.put(("stop",))

        threading.Thread(target=read_control, daemon=True).start()
        tracker = _Tracker(spec)
        for sent, item in enumerate(tracker.frames(_open_bag(spec))):
            _send(out, item)  # blocks while the pipe is full: the smoother sets the pace
            # the next frame (number sent + 1) sees exactly what the parent did up to frame sent + 1 - lead
            if not _apply_until(ctrl, tracker, sent + 1 - spec.lead_frames):
                return
        _send(out, ("end", tracker.counters()))
    except BrokenPipeError:  # the parent stopped reading
        return
    except BaseException as exc:  # reported to the parent, which raises it
        try:
            _send(out, ("error", type(exc).__name__, str(exc)))
        except (BrokenPipeError, OSError):  # the parent has gone: nobody to report to
            return


def spawn_frontend_process() -> subprocess.Popen[bytes]:
    """Start the front end's child process: a fresh interpreter that imports its modules (about 0.6 s)
    and waits for its :class:`WorkerSpec` on stdin, so the parent can read the bag meanwhile."""
    # a fresh interpreter: no fork of a process that may hold GTSAM/OpenCV worker threads, and
    # no re-import of the caller's main module (multiprocessing's spawn would need a guard). It
    # imports what the parent imports: the parent's sys.path as PYTHONPATH (its '' as the working
    # directory), and -P keeps ``-m`` from putting the working directory first (a dcc_fg checkout
    # there, of another version than the parent's, would otherwise be the child's, and the two
    # would deadlock on a different protocol)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p or os.getcwd() for p in sys.path))
    return subprocess.Popen(
        [sys.executable, "-P", "-m", "dcc_fg.vio.worker"], stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env
    )


def stop_process(proc: subprocess.Popen[bytes]) -> None:
    """Close a front-end child's pipes (it ends on EOF) and wait for it; killed after 10 s."""
    for stream in (proc.stdin, proc.stdout):
        if stream is not None:
            try:
                stream.close()
            except OSError:
                pass
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


class FrontendWorker:
    """The front end over a bag's frames, ``inline`` or in a child ``process`` (module docstring)."""

    def __init__(self, spec: WorkerSpec, mode: str = "inline", process: subprocess.Popen[bytes] | None = None) -> None:
        if mode not in MODES:
            raise ValueError(f"front-end worker mode '{mode}' is not one of {', '.join(MODES)}")
        if process is not None and mode != "process":
            stop_process(process)
            raise ValueError(f"a started front-end process was given to a front end that runs {mode}")
        self.spec, self.mode = spec, mode
        self.counters: dict[str, Any] = {}
        self._tracker: _Tracker | None = _Tracker(spec) if mode == "inline" else None
        self._proc: subprocess.Popen[bytes] | None = None
        #: a child started ahead (:func:`spawn_frontend_process`), not yet sent the spec
        self._spawned = process

    def _start(self) -> subprocess.Popen[bytes]:
        proc = self._spawned if self._spawned is not None else spawn_frontend_process()
        self._spawned = None
        assert proc.stdin is not None
        _send(proc.stdin, self.spec)
        return proc

    def _control(self, msg: tuple[Any, ...]) -> None:
        if self._proc is None or self._proc.stdin is None:
            return
        try:
            _send(self._proc.stdin, msg)
        except (BrokenPipeError, ValueError):  # the child has ended
            pass

    def push_theta(self, t_ns: int, theta: FloatArray) -> None:
        """The smoother's joint angles at keyframe time ``t_ns`` (rad)."""
        if self._tracker is not None:
            self._tracker.thetas.push(t_ns, theta)
        else:
            self._control(("theta", int(t_ns), np.asarray(theta, float)))

    def drop(self, ids: IntArray, camera: int = 1) -> None:
        """Stop tracking these track ids of camera ``camera`` (run index: 1 the gimbal camera, >= 2 a
        further camera on a gimbal)."""
        if len(ids) == 0:
            return
        if self._tracker is not None:
            self._tracker.frontend.drop_camera(camera, np.asarray(ids, np.int64))
        else:
            self._control(("drop", np.asarray(ids, np.int64), int(camera)))

    def __iter__(self) -> Iterator[Tracked]:
        if self._tracker is not None:
            yield from self._tracker.frames(_open_bag(self.spec))
            self.counters = self._tracker.counters()
            return
        self._proc = proc = self._start()
        assert proc.stdout is not None
        received = 0
        while True:
            try:
                item = _recv(proc.stdout)
            except EOFError:
                code = proc.wait()
                raise RuntimeError(
                    f"the front-end process for {self.spec.bag} ended early (exit code {code})"
                ) from None
            if isinstance(item, tuple):
                if item[0] == "error":
                    kind = {"ValueError": ValueError, "FileNotFoundError": FileNotFoundError}.get(item[1], RuntimeError)
                    raise kind(
                        item[2] if kind is not RuntimeError else f"front end on {Path(self.spec.bag)}: {item[2]}"
                    )
                self.counters = item[1]
                return
            yield item
            self._control(("done", received))  # everything the parent does for this frame is sent
            received += 1

    def close(self) -> None:
        """Stop the child process (if any) and wait for it."""
        for proc in (self._proc, self._spawned):
            if proc is not None:
                stop_process(proc)
        self._proc = self._spawned = None


if __name__ == "__main__":
    # run the importable module's copy, so pickled objects name dcc_fg.vio.worker, not __main__
    from dcc_fg.vio.worker import child_main as _main

    _main()
    sys.stderr.flush()
    os._exit(0)  # no interpreter shutdown while the control thread still blocks on stdin
