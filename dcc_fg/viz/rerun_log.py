"""Interactive view of a calibration, validation or VIO run as a Rerun recording (``--rerun FILE.rrd``).

Every use of ``rerun-sdk`` (the optional extra ``dcc-fg[viz]``) is in this module. It is imported at the
top inside ``try``: :data:`RERUN_AVAILABLE` says whether it is installed, and :func:`require_rerun`
refuses a ``--rerun`` request without it before any work starts. The geometry comes from
:mod:`dcc_fg.viz.scene` and :mod:`dcc_fg.viz.vio_scene`, the images from :mod:`dcc_fg.viz.images`.

Recording layout (timelines ``snapshot`` (sequence) and ``time`` (timestamp, the snapshot's or
keyframe's stamp in ns) for calibration and validation; ``keyframe``, ``frame`` (the frame's index in the
bag's synchronized pairs) and ``time`` (the static image's stamp) for VIO):

* calibration / validation, world = the static camera frame s (x right, y down, z forward; metres):
  ``world/static_camera``, ``world/gimbal_base``, ``world/link_<l>`` (DH frames between the joints),
  ``world/end_effector``, ``world/gimbal_camera``: ``Transform3D`` ``T_s<frame>`` at each snapshot's
  estimated joint angles, with axes; ``world/chain`` (polyline through the frame origins) and
  ``world/joint_axes``; ``world/target`` (``T_st``) with ``world/target/corners``;
  ``world/<camera>/image``: the camera (``Pinhole``), its image (JPEG; only where the data hold
  images), ``.../detected`` and ``.../reprojected`` corners (pixels, distorted image) and
  ``.../border`` (the image rectangle, so the corners have a canvas without images); time series
  ``joints/theta_<l>`` (rad), ``joints/sigma_<l>`` (1-sigma, rad), ``residuals/static_rms_px`` and
  ``residuals/gimbal_rms_px`` (RMS per axis of the snapshot's residuals, pixels).
* VIO, world = W (gravity along -z; metres): ``world/body`` (``T_WI`` per keyframe),
  ``world/body/static_camera`` (``T_Is``), under it the chain frames as above at each keyframe's
  joint angles (dcc, scc); ``world/trajectory/estimate`` (one line per trajectory segment); with ground
  truth ``world/trajectory/truth`` and ``world/truth_body`` (the truth in W, see
  :func:`dcc_fg.viz.vio_scene.truth_in_estimate_frame`) and ``joints/truth/theta_<l>``; time series
  ``joints/estimate/theta_<l>`` (rad), ``motion/speed_m_s``, ``imu/acc_bias/<axis>`` (m/s^2),
  ``imu/gyro_bias/<axis>`` (rad/s); ``events`` (segment starts). Logged while the run goes
  (:class:`VioRecorder`, the observer of :func:`~dcc_fg.vio.pipeline.run_vio_bag`), on the ``frame`` and
  ``time`` timelines of every frame and the ``keyframe`` timeline of keyframes:
  ``world/body/static_camera/image/tracks`` and ``world/body/static_camera/gimbal_camera/image/tracks``
  (each camera's tracked features, pixels of the distorted image, one row per frame; class ids of
  :data:`~dcc_fg.viz.vio_scene.TRACK_CLASSES`: matched across the cameras or not, rejected by stage two;
  component ``track_id``) and at keyframes ``world/landmarks`` (the window's landmarks in W, m, replacing
  the previous keyframe's; :data:`~dcc_fg.viz.vio_scene.LANDMARK_CLASSES`: seen by the static camera in
  the keyframe, only by the gimbal camera, by neither; component ``track_id``). ``world`` holds the
  ``AnnotationContext`` (label and colour of every class id).

The file is written as ``FILE.rrd.partial`` and renamed when the recording is complete, so an error or
Ctrl-C never leaves a truncated ``FILE.rrd``.
"""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dcc_fg.calibrate import CalibrationResult
from dcc_fg.data import CalibrationDataset
from dcc_fg.data.cameras import RunCamera
from dcc_fg.model import GimbalCalibration
from dcc_fg.vio.backend import VioResult
from dcc_fg.vio.evaluate import GroundTruth
from dcc_fg.vio.pipeline import BagTopics, FrameEvent
from dcc_fg.viz import scene
from dcc_fg.viz.images import DYNAMIC_DIR, STATIC_DIR, ImageSource, calibration_images, jpeg_bytes, topic_images
from dcc_fg.viz.vio_scene import (
    LANDMARK_CLASSES,
    TRACK_CLASSES,
    CameraTracks,
    find_ground_truth,
    frame_tracks,
    further_tracks,
    segment_slices,
    truth_in_estimate_frame,
    window_landmarks,
)
from factors.camera import CameraModel

try:
    import rerun as rr
    import rerun.blueprint as rrb
