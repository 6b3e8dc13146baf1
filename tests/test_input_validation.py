"""Input validation at load (issue 13, item 3): every corrupted input file is refused when it is read.

Each case corrupts one field (NaN, inf, zero, negative, wrong length, wrong type, not a rotation...)
or one file (undecodable bytes, malformed YAML, empty, a folder instead of a file) and asserts the
error type and that the message names the file and the field (or line). Through the command line
(``dcc_fg.cli.main``) the exit code is 2 and nothing is written to ``--out``. Exact duplicate
messages in ROS1 / ROS2 bags are dropped once, with one log line per topic. The good inputs (the
simulated files, and the real data in ``../shared/data`` when present) still load.
"""

from __future__ import annotations

import copy
import json
import logging
import math
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from conftest import shared_data

from dcc_fg.cli import main
from dcc_fg.commands.calibrate import CalibrateConfig
from dcc_fg.commands.vio import camchain_T_sI, kalibr_imu_config
from dcc_fg.io.bag_writer import BagWriter, write_ros1_bag, write_ros2_bag
from dcc_fg.io.bags import read_bag_pairs, scan_imu_and_image_stamps
from dcc_fg.io.camchain import load_camchain
from dcc_fg.io.detections import HEADER, read_detection_table
from dcc_fg.io.euroc import read_image_list, read_sensor_yaml, sensor_camera, sensor_T_BS
from dcc_fg.io.folders import FramePair, ImageFolder, read_joints_csv, write_image_folder
from dcc_fg.io.pairing import pair_timestamps
from dcc_fg.io.tum import read_tum
from dcc_fg.model import load_calibration
from dcc_fg.sim.write_dataset import (
    CalibrationSimSpec,
    RenderedCalibration,
    load_ground_truth,
    write_calibration_dataset,
)
from dcc_fg.sources.dataset import load_dataset
from dcc_fg.sources.detections import read_detection_folder
from dcc_fg.sources.eqvio import load_eqvio_csv
from dcc_fg.sources.euroc import load_euroc
from dcc_fg.targets import load_target
from dcc_fg.util.config import ConfigError, load_yaml_config

NAN, INF = math.nan, math.inf
T0 = 1_700_000_000_000_000_000  # ns
PERIOD = 50_000_000  # 20 Hz

