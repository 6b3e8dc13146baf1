"""``--rerun FILE.rrd`` on calibrate, validate and vio (issue 17, item 2): the recording is read back with
Rerun's own reader (``rerun.chunk.RrdReader``, rerun-sdk 0.41) and checked against the run's output files
(entity paths, one row per snapshot / keyframe, joint angles, poses, residuals) and, for the VIO's tracks and
landmarks, against the pipeline's own frame events (one row per processed frame, pixels = the camera model's
projection of the tracked normalized coordinates, match and rejection classes, the window's landmarks);
without rerun-sdk the flag is refused before any work with what to install.

Small inputs keep it fast (~20 s): a rendered 12-snapshot checkerboard set (image folder and ROS2 bag) and
a rendered 8 s flight at half resolution.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pyarrow as pa
import pytest

import dcc_fg.commands.vio as vio_command
import dcc_fg.viz.rerun_log as rerun_log
from dcc_fg import load_calibration
from dcc_fg.calibrate import CalibrationOptions, calibrate
from dcc_fg.cli import main
from dcc_fg.data.vio import TrackFrame
from dcc_fg.io.outputs import read_joint_angles_csv
from dcc_fg.io.tum import read_tum
from dcc_fg.sim.calibration_scene import SceneConfig, simulate_calibration
from dcc_fg.sim.flight_bag import FlightBag, write_flight
from dcc_fg.sim.trajectory import FlightConfig
from dcc_fg.sim.write_dataset import CalibrationSimSpec, RenderedCalibration, write_calibration_dataset
from dcc_fg.vio.backend import VioResult
from dcc_fg.vio.evaluate import GroundTruth
from dcc_fg.vio.pipeline import FrameEvent, run_vio_bag
from dcc_fg.viz import scene
from dcc_fg.viz import vio_scene as vs
from dcc_fg.viz.images import display_image, topic_images
from dcc_fg.viz.vio_scene import segment_slices, truth_in_estimate_frame
from factors import chain
from factors.camera import CameraModel

try:
    from rerun.chunk import RrdReader
except ImportError:
    RrdReader = None

needs_rerun = pytest.mark.skipif(
    not rerun_log.RERUN_AVAILABLE or RrdReader is None,
    reason="rerun-sdk (with rerun.chunk.RrdReader, >= 0.41) is not installed: pip install dcc-fg[viz]",
)

CALIBRATION_ENTITIES = {
    "/world",
    "/world/static_camera",
    "/world/gimbal_base",
    "/world/link_1",
    "/world/end_effector",
    "/world/gimbal_camera",
    "/world/chain",
    "/world/joint_axes",
    "/world/target",
    "/world/target/corners",
    "/world/static_camera/image",
    "/world/static_camera/image/detected",
    "/world/static_camera/image/reprojected",
    "/world/static_camera/image/border",
    "/world/gimbal_camera/image",
    "/world/gimbal_camera/image/detected",
    "/world/gimbal_camera/image/reprojected",
    "/joints/theta_1",
    "/joints/theta_2",
    "/joints/sigma_1",
    "/residuals/static_rms_px",
    "/residuals/gimbal_rms_px",
}


# ---------------------------------------------------------------------------------------------- reading a recording


def _column(batch: pa.RecordBatch, name: str) -> list[Any]:
    """A column as Python values; timestamps as integer ns (to_pylist would round them to microseconds)."""
    col = batch.column(name)
    if pa.types.is_timestamp(col.type):
        col = col.cast(pa.int64())
    return col.to_pylist()


def load_rrd(path: Path) -> dict[str, dict[str, Any]]:
    """``{entity path: {"static": {column: value}, "rows": [{column: value}, ...] sorted by time}}``."""
    out: dict[str, dict[str, Any]] = {}
    for chunk in RrdReader(path).stream():  # type: ignore[misc]
        batch = chunk.to_record_batch()
        entry = out.setdefault(chunk.entity_path, {"static": {}, "rows": []})
        names = [n for n in batch.schema.names if not n.startswith("rerun.")]
        cols = {n: _column(batch, n) for n in names}
        for r in range(batch.num_rows):
            row = {n: cols[n][r] for n in names}
            if chunk.is_static:
                entry["static"].update(row)
            else:
                entry["rows"].append(row)
    for entry in out.values():
        key = "snapshot" if any("snapshot" in r for r in entry["rows"]) else "time"
        entry["rows"].sort(key=lambda r: (r.get(key) is None, r.get(key)))
    return out


def scalars(rec: dict[str, dict[str, Any]], entity: str) -> np.ndarray:
    return np.array([r["Scalars:scalars"][0] for r in rec[entity]["rows"]])


def pose(row: dict[str, Any]) -> np.ndarray:
    """The 4x4 of a logged Transform3D row (Rerun stores mat3x3 column-major, in float32)."""
    T = np.eye(4)
    T[:3, :3] = np.array(row["Transform3D:mat3x3"][0]).reshape(3, 3).T
    T[:3, 3] = row["Transform3D:translation"][0]
    return T


# ---------------------------------------------------------------------------------------------- calibration


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> RenderedCalibration:
    spec = CalibrationSimSpec("checkerboard", "folder", seed=5, n_snapshots=12)
    return write_calibration_dataset(tmp_path_factory.mktemp("rendered"), spec)


def _calibrate_argv(r: RenderedCalibration, data: Path, out: Path) -> list[str]:
    files = ["--camchain", str(r.camchain), "--target", str(r.target), "--gimbal", str(r.gimbal)]
    return ["calibrate", str(data), *files, "--out", str(out), "-q"]


@pytest.fixture(scope="module")
def calibrated(rendered: RenderedCalibration, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    root = tmp_path_factory.mktemp("calibrated")
    rrd = root / "rec" / "calibration.rrd"  # the folder is created
    assert main([*_calibrate_argv(rendered, rendered.data, root / "cal"), "--rerun", str(rrd)]) == 0
    return {"out": root / "cal", "rrd": rrd, "rec": load_rrd(rrd)}


@needs_rerun
def test_calibration_recording_matches_the_outputs(calibrated: dict[str, Any]) -> None:
    rec, out = calibrated["rec"], calibrated["out"]
    assert CALIBRATION_ENTITIES <= set(rec), sorted(CALIBRATION_ENTITIES - set(rec))
    assert not calibrated["rrd"].with_name("calibration.rrd.partial").exists()
    t_ns, theta = read_joint_angles_csv(out / "joint_angles.csv")
    K = len(t_ns)
    assert K == 12
    for j in range(2):
        rows = rec[f"/joints/theta_{j + 1}"]["rows"]
        assert [r["snapshot"] for r in rows] == list(range(K))
        assert [r["time"] for r in rows] == [int(x) for x in t_ns]
        np.testing.assert_allclose(scalars(rec, f"/joints/theta_{j + 1}"), theta[:, j], atol=1e-9)
    # every snapshot's images (the image folder has them) and corners; chain frames at the estimated angles
    for name in ("static_camera", "gimbal_camera"):
        rows = rec[f"/world/{name}/image"]["rows"]
        assert [r["snapshot"] for r in rows] == list(range(K))
        jpeg = np.frombuffer(bytes(rows[4]["EncodedImage:blob"][0]), dtype=np.uint8)
        assert cv2.imdecode(jpeg, cv2.IMREAD_UNCHANGED).shape[:2] == (480, 640)
        assert rec[f"/world/{name}/image"]["static"]["Pinhole:resolution"] == [[640.0, 480.0]]
        assert len(rec[f"/world/{name}/image/detected"]["rows"]) == K
    cal = load_calibration(out / "calibration.yaml")
    for i in (0, 5, K - 1):
        T_sd = chain.inv_se3(cal.T_ds(theta[i]))
        np.testing.assert_allclose(pose(rec["/world/gimbal_camera"]["rows"][i]), T_sd, atol=2e-6)
    # the residual RMS per snapshot pools to the run's own statistics (summary.json)
    summary = json.loads((out / "summary.json").read_text())["reprojection_error_px"]
    for name, cam in (("static", "static_camera"), ("gimbal", "gimbal_camera")):
        n = np.array([len(r["Points2D:positions"]) for r in rec[f"/world/{cam}/image/detected"]["rows"]])
        rms = scalars(rec, f"/residuals/{name}_rms_px")
        pooled = float(np.sqrt(np.sum(n * rms**2) / np.sum(n)))
        expected = summary["static" if name == "static" else "dynamic"]["rms_per_axis"]
        assert pooled == pytest.approx(expected, rel=1e-6)
        # the drawn reprojections are the model's: their distance to the detections is the residual
        row_d = rec[f"/world/{cam}/image/detected"]["rows"][3]["Points2D:positions"]
        row_r = rec[f"/world/{cam}/image/reprojected"]["rows"][3]["Points2D:positions"]
        diff = np.array(row_r) - np.array(row_d)
        assert float(np.sqrt(np.mean(diff**2))) == pytest.approx(rms[3], rel=1e-3, abs=1e-4)


@needs_rerun
def test_validation_recording(rendered: RenderedCalibration, calibrated: dict[str, Any], tmp_path: Path) -> None:
    rrd = tmp_path / "validation.rrd"
    argv = ["validate", str(rendered.data), "--calibration", str(calibrated["out"] / "calibration.yaml")]
    argv += ["--target", str(rendered.target), "--out", str(tmp_path / "val"), "-q"]
    assert main([*argv, "--rerun", str(rrd)]) == 0
    rec = load_rrd(rrd)
    t_ns, theta = read_joint_angles_csv(tmp_path / "val" / "joint_angles.csv")
    assert CALIBRATION_ENTITIES <= set(rec)
    np.testing.assert_allclose(scalars(rec, "/joints/theta_2"), theta[:, 1], atol=1e-9)
    assert len(rec["/world/gimbal_camera/image"]["rows"]) == len(t_ns)


@needs_rerun
def test_calibration_from_a_bag_shows_its_images(tmp_path: Path) -> None:
    """A ROS2 bag: the images are decoded again from the camchain's topics."""
    r = write_calibration_dataset(tmp_path / "sim", CalibrationSimSpec("checkerboard", "ros2", seed=3, n_snapshots=8))
    rrd = tmp_path / "bag.rrd"
    assert main([*_calibrate_argv(r, r.data, tmp_path / "cal"), "--rerun", str(rrd)]) == 0
    rec = load_rrd(rrd)
    t_ns, _ = read_joint_angles_csv(tmp_path / "cal" / "joint_angles.csv")
    for name in ("static_camera", "gimbal_camera"):
        rows = rec[f"/world/{name}/image"]["rows"]
        assert [r["time"] for r in rows] == [int(x) for x in t_ns]