except ImportError:  # the optional extra dcc-fg[viz] is not installed
    RERUN_AVAILABLE = False
else:
    RERUN_AVAILABLE = True

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)

#: What to install for ``--rerun`` (the message of :class:`RerunUnavailableError`).
INSTALL_HINT = 'pip install dcc-fg[viz] (quoted in zsh: pip install "dcc-fg[viz]"), which installs rerun-sdk'
APPLICATION_ID = "dcc-fg"
#: Colours (RGB): detected corners, reprojected corners, image border, ground truth, estimate.
DETECTED, REPROJECTED, BORDER = (40, 220, 40), (240, 40, 40), (150, 150, 150)
TRUTH, ESTIMATE = (240, 160, 0), (30, 140, 255)
#: JPEG quality of the logged camera images.
JPEG_QUALITY = 85
#: Which camera images a VIO recording holds: those of the keyframes (default), of all frames, none.
VIO_IMAGE_CHOICES = ("keyframes", "all", "none")
#: VIO entities: the two cameras' pinholes (their tracks are ``<camera>/tracks``) and the window's landmarks.
STATIC_IMAGE = "world/body/static_camera/image"
GIMBAL_IMAGE = "world/body/static_camera/gimbal_camera/image"
STATIC_TRACKS, GIMBAL_TRACKS = f"{STATIC_IMAGE}/tracks", f"{GIMBAL_IMAGE}/tracks"
#: Pairing tolerance (ns) when reading a further camera's image back by the static image's stamp: the
#: cameras of a cluster are triggered together (their stamps agree within a few ms).
FURTHER_IMAGE_TOLERANCE_NS = 10_000_000


def further_camera(name: str) -> str:
    """Entity of further camera ``name`` (its pose relative to the static camera, per keyframe)."""
    return f"world/body/static_camera/{name}"


def further_image(name: str) -> str:
    """Entity of further camera ``name``'s image (pinhole, tracks and image)."""
    return f"{further_camera(name)}/image"


LANDMARKS = "world/landmarks"
#: Drawn size (radius, UI points: the same on screen at any zoom) of tracked features and landmarks.
TRACK_RADIUS_UI, LANDMARK_RADIUS_UI = 3.0, 2.0


class RerunUnavailableError(ValueError):
    """``--rerun`` / ``--rerun-spawn`` was asked for but rerun-sdk is not installed (a bad-input error:
    the command line reports it in one line with exit code 2, before any work)."""


@dataclass(frozen=True)
class RerunOptions:
    """Where a run's recording goes: ``path`` a ``.rrd`` file (None: not saved), ``spawn`` also starts
    the Rerun viewer and streams to it; ``vio_images``: which camera images a VIO recording holds
    (``keyframes``, ``all`` frames or ``none``; see :data:`VIO_IMAGE_CHOICES`)."""

    path: Path | None = None
    spawn: bool = False
    vio_images: str = "keyframes"

    @property
    def wanted(self) -> bool:
        return self.path is not None or self.spawn


def viewer_executable() -> str | None:
    """The Rerun viewer that rerun-sdk installs (``rerun`` beside this Python, else on PATH), or None."""
    beside = Path(sys.executable).parent / "rerun"
    return str(beside) if beside.is_file() else shutil.which("rerun")


def require_rerun(options: RerunOptions) -> None:
    """Check a recording request before any work: rerun-sdk installed, ``path`` a ``.rrd`` file name
    that is not a folder, the viewer executable present for ``spawn``.

    Raises:
        RerunUnavailableError: rerun-sdk is missing (the message says what to install).
        ValueError: a path that is not ``*.rrd`` or is an existing folder; no viewer to spawn.
    """
    if not options.wanted:
        return
    if not RERUN_AVAILABLE:
        flag = "--rerun" if options.path is not None else "--rerun-spawn"
        raise RerunUnavailableError(f"{flag} needs the Rerun SDK, which is not installed: {INSTALL_HINT}")
    if options.path is not None:
        if options.path.suffix != ".rrd":
            raise ValueError(f"--rerun {options.path}: the recording file must end in .rrd")
        if options.path.is_dir():
            raise ValueError(f"--rerun {options.path}: is a folder; give a file name ending in .rrd")
    if options.spawn and viewer_executable() is None:
        raise ValueError(f"--rerun-spawn: the Rerun viewer executable 'rerun' is not found beside {sys.executable} "
                         f"or on PATH; {INSTALL_HINT}")  # fmt: skip


def _stream_to_viewer(rec: Any, blueprint: Any) -> bool:
    """Start the viewer and stream ``rec`` to it; False (with a warning) when it does not start: a viewer
    problem never fails the run."""
    try:
        rr.spawn(connect=False, executable_path=viewer_executable(), recording=rec)
        rec.set_sinks(rr.GrpcSink(), default_blueprint=blueprint)
    except RuntimeError as exc:
        log.warning("rerun: the viewer did not start (%s)", exc)
        return False
    return True