CAM0: dict[str, Any] = {
    "camera_model": "pinhole",
    "intrinsics": [460.0, 460.0, 320.5, 240.5],
    "distortion_model": "radtan",
    "distortion_coeffs": [-0.05, 0.01, 0.0005, -0.0003],
    "resolution": [640, 480],
    "rostopic": "/cam0/image_raw",
}
C, S = math.cos(0.1), math.sin(0.1)
T_GOOD = [[C, -S, 0.0, 0.1], [S, C, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
CAMCHAIN: dict[str, Any] = {
    "cam0": copy.deepcopy(CAM0),
    "cam1": {**copy.deepcopy(CAM0), "rostopic": "/cam1/image_raw", "T_cn_cnm1": T_GOOD},
}
CHECKERBOARD = {
    "target_type": "checkerboard",
    "targetCols": 10,
    "targetRows": 7,
    "rowSpacingMeters": 0.06,
    "colSpacingMeters": 0.06,
}
APRILGRID = {"target_type": "aprilgrid", "tagCols": 6, "tagRows": 6, "tagSize": 0.088, "tagSpacing": 0.3}
GIMBAL: dict[str, Any] = {
    "joints": 2,
    "tau_s": [0.1, 0.25, 0.12, -0.06, -0.007, -0.01],
    "tau_d": [-0.18, 0.13, 1.45, 0.06, 0.015, 0.034],
    "dh": [[0.043, -0.01, 1.59], [0.029, 0.032, -1.57]],
}


def _with(base: dict[str, Any], path: tuple[Any, ...], value: Any) -> dict[str, Any]:
    """A deep copy of ``base`` with the entry at ``path`` set to ``value`` (``...`` deletes it)."""
    d = copy.deepcopy(base)
    node: Any = d
    for key in path[:-1]:
        node = node[key]
    if value is ...:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return d


def _write_yaml(path: Path, d: Any) -> Path:
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    return path


def _refused(
    load: Callable[[Path], Any], path: Path, *needles: str, error: type[Exception] = ValueError
) -> pytest.ExceptionInfo[Exception]:
    """``load(path)`` raises ``error`` whose message names the file and contains every needle."""
    with pytest.raises(error) as info:
        load(path)
    msg = str(info.value)
    assert path.name in msg, f"file {path.name} not named in {msg!r}"
    for needle in needles:
        assert needle in msg, f"{needle!r} not in {msg!r}"
    return info


# ---------------------------------------------------------------------------------------------
# Kalibr camchain: every field of every entry
# ---------------------------------------------------------------------------------------------

ROTATION_X2 = [[2.0, 0.0, 0.0, 0.0], [0.0, 2.0, 0.0, 0.0], [0.0, 0.0, 2.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
REFLECTION = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
CAMCHAIN_CASES = [
    ("fu_negative", ("cam1", "intrinsics", 0), -450, "cam1.intrinsics[0] (fu) must be a positive number of pixels"),
    ("fv_zero", ("cam1", "intrinsics", 1), 0, "cam1.intrinsics[1] (fv) must be a positive number of pixels"),
    ("fu_nan", ("cam0", "intrinsics", 0), NAN, "cam0.intrinsics[0] (fu) must be a number, got nan"),
    ("pu_inf", ("cam1", "intrinsics", 2), INF, "cam1.intrinsics[2] (pu) must be a number, got inf"),
    ("pv_text", ("cam1", "intrinsics", 3), "abc", "cam1.intrinsics[3] (pv) must be a number, got 'abc'"),
    ("fu_bool", ("cam1", "intrinsics", 0), True, "cam1.intrinsics[0] (fu) must be a number, got True"),
    ("intrinsics_3", ("cam1", "intrinsics"), [460.0, 460.0, 320.0], "cam1.intrinsics must have 4 entries"),
    ("intrinsics_scalar", ("cam1", "intrinsics"), 460.0, "cam1.intrinsics must be a list [fu, fv, pu, pv]"),
    ("resolution_1", ("cam0", "resolution"), [640], "cam0.resolution must have 2 entries [width, height]"),
    (
        "width_zero",
        ("cam0", "resolution", 0),
        0,
        "cam0.resolution[0] (width) must be a positive integer count of pixels, got 0",
    ),
    ("height_negative", ("cam0", "resolution", 1), -480, "cam0.resolution[1] (height) must be a positive integer"),
    (
        "width_fraction",
        ("cam0", "resolution", 0),
        640.5,
        "cam0.resolution[0] (width) must be a positive integer count of pixels, got 640.5",
    ),
    ("distortion_unknown", ("cam1", "distortion_model"), "fisheye", "cam1.distortion_model must be one of"),
    ("coeff_nan", ("cam1", "distortion_coeffs", 0), NAN, "cam1.distortion_coeffs[0] must be a number, got nan"),
    ("coeff_inf", ("cam0", "distortion_coeffs", 3), -INF, "cam0.distortion_coeffs[3] must be a number, got -inf"),
    ("coeffs_5", ("cam1", "distortion_coeffs"), [0.0] * 5, "cam1.distortion_coeffs must have 4 entries"),
    ("camera_model", ("cam1", "camera_model"), "omni", "cam1.camera_model must be 'pinhole'"),
    ("missing_intrinsics", ("cam1", "intrinsics"), ..., "cam1.intrinsics: missing field"),
    ("rostopic_number", ("cam0", "rostopic"), 5, "cam0.rostopic must be a topic name"),
    ("entry_list", ("cam1",), [1, 2], "cam1 must be a mapping"),
    ("T_scaled", ("cam1", "T_cn_cnm1"), ROTATION_X2, "cam1.T_cn_cnm1: the 3x3 block is not a rotation"),
    ("T_reflection", ("cam1", "T_cn_cnm1"), REFLECTION, "cam1.T_cn_cnm1: the 3x3 block is a reflection"),
    ("T_last_row", ("cam1", "T_cn_cnm1", 3), [0.0, 0.0, 0.0, 2.0], "cam1.T_cn_cnm1: last row must be [0, 0, 0, 1]"),
    ("T_3x4", ("cam1", "T_cn_cnm1"), T_GOOD[:3], "cam1.T_cn_cnm1 must be a 4x4 matrix"),
    ("T_nan", ("cam1", "T_cn_cnm1", 0, 3), NAN, "cam1.T_cn_cnm1[0][3] must be a number, got nan"),
    ("T_cam_imu_scaled", ("cam0", "T_cam_imu"), ROTATION_X2, "cam0.T_cam_imu: the 3x3 block is not a rotation"),
    ("timeshift_nan", ("cam0", "timeshift_cam_imu"), NAN, "cam0.timeshift_cam_imu must be a number"),
]


@pytest.mark.parametrize(
    ("path", "value", "needle"), [c[1:] for c in CAMCHAIN_CASES], ids=[c[0] for c in CAMCHAIN_CASES]
)
def test_camchain_field_refused(tmp_path: Path, path: tuple[Any, ...], value: Any, needle: str) -> None:
    bad = _write_yaml(tmp_path / "camchain_bad.yaml", _with(CAMCHAIN, path, value))
    _refused(load_camchain, bad, needle)


def test_camchain_principal_point_outside_the_image_warns(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = _write_yaml(tmp_path / "camchain_pp.yaml", _with(CAMCHAIN, ("cam1", "intrinsics", 2), 900.0))
    with caplog.at_level(logging.WARNING):
        entries = load_camchain(path)
    assert entries["cam1"].camera.intrinsics[2] == 900.0
    assert "cam1.intrinsics: principal point (900, 240.5) px lies outside the 640x480 image" in caplog.text


# ---------------------------------------------------------------------------------------------
# Kalibr target
# ---------------------------------------------------------------------------------------------

TARGET_CASES = [
    ("cols_zero", CHECKERBOARD, "targetCols", 0, "targetCols must be an integer count of inner corners >= 3, got 0"),
    (
        "cols_negative",
        CHECKERBOARD,
        "targetCols",
        -10,
        "targetCols must be an integer count of inner corners >= 3, got -10",
    ),
    ("rows_two", CHECKERBOARD, "targetRows", 2, "targetRows must be an integer count of inner corners >= 3, got 2"),
    (
        "rows_fraction",
        CHECKERBOARD,
        "targetRows",
        7.5,
        "targetRows must be an integer count of inner corners >= 3, got 7.5",
    ),
    (
        "cols_text",
        CHECKERBOARD,
        "targetCols",
        "ten",
        "targetCols must be an integer count of inner corners >= 3, got 'ten'",
    ),
    ("cols_nan", CHECKERBOARD, "targetCols", NAN, "targetCols must be an integer count of inner corners >= 3, got nan"),
    ("spacing_zero", CHECKERBOARD, "rowSpacingMeters", 0.0, "rowSpacingMeters must be a positive number of metres"),
    ("spacing_negative", CHECKERBOARD, "colSpacingMeters", -0.06, "colSpacingMeters must be a positive number"),
    ("spacing_inf", CHECKERBOARD, "rowSpacingMeters", INF, "rowSpacingMeters must be a positive number of metres"),
    (
        "spacing_nan",
        CHECKERBOARD,
        "colSpacingMeters",
        NAN,
        "colSpacingMeters must be a positive number of metres, got nan",
    ),
    ("spacing_list", CHECKERBOARD, "colSpacingMeters", [0.06], "colSpacingMeters must be a positive number"),
    ("spacing_missing", CHECKERBOARD, "colSpacingMeters", ..., "missing the field 'colSpacingMeters'"),
    ("type_unknown", CHECKERBOARD, "target_type", "circlegrid", "target_type must be 'checkerboard' or 'aprilgrid'"),
    ("tags_zero", APRILGRID, "tagCols", 0, "tagCols must be a positive integer count of tags, got 0"),
    ("tags_bool", APRILGRID, "tagRows", True, "tagRows must be a positive integer count of tags, got True"),
    ("tag_size_zero", APRILGRID, "tagSize", 0.0, "tagSize must be a positive number of metres, got 0"),
    ("tag_size_nan", APRILGRID, "tagSize", NAN, "tagSize must be a positive number of metres, got nan"),
    ("tag_spacing_negative", APRILGRID, "tagSpacing", -0.3, "tagSpacing must be a positive number"),
    ("tag_spacing_inf", APRILGRID, "tagSpacing", INF, "tagSpacing must be a positive number"),
]


@pytest.mark.parametrize(
    ("base", "key", "value", "needle"), [c[1:] for c in TARGET_CASES], ids=[c[0] for c in TARGET_CASES]
)
def test_target_field_refused(tmp_path: Path, base: dict[str, Any], key: str, value: Any, needle: str) -> None:
    bad = _write_yaml(tmp_path / "target_bad.yaml", _with(base, (key,), value))
    _refused(load_target, bad, needle)


def test_target_in_millimetres_warns(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = _write_yaml(tmp_path / "target_mm.yaml", _with(CHECKERBOARD, ("rowSpacingMeters",), 60.0))
    with caplog.at_level(logging.WARNING):
        load_target(path)
    assert "rowSpacingMeters = 60 m" in caplog.text and "millimetres" in caplog.text


# ---------------------------------------------------------------------------------------------
# gimbal.yaml / calibration.yaml
# ---------------------------------------------------------------------------------------------

STD = {"tau_s_std": [0.01] * 6, "tau_d_std": [0.01] * 6, "dh_std": [[0.001, None, 0.01], [0.001, 0.001, None]]}
GIMBAL_CASES = [
    ("joints_negative", ("joints",), -1, "joints must be a non-negative integer count of joints, got -1"),
    ("joints_fraction", ("joints",), 1.5, "joints must be a non-negative integer count of joints, got 1.5"),
    ("joints_text", ("joints",), "two", "joints must be a non-negative integer"),
    ("joints_vs_dh", ("joints",), 3, "dh must have one row [d, a, alpha] per joint (joints = 3), got 2 rows"),
    ("tau_s_5", ("tau_s",), [0.0] * 5, "tau_s must have 6 entries [rx, ry, rz, tx, ty, tz]"),
    ("tau_s_nan", ("tau_s", 3), NAN, "tau_s[3] (tx) must be a number, got nan"),
    ("tau_d_inf", ("tau_d", 0), INF, "tau_d[0] (rx) must be a number, got inf"),
    ("tau_d_text", ("tau_d",), "identity", "tau_d must be a list [rx, ry, rz, tx, ty, tz]"),
    ("dh_row_2", ("dh", 1), [0.0, 0.0], "dh[1] must have 3 entries [d, a, alpha]"),
    ("dh_nan", ("dh", 0, 2), NAN, "dh[0][2] (alpha) must be a number, got nan"),
    ("dh_missing", ("dh",), ..., "missing field 'dh'"),
    ("std_negative", ("tau_s_std", 0), -0.1, "tau_s_std[0] (rx) must be a non-negative number, got -0.1"),
    ("std_nan", ("tau_d_std", 2), NAN, "tau_d_std[2] (rz) must be a non-negative number, got nan"),
    ("std_length", ("dh_std",), [[0.0, 0.0, 0.0]], "dh_std must have one row [d, a, alpha] per joint"),
    ("gauge_unknown", ("gauge_fixed",), ["tau_s.rx", "nonsense"], "gauge_fixed must be a list of parameter names"),
    ("observable_list", ("observable",), [True], "observable must be a mapping"),
    ("cam1_fu", ("cam1",), _with(CAM0, ("intrinsics", 0), -450), "cam1.intrinsics[0] (fu) must be a positive number"),
]


@pytest.mark.parametrize(("path", "value", "needle"), [c[1:] for c in GIMBAL_CASES], ids=[c[0] for c in GIMBAL_CASES])
def test_gimbal_field_refused(tmp_path: Path, path: tuple[Any, ...], value: Any, needle: str) -> None:
    base = {**GIMBAL, **copy.deepcopy(STD)}
    bad = _write_yaml(tmp_path / "gimbal_bad.yaml", _with(base, path, value))
    _refused(load_calibration, bad, needle)


def test_gimbal_angles_in_degrees_warn(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = _write_yaml(tmp_path / "gimbal_deg.yaml", _with(GIMBAL, ("dh", 0, 2), 90.0))
    with caplog.at_level(logging.WARNING):
        load_calibration(path)
    assert "dh[0][2] (alpha) = 90" in caplog.text and "degrees" in caplog.text


# ---------------------------------------------------------------------------------------------
# joints.csv, yac detection files, TUM trajectories: rows with line numbers
# ---------------------------------------------------------------------------------------------

JOINTS_HEADER = "timestamp_ns,theta_1,theta_2\n"
JOINTS_CASES = [
    ("nan", "10,0.1,0.2\n20,nan,0.2\n", "joints.csv:3: theta_1 must be a finite angle in radians, got nan"),
    ("inf", "10,0.1,0.2\n20,0.1,-inf\n", "joints.csv:3: theta_2 must be a finite angle in radians, got -inf"),
    ("degrees", "10,45.0,-30.0\n20,90.0,10.0\n", "joints.csv:2: theta_1 = 45 is beyond one turn"),
    ("text", "10,0.1,0.2\n20,abc,0.2\n", "joints.csv:3: not a number"),
    ("count", "10,0.1,0.2\n20,0.1\n", "joints.csv:3: expected 3 fields"),
    ("decreasing", "20,0.1,0.2\n10,0.1,0.2\n", "joints.csv:3: timestamp_ns 10 does not increase"),
    ("repeated", "10,0.1,0.2\n10,0.3,0.2\n", "joints.csv:3: timestamp_ns 10 does not increase"),
    ("stamp_negative", "-10,0.1,0.2\n", "joints.csv:2: timestamp_ns must be a positive integer"),
    ("stamp_float", "1.5e18,0.1,0.2\n", "joints.csv:2: not a number"),
]


@pytest.mark.parametrize(("body", "needle"), [c[1:] for c in JOINTS_CASES], ids=[c[0] for c in JOINTS_CASES])
def test_joints_csv_refused(tmp_path: Path, body: str, needle: str) -> None:
    path = tmp_path / "joints.csv"
    path.write_text(JOINTS_HEADER + body)
    info = _refused(read_joints_csv, path, needle)
    if "beyond one turn" in needle:
        assert "look like degrees" in str(info.value) and "must be radians" in str(info.value)


GOOD_ROW = "1000,6,6,0.088,0.3,100.5,200.5,0.0,0.0,0.0,0,0"
DETECTION_CASES = [
    ("kp_nan", "1000,6,6,0.088,0.3,nan,200.5,0.0,0.0,0.0,0,1", "csv:3: column kp_x must be a finite number, got nan"),
    ("p_inf", "1000,6,6,0.088,0.3,100.5,200.5,inf,0.0,0.0,0,1", "csv:3: column p_x must be a finite number, got inf"),
    ("columns", "1000,6,6,0.088,0.3,100.5,200.5,0.0,0.0,0,1", "csv:3: expected 12 columns"),
    ("text", "1000,6,6,0.088,0.3,abc,200.5,0.0,0.0,0.0,0,1", "csv:3: column kp_x is not a number: 'abc'"),
    ("tag_id_fraction", "1000,6,6,0.088,0.3,1.0,2.0,0.0,0.0,0.0,1.5,1", "csv:3: column tag_id must be a non-negative"),
    ("tag_id_negative", "1000,6,6,0.088,0.3,1.0,2.0,0.0,0.0,0.0,-1,1", "csv:3: column tag_id must be a non-negative"),
    ("corner_4", "1000,6,6,0.088,0.3,1.0,2.0,0.0,0.0,0.0,0,4", "csv:3: corner_idx must be 0..3, got 4"),
    ("ts_negative", "-1000,6,6,0.088,0.3,1.0,2.0,0.0,0.0,0.0,0,1", "csv:3: column ts must be a positive timestamp"),
]


@pytest.mark.parametrize(("row", "needle"), [c[1:] for c in DETECTION_CASES], ids=[c[0] for c in DETECTION_CASES])
def test_detection_csv_refused(tmp_path: Path, row: str, needle: str) -> None:
    path = tmp_path / "1000.csv"
    path.write_text(f"{HEADER}\n{GOOD_ROW}\n{row}\n")
    _refused(read_detection_table, path, needle)


@pytest.mark.parametrize(
    ("grid", "needle"),
    [
        ("0,6,0.088,0.3", "column tag_rows must be a positive integer count of tags, got 0"),
        ("6,6,0.0,0.3", "column tag_size must be a positive number of metres, got 0"),
        ("6,6,0.088,-0.3", "column tag_spacing must be a positive number"),
    ],
    ids=["tag_rows_zero", "tag_size_zero", "tag_spacing_negative"],
)
def test_detection_grid_refused(tmp_path: Path, grid: str, needle: str) -> None:
    path = tmp_path / "1000.csv"
    path.write_text(f"{HEADER}\n1000,{grid},100.5,200.5,0.0,0.0,0.0,0,0\n")
    _refused(read_detection_table, path, "1000.csv:2: " + needle)


POSE = "0 0 0 0 0 0 1"
TUM_CASES = [
    ("columns", f"1.0 {POSE}\n2.0 0 0 0 0 0 1\n", "traj.tum:2: expected 8 columns"),
    ("nan", f"1.0 {POSE}\n2.0 nan 0 0 0 0 0 1\n", "traj.tum:2: tx must be a finite number"),
    ("inf", f"1.0 {POSE}\n2.0 0 0 0 0 0 inf 1\n", "traj.tum:2: qz must be a finite number"),
    ("decreasing", f"2.0 {POSE}\n1.0 {POSE}\n", "traj.tum:2: timestamp 1.0 s does not increase"),
    ("repeated", f"1.0 {POSE}\n1.0 {POSE}\n", "traj.tum:2: timestamp 1.0 s does not increase"),
    ("zero_quaternion", f"1.0 {POSE}\n2.0 0 0 0 0 0 0 0\n", "traj.tum:2: quaternion qx qy qz qw has norm 0"),
    ("text", f"1.0 {POSE}\n2.0 a 0 0 0 0 0 1\n", "traj.tum:2: not a number"),
    ("no_poses", "# only a comment\n", "traj.tum: no poses"),
]


@pytest.mark.parametrize(("text", "needle"), [c[1:] for c in TUM_CASES], ids=[c[0] for c in TUM_CASES])
def test_tum_refused(tmp_path: Path, text: str, needle: str) -> None:
    path = tmp_path / "traj.tum"
    path.write_text(text)
    _refused(read_tum, path, needle)


# ---------------------------------------------------------------------------------------------
# Files that are not what they should be: undecodable bytes, malformed YAML, empty, a folder
# ---------------------------------------------------------------------------------------------


def _load_config(path: Path) -> Any:
    return load_yaml_config(path, CalibrateConfig, "calibrate")


LOADERS: dict[str, tuple[Callable[[Path], Any], str]] = {
    "camchain": (load_camchain, "camchain.yaml"),
    "target": (load_target, "target.yaml"),
    "gimbal": (load_calibration, "gimbal.yaml"),
    "joints": (read_joints_csv, "joints.csv"),
    "detections": (read_detection_table, "1000.csv"),
    "tum": (read_tum, "traj.tum"),
    "sensor_yaml": (read_sensor_yaml, "sensor.yaml"),
    "config": (_load_config, "config.yaml"),
}
YAML_LOADERS = ("camchain", "target", "gimbal", "sensor_yaml", "config")
FILE_FAULTS = [
    (name, fault)
    for name in LOADERS
    for fault in ("undecodable", "folder", "empty", "malformed_yaml")
    if (fault != "malformed_yaml" or name in YAML_LOADERS) and not (name == "config" and fault == "empty")
]


@pytest.mark.parametrize(("loader", "fault"), FILE_FAULTS, ids=[f"{n}-{f}" for n, f in FILE_FAULTS])
def test_bad_file_named(tmp_path: Path, loader: str, fault: str) -> None:
    load, name = LOADERS[loader]
    path = tmp_path / name
    if fault == "undecodable":
        path.write_bytes(b"a: 1\n\xff\xfe\x00binary")
        needles: tuple[str, ...] = ("not a text file", "UTF-8")
    elif fault == "folder":
        path.mkdir()
        needles = ("is a folder",)
    elif fault == "empty":
        path.write_text("\n")
        needles = ("empty file",)
    else:
        path.write_text("cam0:\n  intrinsics: [1, 2\n  resolution: ]\n")
        needles = ("malformed YAML",)
    info = _refused(load, path, *needles)
    assert "codec can't decode" not in str(info.value)
    if fault == "malformed_yaml" and loader != "config":
        assert f"{name}:3: malformed YAML" in str(info.value)  # the line of the error
    if fault == "undecodable" and loader != "config":
        assert f"{name}:2: not a text file" in str(info.value)


@pytest.mark.parametrize("loader", ["camchain", "target", "gimbal", "joints", "tum"])
def test_missing_file_named(tmp_path: Path, loader: str) -> None:
    load, name = LOADERS[loader]
    _refused(load, tmp_path / name, "not found", error=FileNotFoundError)


def test_config_refuses_non_finite_numbers(tmp_path: Path) -> None:
    path = tmp_path / "config.yaml"
    path.write_text("command: calibrate\nreader:\n  sync_tolerance_ms: .nan\n")
    _refused(_load_config, path, "reader.sync_tolerance_ms: expected a finite number, got nan", error=ConfigError)


# ---------------------------------------------------------------------------------------------
# Through the command line: exit 2, one line naming the culprit, nothing written to --out
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> RenderedCalibration:
    spec = CalibrationSimSpec("checkerboard", "folder", seed=5, n_snapshots=6)
    return write_calibration_dataset(tmp_path_factory.mktemp("rendered"), spec)


def _calibrate_fails(
    r: RenderedCalibration, tmp_path: Path, capsys: pytest.CaptureFixture[str], *needles: str, **files: Any
) -> None:
    args = {"data": r.data, "camchain": r.camchain, "target": r.target, "gimbal": r.gimbal, **files}
    out = tmp_path / "out"
    argv = ["calibrate", str(args.pop("data")), "--out", str(out), "-q"]
    for key, value in args.items():
        argv += [f"--{key.replace('_', '-')}", str(value)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    for needle in needles:
        assert needle in err, f"{needle!r} not in {err!r}"
    assert "Traceback" not in err and "SVD" not in err
    assert not out.exists(), f"{out} was written: {list(out.iterdir())}"


def _bad_yaml(src: Path, dst: Path, path: tuple[Any, ...], value: Any) -> Path:
    return _write_yaml(dst, _with(yaml.safe_load(src.read_text()), path, value))


def test_cli_negative_focal_length(rendered: RenderedCalibration, tmp_path: Path, capsys) -> None:  # noqa: ANN001
    bad = _bad_yaml(rendered.camchain, tmp_path / "cam.yaml", ("cam1", "intrinsics", 0), -450)
    _calibrate_fails(
        rendered, tmp_path, capsys, "cam.yaml: cam1.intrinsics[0] (fu) must be a positive number of pixels, got -450",
        camchain=bad,
    )  # fmt: skip


def test_cli_nan_square_size(rendered: RenderedCalibration, tmp_path: Path, capsys) -> None:  # noqa: ANN001
    bad = _bad_yaml(rendered.target, tmp_path / "target_nan.yaml", ("rowSpacingMeters",), NAN)
    _calibrate_fails(rendered, tmp_path, capsys, "target_nan.yaml: rowSpacingMeters must be a positive", target=bad)


def test_cli_zero_square_size(rendered: RenderedCalibration, tmp_path: Path, capsys) -> None:  # noqa: ANN001
    bad = _bad_yaml(rendered.target, tmp_path / "target_zero.yaml", ("colSpacingMeters",), 0)
    _calibrate_fails(rendered, tmp_path, capsys, "target_zero.yaml: colSpacingMeters", "got 0", target=bad)


def test_cli_undecodable_target(rendered: RenderedCalibration, tmp_path: Path, capsys) -> None:  # noqa: ANN001
    bad = tmp_path / "target_bin.yaml"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\xff")
    _calibrate_fails(rendered, tmp_path, capsys, "target_bin.yaml:1: not a text file", target=bad)


def test_cli_camchain_is_a_folder(rendered: RenderedCalibration, tmp_path: Path, capsys) -> None:  # noqa: ANN001
    folder = tmp_path / "camchain_dir"
    folder.mkdir()
    _calibrate_fails(rendered, tmp_path, capsys, "camchain_dir: is a folder; expected a Kalibr camchain file",
                     camchain=folder)  # fmt: skip


def test_cli_nan_option(rendered: RenderedCalibration, tmp_path: Path, capsys) -> None:  # noqa: ANN001
    _calibrate_fails(rendered, tmp_path, capsys, "sync_tolerance_ms: expected a finite number", sync_tolerance="nan")


def _joints_csv(r: RenderedCalibration, folder: Path, scale: float) -> Path:
    """``folder`` = a copy of the rendered images with a ``joints.csv`` of the true angles times ``scale``."""
    shutil.copytree(r.data, folder)
    truth = load_ground_truth(r.ground_truth)
    pairs = zip(truth.timestamps_ns, truth.theta, strict=True)
    rows = [f"{t}," + ",".join(f"{scale * q:.9f}" for q in theta) for t, theta in pairs]
    (folder / "joints.csv").write_text("timestamp_ns,theta_1,theta_2\n" + "\n".join(rows) + "\n")
    return folder


def test_cli_joints_in_degrees(rendered: RenderedCalibration, tmp_path: Path, capsys) -> None:  # noqa: ANN001
    data = _joints_csv(rendered, tmp_path / "images", 180.0 / math.pi)
    _calibrate_fails(
        rendered, tmp_path, capsys, "joints.csv:2: theta_", "look like degrees", "must be radians", data=data,
        mode="encoders",
    )  # fmt: skip


def test_cli_good_joints_in_radians_run(rendered: RenderedCalibration, tmp_path: Path, capsys) -> None:  # noqa: ANN001
    """The same files with the angles in radians pass every check and calibrate (exit 0), and the
    reader's pairing statistics reach summary.json."""
    data = _joints_csv(rendered, tmp_path / "images", 1.0)
    out = tmp_path / "out"
    argv = ["calibrate", str(data), "--camchain", str(rendered.camchain), "--target", str(rendered.target)]
    assert main([*argv, "--gimbal", str(rendered.gimbal), "--mode", "encoders", "--out", str(out), "-q"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    pairing = summary["input"]["pairing"]
    assert pairing["pairs"] == 6 and pairing["unpaired_static"] == 0 and pairing["gap_max_ms"] <= 5.0
    assert pairing["period_static_ms"] > 0 and pairing["period_dynamic_ms"] == pytest.approx(
        pairing["period_static_ms"]
    )


def test_cli_gimbal_not_finite(rendered: RenderedCalibration, tmp_path: Path, capsys) -> None:  # noqa: ANN001
    bad = _bad_yaml(rendered.gimbal, tmp_path / "gimbal_inf.yaml", ("tau_d", 2), INF)
    _calibrate_fails(rendered, tmp_path, capsys, "gimbal_inf.yaml: tau_d[2] (rz) must be a number, got inf", gimbal=bad)


# ---------------------------------------------------------------------------------------------
# Duplicate messages in bags
# ---------------------------------------------------------------------------------------------


def _board(shift: int) -> np.ndarray:
    """A small 9x6 inner-corner chessboard image shifted by ``shift`` px (distinct images per frame)."""
    img = np.full((180, 240), 255, np.uint8)
    for i in range(-1, 9):
        for j in range(-1, 6):
            if (i + j) % 2 == 0:
                u, v = 30 + shift + i * 16, 30 + shift // 2 + j * 16
                img[v : v + 16, u : u + 16] = 0
    return img


def _frames(n: int) -> list[FramePair]:
    return [
        FramePair(T0 + k * PERIOD, _board(2 * k), _board(3 * k + 1), np.array([0.1 * k, -0.1 * k]),
                  dynamic_timestamp_ns=T0 + k * PERIOD + 1_000_000)
        for k in range(n)
    ]  # fmt: skip


def _bag(kind: str, path: Path, frames: list[FramePair]) -> Path:
    if kind == "ros1":
        return write_ros1_bag(path.with_suffix(".bag"), frames)
    return write_ros2_bag(path, frames)


@pytest.mark.parametrize("kind", ["ros1", "ros2"])
def test_exact_duplicate_messages_dropped(tmp_path: Path, kind: str, caplog: pytest.LogCaptureFixture) -> None:
    src = _frames(4)
    bag = _bag(kind, tmp_path / "dup", [f for f in src for _ in range(2)])  # every message recorded twice
    with caplog.at_level(logging.WARNING):
        pairs = read_bag_pairs(bag, "/cam0/image_raw", "/cam1/image_raw", joint_topic="auto")
        got = list(pairs)
    assert len(pairs) == 4 and not pairs.pairing.unpaired_static and not pairs.pairing.unpaired_dynamic
    for g, s in zip(got, src, strict=True):
        assert g.timestamp_ns == s.timestamp_ns and np.array_equal(g.static, s.static)
        assert np.array_equal(g.dynamic, s.dynamic) and g.joints is not None and np.allclose(g.joints, s.joints)
    lines = [r.getMessage() for r in caplog.records if "exact duplicate" in r.getMessage()]
    for topic in ("/cam0/image_raw", "/cam1/image_raw", "/gimbal/joint_states"):
        mine = [line for line in lines if f"topic {topic}:" in line]
        assert len(mine) == 1 and "dropped 4 exact duplicate messages" in mine[0] and bag.name in mine[0]


@pytest.mark.parametrize("kind", ["ros1", "ros2"])
def test_second_image_with_the_same_stamp_dropped(tmp_path: Path, kind: str, caplog: pytest.LogCaptureFixture) -> None:
    src = _frames(3)
    other = FramePair(
        src[1].timestamp_ns, _board(20), _board(21), src[1].joints, dynamic_timestamp_ns=src[1].dynamic_timestamp_ns
    )
    bag = _bag(kind, tmp_path / "same", [src[0], src[1], other, src[2]])
    with caplog.at_level(logging.WARNING):
        pairs = read_bag_pairs(bag, "/cam0/image_raw", "/cam1/image_raw", joint_topic=None)
        got = list(pairs)
    assert len(got) == 3 and np.array_equal(got[1].static, src[1].static)  # the first one is kept
    assert "topic /cam0/image_raw: 1 images have the header stamp of an earlier, different image" in caplog.text


def test_duplicates_not_counted_twice_by_load_dataset(tmp_path: Path) -> None:
    src = _frames(3)
    bag = _bag("ros2", tmp_path / "dup", [f for f in src for _ in range(3)])
    cam = {**CAM0, "intrinsics": [200.0, 200.0, 120.0, 90.0], "resolution": [240, 180]}
    chain = _write_yaml(tmp_path / "camchain.yaml", {"cam0": cam, "cam1": {**cam, "rostopic": "/cam1/image_raw"}})
    target = _write_yaml(tmp_path / "target.yaml", {**CHECKERBOARD, "targetCols": 9, "targetRows": 6})
    report: dict[str, Any] = {}
    data = load_dataset(bag, chain, target, progress=False, report=report, joint_topic=None)
    assert len(data.snapshots) == 3 and report["pairs"] == 3
    assert report["pairing"]["pairs"] == 3 and report["pairing"]["period_static_ms"] == pytest.approx(50.0)


def test_duplicate_imu_messages_dropped(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "imu.bag"
    with BagWriter(path, ros=1) as bag:
        for k in range(10):
            t = T0 + k * 5_000_000
            for _ in range(2 if k % 3 == 0 else 1):
                bag.imu("/imu0", t, np.array([0.0, 0.0, 9.81]), np.array([0.0, 0.0, 0.01 * k]))
        bag.image("/cam0/image_raw", T0, _board(0), "cam0")
    with caplog.at_level(logging.WARNING):
        scan = scan_imu_and_image_stamps(path, "/imu0", ["/cam0/image_raw"])
    assert scan.imu_t_ns.shape == (10,) and np.all(np.diff(scan.imu_t_ns) > 0)
    assert "topic /imu0: dropped 4 exact duplicate messages" in caplog.text


# ---------------------------------------------------------------------------------------------
# Pairing statistics (for the pairing health check)
# ---------------------------------------------------------------------------------------------


def test_pairing_statistics() -> None:
    s = [T0 + k * PERIOD for k in range(10)]
    d = [t + 2_000_000 for t in s[:8]] + [T0 + 30 * PERIOD]  # 2 static frames unpaired, 1 dynamic
    d[3] += 1_000_000  # one pair 3 ms apart
    stats = pair_timestamps(s, d, 5_000_000).statistics()
    assert stats["pairs"] == 8 and stats["unpaired_static"] == 2 and stats["unpaired_dynamic"] == 1
    assert stats["gap_median_ms"] == pytest.approx(2.0) and stats["gap_max_ms"] == pytest.approx(3.0)
    assert stats["gap_median_signed_ms"] == pytest.approx(2.0) and stats["tolerance_ms"] == 5.0
    assert stats["period_static_ms"] == pytest.approx(50.0) and stats["period_dynamic_ms"] == pytest.approx(50.0)
    empty = pair_timestamps([T0], [], 5_000_000).statistics()
    assert empty["pairs"] == 0 and empty["gap_median_ms"] is None and empty["period_static_ms"] is None


# ---------------------------------------------------------------------------------------------
# Good inputs still load
# ---------------------------------------------------------------------------------------------


def test_simulated_files_still_load(rendered: RenderedCalibration) -> None:
    chain = load_camchain(rendered.camchain)
    assert set(chain) == {"cam0", "cam1"}
    assert load_target(rendered.target).target_type == "checkerboard"
    assert load_calibration(rendered.gimbal).n_joints == 2
    assert load_ground_truth(rendered.ground_truth).kinematics.n_joints == 2


def test_camchain_with_all_fields_round_trips(tmp_path: Path) -> None:
    path = _write_yaml(tmp_path / "camchain.yaml", _with(CAMCHAIN, ("cam0", "T_cam_imu"), T_GOOD))
    entries = load_camchain(path)
    assert entries["cam1"].extra["T_cn_cnm1"] == T_GOOD and entries["cam0"].rostopic == "/cam0/image_raw"
    tgt = _write_yaml(tmp_path / "target.yaml", {**APRILGRID, "tagSize": "8.8e-2"})  # YAML 1.1 reads it as text
    assert load_target(tgt).tag_size == pytest.approx(0.088)


def test_real_data_still_loads() -> None:
    root = shared_data("")
    tum = root / "euroc_v1_01_gt/V1_01_easy_original.txt"
    t, T = read_tum(tum)
    assert t.size > 20_000 and np.allclose(np.linalg.det(T[:, :3, :3]), 1.0)
    ds = load_euroc(root / "euroc_v1_01_micro/MicroEurocDataset")
    assert ds.cam0.resolution == (752, 480) and len(ds.images0) > 50
    snaps, target, pairing = read_detection_folder(root / "euroc_aprilgrid/calib/cam_april")
    assert len(snaps) == 30 and target.tag_size == pytest.approx(0.088)
    assert pairing.statistics()["period_static_ms"] == pytest.approx(50.0, abs=0.1)


def test_gtsam_eqvio_file_still_loads() -> None:
    data = load_eqvio_csv()
    assert len(data.frames) > 100 and data.imu.t_ns.size > 1000


# ---------------------------------------------------------------------------------------------
# ASL / EuRoC folders: sensor.yaml fields and image lists
# ---------------------------------------------------------------------------------------------

SENSOR: dict[str, Any] = {
    "sensor_type": "camera",
    "T_BS": {"cols": 4, "rows": 4, "data": [1.0, 0, 0, 0.1, 0, 1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0]},
    "rate_hz": 20,
    "resolution": [752, 480],
    "camera_model": "pinhole",
    "intrinsics": [458.654, 457.296, 367.215, 248.375],
    "distortion_model": "radial-tangential",
    "distortion_coefficients": [-0.28, 0.07, 0.0002, 1.8e-05],
}
SENSOR_CASES = [
    ("T_BS_15", ("T_BS", "data"), [1.0] * 15, "T_BS.data must be the 16 entries of a 4x4 matrix"),
    ("T_BS_scaled", ("T_BS", "data", 0), 3.0, "T_BS: the 3x3 block is not a rotation"),
    ("T_BS_nan", ("T_BS", "data", 3), NAN, "T_BS[0][3] must be a number, got nan"),
    ("fu_negative", ("intrinsics", 0), -458.0, "intrinsics[0] (fu) must be a positive number of pixels"),
    ("distortion_unknown", ("distortion_model",), "fov", "distortion_model must be one of"),
    ("coeff_inf", ("distortion_coefficients", 1), INF, "distortion_coeffs[1] must be a number, got inf"),
    ("resolution_1", ("resolution",), [752], "resolution must have 2 entries"),
]


def _load_sensor(path: Path) -> Any:
    d = read_sensor_yaml(path)
    return sensor_T_BS(d, path), sensor_camera(d, path)


@pytest.mark.parametrize(("path", "value", "needle"), [c[1:] for c in SENSOR_CASES], ids=[c[0] for c in SENSOR_CASES])
def test_asl_sensor_yaml_refused(tmp_path: Path, path: tuple[Any, ...], value: Any, needle: str) -> None:
    bad = tmp_path / "sensor.yaml"
    bad.write_text("%YAML:1.0\n" + yaml.safe_dump(_with(SENSOR, path, value), sort_keys=False))
    _refused(_load_sensor, bad, needle)


def test_asl_sensor_yaml_good_and_malformed_line(tmp_path: Path) -> None:
    good = tmp_path / "sensor.yaml"
    good.write_text("%YAML:1.0\n" + yaml.safe_dump(SENSOR, sort_keys=False))
    T, cam = _load_sensor(good)
    assert T[0, 3] == 0.1 and cam.distortion_model == "radtan"
    good.write_text("%YAML:1.0\nrate_hz: 20\nresolution: [752, 480\n")
    _refused(read_sensor_yaml, good, "sensor.yaml:3: malformed YAML")  # the file's own line numbers


@pytest.mark.parametrize(
    ("rows", "needle"),
    [
        ("100,a.png\n100,b.png\n", "data.csv:3: timestamp 100 is listed twice (also line 2)"),
        ("1.5e9,a.png\n", "data.csv:2: timestamp must be an integer in ns, got '1.5e9'"),
        ("-100,a.png\n", "data.csv:2: timestamp must be a positive integer in ns"),
    ],
    ids=["repeated", "float", "negative"],
)
def test_asl_image_list_refused(tmp_path: Path, rows: str, needle: str) -> None:
    (tmp_path / "data").mkdir()
    (tmp_path / "data.csv").write_text("#timestamp [ns],filename\n" + rows)
    with pytest.raises(ValueError) as info:
        read_image_list(tmp_path)
    assert needle in str(info.value) and str(tmp_path / "data.csv") in str(info.value)


def test_joints_csv_that_is_a_folder_is_refused_not_ignored(tmp_path: Path) -> None:
    root = write_image_folder(tmp_path / "images", _frames(2))
    (root / "joints.csv").unlink(missing_ok=True)
    (root / "joints.csv").mkdir()
    with pytest.raises(ValueError, match=r"joints.csv: is a folder; expected a joints.csv file"):
        ImageFolder(root)


@pytest.mark.parametrize(
    ("which", "line", "needle"),
    [
        ("ground_truth", "3.0 0 nan 0 0 0 0 1", "gt.tum:5: ty must be a finite number"),
        ("ground_truth", "1.5 0 0 0 0 0 0 1", "gt.tum:5: timestamp 1.5 s does not increase"),
        ("trajectory", "3.0 0 0 0 0 0 1", "trajectory.tum:5: expected 8 columns"),
    ],
    ids=["gt_nan", "gt_not_increasing", "estimate_columns"],
)
def test_cli_evaluate_refuses_bad_trajectories(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    which: str,
    line: str,
    needle: str,
) -> None:
    poses = "".join(f"{k}.0 {0.1 * k} 0 0 0 0 0 1\n" for k in range(3))
    run = tmp_path / "run"
    run.mkdir()
    gt = tmp_path / "gt.tum"
    (run / "trajectory.tum").write_text(
        "# t tx ty tz qx qy qz qw\n" + poses + (line + "\n" if which == "trajectory" else "")
    )
    gt.write_text("# t tx ty tz qx qy qz qw\n" + poses + (line + "\n" if which == "ground_truth" else ""))
    before = sorted(p.name for p in run.iterdir())
    assert main(["evaluate", str(run), "--ground-truth", str(gt)]) == 2
    err = capsys.readouterr().err
    assert needle in err and "Traceback" not in err
    assert sorted(p.name for p in run.iterdir()) == before  # no evaluation.json, no figures


# ------------------------------------------------------------------ simulate flags, Kalibr IMU files of vio


@pytest.mark.parametrize(
    "argv, culprit",
    [
        (["calibration", "--snapshots", "-1"], "--snapshots"),
        (["calibration", "--snapshots", "0"], "--snapshots"),
        (["calibration", "--noise", "nan"], "--noise"),
        (["calibration", "--blur", "-2"], "--blur"),
        (["flight", "--duration", "inf"], "--duration"),
        (["flight", "--duration", "0"], "--duration"),
        (["flight", "--scale", "-1"], "--scale"),
    ],
)
def test_simulate_refuses_bad_numbers_before_any_work(tmp_path, capsys, argv, culprit):
    out = tmp_path / "sim"
    with pytest.raises(SystemExit) as exc:
        main(["simulate", argv[0], "--out", str(out), *argv[1:]])
    assert exc.value.code == 2
    assert culprit in capsys.readouterr().err
    assert not out.exists()


def test_vio_kalibr_imu_files_are_checked(tmp_path):
    bad_bytes = tmp_path / "imu.yaml"
    bad_bytes.write_bytes(b"accelerometer_noise_density: \xff\xfe\n")
    with pytest.raises(ValueError, match=r"imu.yaml:1: not a text file"):
        kalibr_imu_config(bad_bytes, np.eye(4))
    negative = tmp_path / "imu_neg.yaml"
    negative.write_text(
        "imu0:\n  accelerometer_noise_density: -0.01\n  accelerometer_random_walk: 0.0002\n"
        "  gyroscope_noise_density: 0.0002\n  gyroscope_random_walk: 4.0e-06\n"
    )
    with pytest.raises(ValueError, match=r"imu_neg.yaml: imu0.accelerometer_noise_density must be a positive"):
        kalibr_imu_config(negative, np.eye(4))
    camchain = tmp_path / "camchain-imucam.yaml"
    camchain.write_text("cam0:\n  T_cam_imu: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 2, 0], [0, 0, 0, 1]]\n")
    with pytest.raises(ValueError, match=r"camchain-imucam.yaml: cam0.T_cam_imu: the 3x3 block is not a rotation"):
        camchain_T_sI(camchain)