def test_reprojected_corners_are_the_residuals() -> None:
    """scene.snapshot_corners reproduces the calibration's own residuals h(x) - z, corner by corner."""
    sim = simulate_calibration(1, SceneConfig(n_calibration=6, n_validation=1))
    result = calibrate(sim.calibration_set, sim.initial, CalibrationOptions())
    for i in (0, 3):
        static, gimbal = scene.snapshot_corners(sim.calibration_set, result, i)
        np.testing.assert_allclose(static.reprojected - static.detected, result.residuals_static[i], atol=1e-6)
        np.testing.assert_allclose(gimbal.reprojected - gimbal.detected, result.residuals_dynamic[i], atol=1e-6)
    names = list(scene.chain_poses(result.calibration, result.joint_angles[0]))
    assert names == ["static_camera", "gimbal_base", "link_1", "end_effector", "gimbal_camera"]


# ---------------------------------------------------------------------------------------------- VIO


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> FlightBag:
    return write_flight(tmp_path_factory.mktemp("flight") / "f", "ros2", FlightConfig.short(8.0), seed=0, scale=0.5)


def _collect_events(monkeypatch: pytest.MonkeyPatch, events: list[FrameEvent]) -> list[Any]:
    """Make ``dcc-fg vio`` keep the frame events its observer sees; returns the observers it passed."""
    observers: list[Any] = []

    def run_and_collect(*args: Any, observer: Any = None, **kwargs: Any) -> Any:
        observers.append(observer)

        def both(event: FrameEvent) -> None:
            events.append(event)
            if observer is not None:
                observer(event)

        return run_vio_bag(*args, observer=both, **kwargs)

    monkeypatch.setattr(vio_command, "run_vio_bag", run_and_collect)
    return observers