def open_in_viewer(path: Path) -> None:
    """Open the written recording ``path`` in a Rerun viewer of its own (detached; a viewer that cannot
    start, e.g. without a display, only logs a warning)."""
    viewer = viewer_executable()
    try:
        if viewer is None:
            raise OSError("no 'rerun' executable")
        subprocess.Popen(  # noqa: S603 - the viewer rerun-sdk installed, on a file this run wrote
            [viewer, str(path)], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            start_new_session=True,
        )  # fmt: skip
        log.info("rerun: opened %s in the viewer", path)
    except OSError as exc:
        log.warning("rerun: the viewer did not start (%s); open the recording with: rerun %s", exc, path)


@contextmanager
def recording(options: RerunOptions, blueprint: Any = None) -> Iterator[Any]:
    """A ``rerun.RecordingStream`` for one run. With ``options.path`` it writes ``PATH.partial``, renamed
    to ``PATH`` when the block ends (removed on an exception), and with ``spawn`` then opens the file in
    the viewer; with ``spawn`` alone it streams to a spawned viewer."""
    require_rerun(options)
    rec = rr.RecordingStream(APPLICATION_ID)
    rr.set_log_time_enabled(False, recording=rec)  # only the run's own timelines, no wall-clock one
    partial = None if options.path is None else options.path.with_name(options.path.name + ".partial")
    if partial is not None:
        partial.parent.mkdir(parents=True, exist_ok=True)
        rec.set_sinks(rr.FileSink(str(partial)), default_blueprint=blueprint)
    elif not _stream_to_viewer(rec, blueprint):
        rec = rr.RecordingStream(APPLICATION_ID, default_enabled=False)  # log into nothing
    try:
        yield rec
        if partial is not None:
            rec.flush()
    except BaseException:
        rec.disconnect()
        if partial is not None:
            partial.unlink(missing_ok=True)
        raise
    if partial is None:
        try:
            rec.flush()
        except RuntimeError as exc:  # the gRPC sink of a viewer that went away
            log.warning("rerun: the viewer did not receive the whole recording (%s)", exc)
    rec.disconnect()
    if partial is not None and options.path is not None:
        os.replace(partial, options.path)
        log.info("rerun: wrote %s", options.path)
        if options.spawn:
            open_in_viewer(options.path)


# ---------------------------------------------------------------------------------------------- helpers


def _time_ns(t_ns: Any) -> Any:
    """Integer ns stamps (one or an array) as numpy datetime64[ns] (Rerun's timestamp timeline)."""
    if np.ndim(t_ns) == 0:
        return np.datetime64(int(t_ns), "ns")
    return np.asarray(t_ns, dtype=np.int64).astype("datetime64[ns]")


def _send_poses(rec: Any, entity: str, indexes: Sequence[Any], T: FloatArray) -> None:
    """One ``Transform3D`` (4x4 ``T``: child -> parent) per row of ``indexes``."""
    T = np.asarray(T, dtype=float)
    rec.send_columns(
        entity, indexes=indexes, columns=rr.Transform3D.columns(translation=T[:, :3, 3], mat3x3=T[:, :3, :3])
    )


def _send_scalars(rec: Any, entity: str, indexes: Sequence[Any], values: FloatArray, name: str) -> None:
    """A named time series: one value per row of ``indexes``."""
    rec.log(entity, rr.SeriesLines(names=name), static=True)
    rec.send_columns(entity, indexes=indexes, columns=rr.Scalars.columns(scalars=np.asarray(values, dtype=float)))


def _log_camera(rec: Any, entity: str, camera: CameraModel | None, plane_distance: float) -> None:
    """The camera's pinhole (``entity``, RDF axes) and its image rectangle as a canvas."""
    if camera is None:
        return
    w, h = camera.resolution
    rec.log(
        entity,
        rr.Pinhole(
            image_from_camera=camera.K,
            resolution=[w, h],
            camera_xyz=rr.ViewCoordinates.RDF,
            image_plane_distance=plane_distance,
        ),
        static=True,
    )
    rec.log(f"{entity}/border", rr.Boxes2D(mins=[0, 0], sizes=[w, h], colors=BORDER), static=True)


def _log_chain_axes(rec: Any, root: str, names: Sequence[str], length: float) -> None:
    """Axes (x red, y green, z blue; ``length`` m) on every chain frame under ``root``."""
    for name in names:
        rec.log(f"{root}/{name}", rr.TransformAxes3D(length, show_frame=True), static=True)


# ---------------------------------------------------------------------------------------------- calibration


def calibration_blueprint(n_joints: int) -> Any:
    """Layout: the 3D scene, both camera images, joint angles and residuals over the snapshots."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(origin="world", name="chain and target (static camera frame)"),
                rrb.Horizontal(
                    rrb.Spatial2DView(origin="world/static_camera/image", name="static camera"),
                    rrb.Spatial2DView(origin="world/gimbal_camera/image", name="gimbal camera"),
                ),
                row_shares=[3, 2],
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(
                    origin="joints",
                    contents=[f"joints/theta_{j + 1}" for j in range(n_joints)],
                    name="joint angles (rad)",
                ),
                rrb.TimeSeriesView(origin="residuals", name="residual RMS per axis (px)"),
            ),
            column_shares=[3, 2],
        )
    )


def _log_calibration_static(rec: Any, result: CalibrationResult, data: CalibrationDataset, length: float) -> None:
    """What does not change over the snapshots: view axes, cameras, target corners, frame axes."""
    rec.log("world", rr.ViewCoordinates.RDF, static=True)
    rec.log("world/static_camera", rr.Transform3D(translation=[0.0, 0.0, 0.0], mat3x3=np.eye(3)), static=True)
    _log_camera(rec, "world/static_camera/image", data.static_camera, 2.0 * length)
    _log_camera(rec, "world/gimbal_camera/image", data.dynamic_camera, 2.0 * length)
    pts = np.asarray(data.target_points, dtype=float)
    rec.log("world/target/corners", rr.Points3D(pts, radii=0.1 * length / 4, colors=(90, 90, 90)), static=True)
    rec.log("world/target/outline", rr.LineStrips3D([scene.target_outline(pts)], colors=(90, 90, 90)), static=True)
    names = list(scene.chain_poses(result.calibration, result.joint_angles[0]))
    _log_chain_axes(rec, "world", names, length)
    rec.log("world/target", rr.TransformAxes3D(length, show_frame=True), static=True)
    for j in range(result.calibration.n_joints):
        rec.log(f"joints/theta_{j + 1}", rr.SeriesLines(names=f"theta_{j + 1} (rad)"), static=True)
        rec.log(f"joints/sigma_{j + 1}", rr.SeriesLines(names=f"theta_{j + 1} 1-sigma (rad)"), static=True)
    rec.log("residuals/static_rms_px", rr.SeriesLines(names="static camera"), static=True)
    rec.log("residuals/gimbal_rms_px", rr.SeriesLines(names="gimbal camera"), static=True)


def _log_snapshot_images(rec: Any, result: CalibrationResult, data: CalibrationDataset, i: int, images: Any) -> None:
    """Corners (and images, where found) of snapshot ``i`` in both cameras."""
    corners = scene.snapshot_corners(data, result, i)
    for (name, cam), c in zip((("static_camera", STATIC_DIR), ("gimbal_camera", DYNAMIC_DIR)), corners, strict=True):
        entity = f"world/{name}/image"
        image = images[cam][i]
        if image is not None:
            rec.log(entity, rr.EncodedImage(contents=jpeg_bytes(image, JPEG_QUALITY), media_type="image/jpeg"))
        labels = [str(int(x)) for x in c.ids]
        for what, uv, color, radius in (
            ("detected", c.detected, DETECTED, 4.0),
            ("reprojected", c.reprojected, REPROJECTED, 2.0),
        ):
            rec.log(f"{entity}/{what}", rr.Points2D(uv, colors=color, radii=radius, labels=labels, show_labels=False))


def _log_snapshot_scene(rec: Any, result: CalibrationResult, i: int, length: float) -> None:
    """Chain frames at snapshot ``i``'s joint angles, the chain polyline, joint axes and the target pose."""
    cal = result.calibration
    poses = scene.chain_poses(cal, result.joint_angles[i])
    for name, T in poses.items():
        if name != "static_camera":
            rec.log(f"world/{name}", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
    rec.log("world/chain", rr.LineStrips3D([np.array([T[:3, 3] for T in poses.values()])], colors=(60, 60, 60)))
    if cal.n_joints:
        axes = scene.joint_axis_segments(cal, result.joint_angles[i], 1.6 * length)
        labels = [f"joint {j + 1}" for j in range(cal.n_joints)]
        rec.log("world/joint_axes", rr.LineStrips3D(list(axes), colors=(0, 0, 0), labels=labels))
    T_st = np.asarray(result.T_st[i], dtype=float)
    rec.log("world/target", rr.Transform3D(translation=T_st[:3, 3], mat3x3=T_st[:3, :3]))


def log_calibration(
    rec: Any, result: CalibrationResult, data: CalibrationDataset, images: dict[str, list[Any]] | None = None
) -> None:
    """Log a calibration or validation ``result`` on ``data`` (module docstring); ``images``: per camera
    the image of each snapshot or None (:func:`dcc_fg.viz.images.calibration_images`)."""
    K = len(data.snapshots)
    images = images or {STATIC_DIR: [None] * K, DYNAMIC_DIR: [None] * K}
    length = scene.axis_length(result)
    _log_calibration_static(rec, result, data, length)
    for i in range(K):
        rec.set_time("snapshot", sequence=i)
        rec.set_time("time", timestamp=_time_ns(int(result.timestamps_ns[i])))
        _log_snapshot_scene(rec, result, i, length)
        _log_snapshot_images(rec, result, data, i, images)
    indexes = [
        rr.TimeColumn("snapshot", sequence=np.arange(K)),
        rr.TimeColumn("time", timestamp=_time_ns(result.timestamps_ns)),
    ]
    for j in range(result.calibration.n_joints):
        values = result.joint_angles[:, j]
        rec.send_columns(f"joints/theta_{j + 1}", indexes=indexes, columns=rr.Scalars.columns(scalars=values))
        sigma = np.asarray(result.joint_angle_std, dtype=float).reshape(K, -1)[:, j]
        rec.send_columns(f"joints/sigma_{j + 1}", indexes=indexes, columns=rr.Scalars.columns(scalars=sigma))
    for name, res in (("static", result.residuals_static), ("gimbal", result.residuals_dynamic)):
        rms = scene.residual_rms(res)
        rec.send_columns(f"residuals/{name}_rms_px", indexes=indexes, columns=rr.Scalars.columns(scalars=rms))


def record_calibration(
    options: RerunOptions, result: CalibrationResult, data: CalibrationDataset, source: ImageSource | None
) -> None:
    """Write (and/or show) the recording of a calibration or validation run; the images come from
    ``source`` (None: corners only)."""
    if not options.wanted:
        return
    images = calibration_images(source, result.timestamps_ns) if source is not None else None
    with recording(options, calibration_blueprint(result.calibration.n_joints)) as rec:
        log_calibration(rec, result, data, images)


# ---------------------------------------------------------------------------------------------- VIO


def vio_blueprint(gimbal: bool = True, further: Sequence[str] = ()) -> Any:
    """Layout: the 3D scene with the trajectory and the landmarks, each camera's tracks (``gimbal``: the
    gimbal camera's too; ``further``: the further cameras of an N-camera run, by name), the joint angles
    and the motion over time; the ``time`` timeline selected and following the newest data (a finished
    recording opens at its last frame, the whole trajectory shown; a streamed one follows the run)."""
    cameras = [rrb.Spatial2DView(origin=STATIC_IMAGE, name="static camera tracks")]
    if gimbal:
        cameras.append(rrb.Spatial2DView(origin=GIMBAL_IMAGE, name="gimbal camera tracks"))
    cameras += [rrb.Spatial2DView(origin=further_image(name), name=f"{name} tracks") for name in further]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(origin="world", name="trajectory and landmarks (world W, gravity -z)"),
                rrb.Horizontal(*cameras),
                row_shares=[3, 2],
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="joints", name="joint angles (rad)"),
                rrb.TimeSeriesView(origin="motion", name="speed (m/s)"),
                rrb.TimeSeriesView(origin="imu", name="IMU biases"),
                rrb.TextLogView(origin="events", name="events"),
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(timeline="time", play_state="following"),
    )