@needs_rerun
def test_vio_recording_matches_the_outputs(flight: FlightBag, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    rrd, out = tmp_path / "vio.rrd", tmp_path / "run"
    argv = ["vio", str(flight.bag), "--calibration", str(flight.calibration), "--out", str(out), "-q"]
    events: list[FrameEvent] = []
    observers = _collect_events(monkeypatch, events)
    assert main([*argv, "--frontend", "inline", "--rerun", str(rrd)]) == 0
    assert isinstance(observers[0], rerun_log.VioRecorder)
    rec = load_rrd(rrd)
    expected = {
        "/" + rerun_log.STATIC_TRACKS,
        "/" + rerun_log.GIMBAL_TRACKS,
        "/" + rerun_log.LANDMARKS,
        "/world",
        "/world/body",
        "/world/body/static_camera",
        "/world/body/static_camera/image",
        "/world/body/static_camera/gimbal_camera",
        "/world/body/static_camera/gimbal_base",
        "/world/trajectory/estimate",
        "/world/trajectory/truth",  # the simulated bag carries /ground_truth/pose
        "/world/truth_body",
        "/joints/estimate/theta_1",
        "/joints/estimate/theta_2",
        "/joints/truth/theta_1",
        "/motion/speed_m_s",
        "/imu/acc_bias/x",
        "/imu/gyro_bias/z",
        "/events",
    }
    assert expected <= set(rec), sorted(expected - set(rec))
    t_tum, T_tum = read_tum(out / "trajectory.tum")
    K = len(t_tum)
    body = rec["/world/body"]["rows"]
    assert len(body) == K and [r["keyframe"] for r in body] == list(range(K))
    assert [r["time"] for r in body] == [int(x) for x in t_tum]
    for k in (0, K // 2, K - 1):
        np.testing.assert_allclose(pose(body[k]), T_tum[k], atol=1e-5)
    t_j, theta = read_joint_angles_csv(out / "joint_angles.csv")
    np.testing.assert_array_equal(t_j, t_tum)
    for j in range(2):
        np.testing.assert_allclose(scalars(rec, f"/joints/estimate/theta_{j + 1}"), theta[:, j], atol=1e-9)
        truth = rec[f"/joints/truth/theta_{j + 1}"]["rows"]
        kf = [r["keyframe"] for r in truth]
        err = scalars(rec, f"/joints/truth/theta_{j + 1}") - theta[kf, j]
        assert len(kf) >= K - 2 and np.sqrt(np.mean(err**2)) < 1e-2  # the estimate follows the truth
    gimbal = rec["/world/body/static_camera/gimbal_camera"]["rows"]
    assert len(gimbal) == K
    _check_keyframe_images(rec, flight, t_tum)
    # the truth, brought into the estimate's world, lies along the estimate (a healthy run: < 1 % of 40 m)
    truth_p = np.array(rec["/world/trajectory/truth"]["static"]["LineStrips3D:strips"][0])
    est_p = np.concatenate([np.array(s) for s in rec["/world/trajectory/estimate"]["static"]["LineStrips3D:strips"]])
    assert np.abs(truth_p[0] - est_p[0]).max() < 0.5 and len(truth_p) >= K - 2
    _check_tracks_and_landmarks(rec, events, out, flight, t_tum)


def _check_keyframe_images(rec: dict[str, dict[str, Any]], flight: FlightBag, t_kf: np.ndarray) -> None:
    """Both cameras' images at every keyframe (the default ``--rerun-images keyframes``), on the keyframe
    timeline, equal (up to JPEG) to the bag's image with the keyframe's stamp."""
    for entity, topic in ((rerun_log.STATIC_IMAGE, "/cam0/image_raw"), (rerun_log.GIMBAL_IMAGE, "/cam1/image_raw")):
        rows = [r for r in rec["/" + entity]["rows"] if r.get("EncodedImage:blob") is not None]
        assert [r["keyframe"] for r in rows] == list(range(len(t_kf)))
        assert [r["time"] for r in rows] == [int(x) for x in t_kf]
        k = len(rows) // 2
        shown = cv2.imdecode(np.frombuffer(bytes(rows[k]["EncodedImage:blob"][0]), np.uint8), cv2.IMREAD_UNCHANGED)
        original, following = topic_images(flight.bag, topic, np.array([int(t_kf[k]), int(t_kf[k + 1])]), 0)
        assert original is not None and following is not None and shown.shape[:2] == original.shape[:2]
        err = [np.mean(np.abs(shown.astype(float) - display_image(im).astype(float))) for im in (original, following)]
        assert err[0] < 4.0 and err[0] < 0.5 * err[1], err  # its own frame up to JPEG, not the next keyframe's


def test_vio_recording_of_every_frame_image(flight: FlightBag, tmp_path: Path) -> None:
    """``--rerun-images all``: one image per processed frame and camera; ``none``: no image."""
    base = ["vio", str(flight.bag), "--calibration", str(flight.calibration), "-q", "--frontend", "inline"]
    counts = {}
    for choice in ("all", "none"):
        rrd, out = tmp_path / f"{choice}.rrd", tmp_path / choice
        assert main([*base, "--out", str(out), "--rerun", str(rrd), "--rerun-images", choice]) == 0
        rec = load_rrd(rrd)
        frames = json.loads((out / "summary.json").read_text())["frames"]
        counts[choice] = [
            sum(r.get("EncodedImage:blob") is not None for r in rec.get("/" + e, {}).get("rows", []))
            for e in (rerun_log.STATIC_IMAGE, rerun_log.GIMBAL_IMAGE)
        ]
        static_frames = [r["frame"] for r in rec["/" + rerun_log.STATIC_TRACKS]["rows"]]
        if choice == "all":
            rows = [r for r in rec["/" + rerun_log.STATIC_IMAGE]["rows"] if r.get("EncodedImage:blob") is not None]
            assert [r["frame"] for r in rows] == static_frames
    assert counts["all"] == [frames, frames] and counts["none"] == [0, 0]


def _check_tracks_and_landmarks(
    rec: dict[str, dict[str, Any]], events: list[FrameEvent], out: Path, flight: FlightBag, t_kf: np.ndarray
) -> None:
    """One row of tracks per processed frame in each camera, in pixels of the camera model, classed by match
    and rejection; the window's landmarks at every keyframe, on the keyframe timeline of the result."""
    summary = json.loads((out / "summary.json").read_text())
    rows = {
        cam: rec["/" + entity]["rows"]
        for cam, entity in (("s", rerun_log.STATIC_TRACKS), ("d", rerun_log.GIMBAL_TRACKS))
    }
    n = summary["frames"]
    assert len(events) == n and len(rows["s"]) == n and len(rows["d"]) == n
    assert [r["frame"] for r in rows["s"]] == [e.index for e in events] == [r["frame"] for r in rows["d"]]
    assert [r["time"] for r in rows["s"]] == [e.frame.timestamp_ns for e in events]
    keyframe_rows = [r for r in rows["s"] if r.get("keyframe") is not None]
    assert [r["keyframe"] for r in keyframe_rows] == list(range(len(t_kf)))
    assert [r["time"] for r in keyframe_rows] == [int(x) for x in t_kf]  # the keyframes of trajectory.tum
    cal = load_calibration(flight.calibration)
    cameras = {"s": cal.static_camera, "d": cal.dynamic_camera}
    rejected = 0
    for i, (e, rs, rd) in enumerate(zip(events, rows["s"], rows["d"], strict=True)):
        ids = {"s": e.frame.static_ids, "d": e.frame.dynamic_ids}
        xy = {"s": e.frame.static_xy, "d": e.frame.dynamic_xy}
        for cam, row in (("s", rs), ("d", rd)):
            assert row["track_id"] == ids[cam].tolist()
            uv = np.array(row["Points2D:positions"]).reshape(-1, 2)
            w, h = cameras[cam].resolution
            assert np.all((uv >= 0) & (uv <= [w - 1, h - 1]))  # inside the image
            if i in (0, n // 2, n - 1):  # the camera model's projection of the normalized coordinates
                expected_uv, _ = cameras[cam].project(np.column_stack([xy[cam], np.ones(len(xy[cam]))]))
                np.testing.assert_allclose(uv, expected_uv, atol=1e-3)  # stored as float32
        matched_s = np.isin(ids["s"], ids["d"])
        assert rs["Points2D:class_ids"] == np.where(matched_s, vs.STATIC_MATCHED, vs.STATIC_ONLY).tolist()
        classes_d = np.where(np.isin(ids["d"], ids["s"]), vs.GIMBAL_MATCHED, vs.GIMBAL_ONLY)
        is_rejected = np.isin(ids["d"], e.rejected_ids)
        classes_d[is_rejected] = vs.GIMBAL_REJECTED
        assert rd["Points2D:class_ids"] == classes_d.tolist()
        assert e.keyframe or not len(e.rejected_ids)  # stage two runs at keyframes
        rejected += int(is_rejected.sum())
    assert np.mean([np.isin(e.frame.static_ids, e.frame.dynamic_ids).any() for e in events]) > 0.9
    assert rejected >= summary["run"]["dynamic_tracks_rejected"] > 0  # the run's count of stage-two drops
    # the window's landmarks: one set per keyframe (replacing the previous), in W, classed by who sees them
    landmarks = rec["/" + rerun_log.LANDMARKS]["rows"]
    kf_events = [e for e in events if e.keyframe]
    assert [r["keyframe"] for r in landmarks] == list(range(len(t_kf))) and len(kf_events) == len(t_kf)
    for row, e in zip(landmarks, kf_events, strict=True):
        assert e.landmarks is not None and row["track_id"] == list(e.landmarks)
        p = np.array(row["Points3D:positions"]).reshape(-1, 3)
        np.testing.assert_allclose(p, np.array(list(e.landmarks.values())).reshape(-1, 3), rtol=1e-6, atol=1e-4)
        seen_s = np.isin(row["track_id"], e.frame.static_ids)
        assert np.all((np.array(row["Points3D:class_ids"]) == vs.LANDMARK_STATIC) == seen_s)
    # the first keyframes have no triangulated landmarks yet (a track needs 3 keyframes)
    assert np.median([len(r["track_id"]) for r in landmarks]) >= 10
    classes = np.concatenate([r["Points3D:class_ids"] for r in landmarks])
    assert {vs.LANDMARK_STATIC, vs.LANDMARK_UNSEEN} <= set(classes.tolist())
    # every class has its label and colour in the annotation context on world (rejected: red)
    infos = {
        c["class_id"]: c["class_description"]["info"] for c in rec["/world"]["static"]["AnnotationContext:context"][0]
    }
    assert {c: info["label"] for c, info in infos.items()} == {
        c: label for c, (label, _) in {**vs.TRACK_CLASSES, **vs.LANDMARK_CLASSES}.items()
    }
    assert infos[vs.GIMBAL_REJECTED]["color"] >> 8 == 0xF02828  # RGBA packed


def test_vio_without_a_recording_passes_no_observer(
    flight: FlightBag, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Without --rerun the pipeline gets no observer (and pays nothing for one)."""
    observers: list[Any] = []

    class Stop(Exception):
        pass

    def stop(*args: Any, observer: Any = None, **kwargs: Any) -> Any:
        observers.append(observer)
        raise Stop

    monkeypatch.setattr(vio_command, "run_vio_bag", stop)
    inputs = vio_command.VioInputs(str(flight.bag), str(flight.calibration))
    with pytest.raises(Stop):
        vio_command.run_vio(inputs, tmp_path / "run", vio_command.VioConfig(), quiet=True)
    assert observers == [None]


def test_frame_tracks_and_window_landmarks_classes() -> None:
    """Matched = the id in both cameras' lists, rejected overrides matched; pixels through the distortion;
    landmarks seen by the static camera, else only by the gimbal camera, else by neither; empty frames."""
    camera = CameraModel((400.0, 410.0, 320.0, 240.0), "radtan", (-0.2, 0.05, 1e-3, -1e-3))
    xy = np.array([[0.1, -0.2], [0.0, 0.0], [-0.3, 0.25]])
    frame = TrackFrame(10, np.array([1, 2, 3]), xy, np.array([2, 3, 7]), xy[::-1].copy())
    static, gimbal = vs.frame_tracks(frame, np.array([3, 99]), camera, camera)
    assert static.classes.tolist() == [vs.STATIC_ONLY, vs.STATIC_MATCHED, vs.STATIC_MATCHED]
    assert gimbal is not None and gimbal.ids.tolist() == [2, 3, 7]
    assert gimbal.classes.tolist() == [vs.GIMBAL_MATCHED, vs.GIMBAL_REJECTED, vs.GIMBAL_ONLY]
    fx, fy, cx, cy = camera.intrinsics
    xd, _ = camera.distort(xy)
    np.testing.assert_allclose(static.uv, np.column_stack([fx * xd[:, 0] + cx, fy * xd[:, 1] + cy]), atol=1e-12)
    np.testing.assert_allclose(static.uv[1], [cx, cy])
    assert vs.frame_tracks(frame, np.zeros(0, np.int64), camera, None)[1] is None  # mono: no gimbal camera
    empty = TrackFrame(11, np.zeros(0, np.int64), np.zeros((0, 2)))
    s0, d0 = vs.frame_tracks(empty, np.zeros(0, np.int64), camera, camera)
    assert s0.uv.shape == (0, 2) and d0 is not None and d0.uv.shape == (0, 2) and d0.classes.shape == (0,)
    lms = vs.window_landmarks({2: np.zeros(3), 7: np.ones(3), 50: np.full(3, 2.0)}, frame)
    assert lms.ids.tolist() == [2, 7, 50] and lms.points.shape == (3, 3)
    assert lms.classes.tolist() == [vs.LANDMARK_STATIC, vs.LANDMARK_GIMBAL_ONLY, vs.LANDMARK_UNSEEN]
    assert vs.window_landmarks({}, frame).points.shape == (0, 3)


def _truth_case(mode: str, scale: float) -> tuple[VioResult, GroundTruth, np.ndarray]:
    rng = np.random.default_rng(1)
    n = 30
    t = 1_000_000_000 + np.arange(n, dtype=np.int64) * 50_000_000
    T = np.repeat(np.eye(4)[None], n, axis=0)
    T[:, :3, 3] = np.cumsum(rng.normal(size=(n, 3)), axis=0)
    for k in range(n):
        T[k, :3, :3] = chain.rot_z(0.1 * k) @ chain.rot_x(0.05 * k)
    S = chain.se3_from_tau(np.array([0.1, -0.2, 0.7, 3.0, -1.0, 2.0]))
    gt_T = np.einsum("ij,njk->nik", S, T)
    gt_T[:, :3, 3] = scale * (T[:, :3, 3] @ S[:3, :3].T) + S[:3, 3]
    theta = np.zeros((n, 0))
    zeros = np.zeros((n, 3))
    result = VioResult(t, T, zeros, zeros, zeros, theta, mode, {"segments": [{"start_ns": int(t[0])}]})
    return result, GroundTruth(t, gt_T), T


@pytest.mark.parametrize(("mode", "scale"), [("dcc", 1.0), ("mono", 2.5)])
def test_truth_is_brought_into_the_estimate_frame(mode: str, scale: float) -> None:
    result, gt, T = _truth_case(mode, scale)
    truth = truth_in_estimate_frame(result, gt)
    assert truth.alignment == ("sim3" if mode == "mono" else "se3") and truth.scale == pytest.approx(scale)
    np.testing.assert_allclose(truth.T_WI, T[truth.keyframes], atol=1e-8)


def test_segment_slices() -> None:
    result, _, _ = _truth_case("dcc", 1.0)
    assert segment_slices(result) == [slice(0, 30)]
    result.stats["segments"] = [{"start_ns": int(result.timestamps_ns[0])}, {"start_ns": int(result.timestamps_ns[12])}]
    assert segment_slices(result) == [slice(0, 12), slice(12, 30)]


# ---------------------------------------------------------------------------------------------- refusals


def test_missing_rerun_is_refused_before_any_work(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Without rerun-sdk, --rerun / --rerun-spawn fail first (the inputs do not even exist) and say what to
    install; nothing is written."""
    monkeypatch.setattr(rerun_log, "RERUN_AVAILABLE", False)
    out = tmp_path / "out"
    missing = str(tmp_path / "missing")
    cases = [
        ["calibrate", missing, "--joints", "2", "--out", str(out), "--rerun", str(tmp_path / "a.rrd")],
        ["validate", missing, "--calibration", missing, "--out", str(out), "--rerun-spawn"],
        ["vio", missing, "--calibration", missing, "--out", str(out), "--rerun", str(tmp_path / "a.rrd")],
    ]
    for argv in cases:
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "pip install dcc-fg[viz]" in err and "not installed" in err, err
        assert "missing" not in err  # refused before the inputs were looked at
    assert not out.exists() and not (tmp_path / "a.rrd").exists()


def test_without_rerun_sdk_installed(tmp_path: Path) -> None:
    """With rerun not importable at all, dcc_fg imports, records the absence and refuses --rerun."""
    code = (
        "import sys; sys.modules['rerun'] = None; sys.modules['rerun.blueprint'] = None\n"
        "import dcc_fg.viz.rerun_log as r; from dcc_fg.cli import main\n"
        f"rc = main(['calibrate', {str(tmp_path / 'missing')!r}, '--joints', '2', '--rerun', 'a.rrd'])\n"
        "print('available', r.RERUN_AVAILABLE, 'rc', rc)\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert "available False rc 2" in proc.stdout, proc.stdout + proc.stderr
    assert "pip install dcc-fg[viz]" in proc.stderr


@needs_rerun
def test_bad_recording_requests(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = str(tmp_path / "missing")
    assert main(["calibrate", missing, "--joints", "2", "--out", str(tmp_path / "o"), "--rerun", "rec.txt"]) == 2
    assert "must end in .rrd" in capsys.readouterr().err
    (tmp_path / "dir.rrd").mkdir()
    assert main(["calibrate", missing, "--joints", "2", "--rerun", str(tmp_path / "dir.rrd")]) == 2
    assert "is a folder" in capsys.readouterr().err
    argv = ["vio", missing, "--calibration", missing, "--out", str(tmp_path / "o"), "--rerun-ground-truth", missing]
    assert main(argv) == 2
    assert "--rerun-ground-truth" in capsys.readouterr().err