def shows_gimbal(mode: str, cal: GimbalCalibration) -> bool:
    """Whether a VIO recording of ``mode`` on ``cal`` shows the gimbal chain and camera (not ``mono``, a
    chain with joints and a gimbal camera model)."""
    return mode != "mono" and cal.n_joints > 0 and cal.dynamic_camera is not None


def _trajectory_extent(T_WI: FloatArray) -> float:
    """Size (m) of the drawn body axes: a fiftieth of the trajectory's extent, between 5 cm and 1 m."""
    p = np.asarray(T_WI, dtype=float)[:, :3, 3]
    extent = float(np.ptp(p, axis=0).max()) if len(p) > 1 else 1.0
    return float(np.clip(extent / 50.0, 0.05, 1.0))


def _log_vio_chain(rec: Any, result: VioResult, cal: GimbalCalibration, indexes: Sequence[Any], length: float) -> None:
    """The chain frames relative to the static camera at each keyframe's joint angles."""
    if not shows_gimbal(result.mode, cal) or result.theta.size == 0:
        return
    root = "world/body/static_camera"
    per_frame: dict[str, list[FloatArray]] = {}
    for theta in np.asarray(result.theta, dtype=float).reshape(len(result.timestamps_ns), -1):
        for name, T in scene.chain_poses(cal, theta).items():
            per_frame.setdefault(name, []).append(T)
    per_frame.pop("static_camera", None)
    for name, Ts in per_frame.items():
        _send_poses(rec, f"{root}/{name}", indexes, np.asarray(Ts))
    _log_chain_axes(rec, root, list(per_frame), 0.5 * length)
    _log_camera(rec, GIMBAL_IMAGE, cal.dynamic_camera, length)


def _log_vio_truth(rec: Any, result: VioResult, gt: Any, length: float) -> None:
    """Ground truth in the estimate's world (its line, its body frame and joint angles at the keyframes)."""
    try:
        truth = truth_in_estimate_frame(result, gt)
    except ValueError as exc:
        log.warning("rerun: the ground truth is not shown (%s)", exc)
        return
    p = truth.T_WI[:, :3, 3]
    rec.log("world/trajectory/truth", rr.LineStrips3D([p], colors=TRUTH, labels=["ground truth"]), static=True)
    kf = truth.keyframes
    indexes = [
        rr.TimeColumn("keyframe", sequence=kf),
        rr.TimeColumn("time", timestamp=_time_ns(result.timestamps_ns[kf])),
    ]
    _send_poses(rec, "world/truth_body", indexes, truth.T_WI)
    rec.log("world/truth_body", rr.TransformAxes3D(0.7 * length), static=True)
    if truth.theta is not None:
        for j in range(truth.theta.shape[1]):
            _send_scalars(rec, f"joints/truth/theta_{j + 1}", indexes, truth.theta[:, j], f"true theta_{j + 1}")


def _log_further_cameras(
    rec: Any, result: VioResult, cameras: Sequence[RunCamera], indexes: Sequence[Any], length: float
) -> None:
    """Each further camera's pose relative to the static camera (rigid: once; on a chain: per keyframe at
    its chain's estimated angles), its pinhole, and the further chains' joint angles over time."""
    K = len(result.timestamps_ns)
    for c in cameras:
        entity = further_camera(c.name)
        if not c.on_gimbal:
            T_sc = scene.inverse(c.T_cs_at())
            rec.log(entity, rr.Transform3D(translation=T_sc[:3, 3], mat3x3=T_sc[:3, :3]), static=True)
        else:
            theta = result.theta if c.slot == 0 else result.chain_theta.get(str(c.chain))
            if theta is None or np.asarray(theta).size == 0:
                continue
            T = np.array([scene.inverse(c.T_cs_at(th)) for th in np.asarray(theta, float).reshape(K, -1)])
            _send_poses(rec, entity, indexes, T)
        rec.log(entity, rr.TransformAxes3D(0.5 * length, show_frame=True), static=True)
        _log_camera(rec, further_image(c.name), c.model, length)
    for name, theta in result.chain_theta.items():
        for j in range(theta.shape[1]):
            _send_scalars(rec, f"joints/{name}/theta_{j + 1}", indexes, theta[:, j], f"{name} theta_{j + 1}")


def log_vio(
    rec: Any,
    result: VioResult,
    cal: GimbalCalibration,
    T_sI: FloatArray,
    ground_truth: Any = None,
    cameras: Sequence[RunCamera] = (),
) -> None:
    """Log a VIO ``result`` (module docstring); ``T_sI`` the IMU -> static camera mount (4x4);
    ``ground_truth`` a :class:`~dcc_fg.vio.evaluate.GroundTruth` or None; ``cameras`` the further cameras
    of an N-camera run."""
    t = np.asarray(result.timestamps_ns, dtype=np.int64)
    K = len(t)
    length = _trajectory_extent(result.T_WI)
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    indexes = [rr.TimeColumn("keyframe", sequence=np.arange(K)), rr.TimeColumn("time", timestamp=_time_ns(t))]
    _send_poses(rec, "world/body", indexes, result.T_WI)
    rec.log("world/body", rr.TransformAxes3D(length, show_frame=True), static=True)
    T_Is = scene.inverse(T_sI)
    rec.log("world/body/static_camera", rr.Transform3D(translation=T_Is[:3, 3], mat3x3=T_Is[:3, :3]), static=True)
    rec.log("world/body/static_camera", rr.TransformAxes3D(0.5 * length, show_frame=True), static=True)
    _log_camera(rec, STATIC_IMAGE, cal.static_camera, length)
    _log_vio_chain(rec, result, cal, indexes, length)
    _log_further_cameras(rec, result, cameras, indexes, length)
    strips = [result.T_WI[s, :3, 3] for s in segment_slices(result)]
    labels = [f"estimate, segment {k + 1}" for k in range(len(strips))]
    rec.log("world/trajectory/estimate", rr.LineStrips3D(strips, colors=ESTIMATE, labels=labels), static=True)
    theta = np.asarray(result.theta, dtype=float).reshape(K, -1)
    if result.mode != "mono":
        for j in range(theta.shape[1]):
            _send_scalars(rec, f"joints/estimate/theta_{j + 1}", indexes, theta[:, j], f"theta_{j + 1}")
    _send_scalars(rec, "motion/speed_m_s", indexes, np.linalg.norm(result.v_W, axis=1), "speed (m/s)")
    for name, values, unit in (("acc_bias", result.acc_bias, "m/s^2"), ("gyro_bias", result.gyro_bias, "rad/s")):
        for a, axis in enumerate("xyz"):
            _send_scalars(rec, f"imu/{name}/{axis}", indexes, values[:, a], f"{name} {axis} ({unit})")
    for seg in result.stats.get("segments") or []:
        rec.set_time("time", timestamp=_time_ns(int(seg["start_ns"])))
        reason = str(seg.get("reason", ""))
        level = "INFO" if reason == "start" else "WARN"
        rec.log("events", rr.TextLog(f"trajectory segment starts: {reason}", level=level))
    if ground_truth is not None:
        _log_vio_truth(rec, result, ground_truth, length)


class VioRecorder:
    """The recording of a VIO run while it runs: the observer of :func:`~dcc_fg.vio.pipeline.run_vio_bag`
    (called with each frame's :class:`~dcc_fg.vio.pipeline.FrameEvent`), then :meth:`finish` with the
    result (module docstring for what is logged).

    Per frame one ``Points2D`` per camera (an empty one when the camera sees nothing, so a frame never
    shows the previous frame's tracks) and at keyframes one ``Points3D`` of the window's landmarks; the
    ``keyframe`` timeline counts the frames that became keyframes, which are the result's keyframes in
    order. ``gimbal``: log the gimbal camera's tracks (:func:`shows_gimbal`).

    Camera images (``images``, :data:`VIO_IMAGE_CHOICES`): the stamps of the frames to show are kept while
    the run goes (the front end decodes the images in its own process and does not pass them on); after
    the last frame the images with exactly those stamps are read again from ``bag`` (``topics``) and
    logged as JPEG on the frames' ``frame`` / ``time`` (/ ``keyframe``) timelines, under the tracks. With
    ``keyframes`` the image between two keyframes is the last keyframe's while the tracks move on."""

    def __init__(
        self,
        rec: Any,
        cal: GimbalCalibration,
        T_sI: FloatArray,
        gimbal: bool,
        ground_truth: GroundTruth | None,
        images: str = "none",
        bag: Path | None = None,
        topics: BagTopics | None = None,
        cameras: Sequence[RunCamera] = (),
    ) -> None:
        if cal.static_camera is None:
            raise ValueError("the calibration has no static camera model (cam0): the tracks cannot be drawn")
        if images not in VIO_IMAGE_CHOICES:
            raise ValueError(f"images must be one of {', '.join(VIO_IMAGE_CHOICES)}, got {images!r}")
        self.rec, self.cal, self.T_sI, self.ground_truth = rec, cal, np.asarray(T_sI, dtype=float), ground_truth
        self.static_camera = cal.static_camera
        self.dynamic_camera = cal.dynamic_camera if gimbal else None
        self.keyframes = 0  # keyframes so far: the next keyframe's index
        self.images = images if bag is not None and topics is not None else "none"
        self.bag, self.topics = bag, topics
        self.cameras = tuple(cameras)  # further cameras of an N-camera run
        self._further = {c.index: (c.model, c.on_gimbal) for c in self.cameras}
        # frames whose images are shown: (frame index, keyframe index or -1, static stamp, gimbal stamp), ns
        self.shown: list[tuple[int, int, int, int]] = []
        labels = {**TRACK_CLASSES, **LANDMARK_CLASSES}
        infos = [rr.AnnotationInfo(id=c, label=label, color=color) for c, (label, color) in labels.items()]
        rec.log("world", rr.AnnotationContext(infos), static=True)
        size = rr.components.Radius.ui_points
        further = [f"{further_image(c.name)}/tracks" for c in self.cameras]
        for entity in [STATIC_TRACKS] + ([GIMBAL_TRACKS] if gimbal else []) + further:
            rec.log(entity, rr.Points2D.from_fields(radii=size(TRACK_RADIUS_UI), show_labels=False), static=True)
        rec.log(LANDMARKS, rr.Points3D.from_fields(radii=size(LANDMARK_RADIUS_UI), show_labels=False), static=True)

    def __call__(self, event: FrameEvent) -> None:
        """Log ``event``'s tracks (both cameras) and, at a keyframe, the window's landmarks."""
        rec, frame = self.rec, event.frame
        rec.set_time("frame", sequence=int(event.index))
        rec.set_time("time", timestamp=_time_ns(int(frame.timestamp_ns)))
        if event.keyframe:
            rec.set_time("keyframe", sequence=self.keyframes)
            self.keyframes += 1
        else:
            rec.disable_timeline("keyframe")
        if self.images == "all" or (self.images == "keyframes" and event.keyframe):
            gimbal_ns = frame.dynamic_timestamp_ns if frame.dynamic_timestamp_ns is not None else frame.timestamp_ns
            kf = self.keyframes - 1 if event.keyframe else -1
            self.shown.append((int(event.index), kf, int(frame.timestamp_ns), int(gimbal_ns)))
        static, gimbal = frame_tracks(frame, event.rejected_ids, self.static_camera, self.dynamic_camera)
        self._log_tracks(STATIC_TRACKS, static)
        if gimbal is not None:
            self._log_tracks(GIMBAL_TRACKS, gimbal)
        seen = further_tracks(frame, self._further)
        empty = CameraTracks(np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0, np.uint16))
        for c in self.cameras:  # an empty set when the camera has no image this frame
            self._log_tracks(f"{further_image(c.name)}/tracks", seen.get(c.index, empty))
        if event.landmarks is not None:
            lm = window_landmarks(event.landmarks, frame)
            rec.log(LANDMARKS, rr.Points3D(lm.points, class_ids=lm.classes), rr.AnyValues(track_id=lm.ids))

    def _log_tracks(self, entity: str, tracks: CameraTracks) -> None:
        """One camera's tracks of the current frame: pixels, class ids and track ids."""
        self.rec.log(entity, rr.Points2D(tracks.uv, class_ids=tracks.classes), rr.AnyValues(track_id=tracks.ids))

    def finish(self, result: VioResult) -> None:
        """Log the shown frames' camera images, then the run's per-keyframe estimates (:func:`log_vio`),
        after its last frame."""
        self._log_images()
        self.rec.reset_time()
        log_vio(self.rec, result, self.cal, self.T_sI, self.ground_truth, self.cameras)

    def _log_images(self) -> None:
        """The images of the frames in :attr:`shown`, read again from the bag by their exact stamps."""
        if not self.shown or self.bag is None or self.topics is None:
            return
        static = [s for _, _, s, _ in self.shown]
        cameras = [(STATIC_IMAGE, self.topics.static, static, 0)]
        if self.dynamic_camera is not None and self.topics.dynamic is not None:
            cameras.append((GIMBAL_IMAGE, self.topics.dynamic, [g for _, _, _, g in self.shown], 0))
        # further cameras: the image nearest to the static stamp (triggered together)
        cameras += [(further_image(c.name), c.topic, static, FURTHER_IMAGE_TOLERANCE_NS) for c in self.cameras]
        for entity, topic, stamps, tolerance in cameras:
            try:  # exact stamps: a frame without a gimbal partner finds no gimbal image
                found = topic_images(self.bag, topic, np.array(stamps, dtype=np.int64), tolerance)
            except (ValueError, OSError) as exc:  # the bag was read once already: not expected
                log.warning("rerun: the images of %s are not shown (%s); the tracks are", topic, exc)
                continue
            for k, image in enumerate(found):
                if image is None:
                    continue
                index, kf, static_ns, _ = self.shown[k]
                self.rec.set_time("frame", sequence=index)
                self.rec.set_time("time", timestamp=_time_ns(static_ns))
                if kf >= 0:
                    self.rec.set_time("keyframe", sequence=kf)
                else:
                    self.rec.disable_timeline("keyframe")
                self.rec.log(entity, rr.EncodedImage(contents=jpeg_bytes(image, JPEG_QUALITY), media_type="image/jpeg"))


@contextmanager
def vio_recording(
    options: RerunOptions,
    cal: GimbalCalibration,
    T_sI: FloatArray,
    mode: str,
    bag: str | Path,
    ground_truth: str | Path | None = None,
    topics: BagTopics | None = None,
    cameras: Sequence[RunCamera] = (),
) -> Iterator[VioRecorder | None]:
    """The recording of a VIO run (None when ``options`` want none): pass the recorder as the observer of
    :func:`~dcc_fg.vio.pipeline.run_vio_bag`, then call its :meth:`~VioRecorder.finish` with the result
    inside the block; the file is complete when the block ends (:func:`recording`: nothing is left on an
    error). ``T_sI`` the IMU -> static camera mount (4x4); ``mode`` the smoother's; the ground truth is
    ``ground_truth`` (TUM file or bag) or, without it, the bag's own ``/ground_truth/pose`` topic when
    present, read before the run. ``topics``: the bag's image topics, for the camera images
    (``options.vio_images``; None: no images); ``cameras``: the further cameras of an N-camera run
    (:func:`~dcc_fg.data.cameras.run_cameras`), shown like the others."""
    if not options.wanted:
        yield None
        return
    gt = find_ground_truth(bag, ground_truth)
    gimbal = shows_gimbal(mode, cal)
    with recording(options, vio_blueprint(gimbal, [c.name for c in cameras])) as rec:
        yield VioRecorder(rec, cal, T_sI, gimbal, gt, options.vio_images, Path(bag), topics, cameras)
