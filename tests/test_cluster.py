"""N-camera clusters (dcc_fg.cluster): the cameras:/chains: form of gimbal.yaml / calibration.yaml.

* two-camera files load and mean what they meant: ``T_cs('cam1', theta) == T_ds(theta)`` to the bit,
  and they save unchanged;
* cluster files (static stereo + gimbal camera, two cameras on one chain, two chains): ``T_cs`` equals
  transforms composed by hand here and :mod:`factors.chain`; save/load round trips to the bit;
* every validation error names the file and the field;
* a Kalibr camchain becomes a cluster with ``T_cn_cnm1`` chained from cam0;
* code that handles two cameras only (``dcc-fg vio``, Kalibr export, the calibration) refuses an
  N-camera file with a message naming the file, or uses cam0/cam1 of it where that is all it needs.
"""

from __future__ import annotations

import copy
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from dcc_fg.calibrate import calibrate
from dcc_fg.cli import main
from dcc_fg.cluster import CameraCluster, CameraMount, ChainSpec, cluster_from_camchain
from dcc_fg.data.vio import ImuConfig
from dcc_fg.io.camchain import camchain_transforms, load_camchain
from dcc_fg.model import GimbalCalibration, load_calibration
from dcc_fg.sim.calibration_scene import random_mechanism
from factors import chain
from factors.camera import CameraModel

CAM: dict[str, Any] = {
    "camera_model": "pinhole",
    "intrinsics": [460.0, 461.0, 320.5, 240.5],
    "distortion_model": "radtan",
    "distortion_coeffs": [-0.05, 0.01, 0.0005, -0.0003],
    "resolution": [640, 480],
}
GIMBAL: dict[str, Any] = {  # the two-camera fixture of tests/test_input_validation.py
    "joints": 2,
    "tau_s": [0.1, 0.25, 0.12, -0.06, -0.007, -0.01],
    "tau_d": [-0.18, 0.13, 1.45, 0.06, 0.015, 0.034],
    "dh": [[0.043, -0.01, 1.59], [0.029, 0.032, -1.57]],
}
TAU_D2 = [0.05, -0.1, -1.5, -0.04, 0.01, 0.02]


# ------------------------------------------------------------------------------------ hand-made math


def _rot(axis: str, a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    R = {"x": [[1, 0, 0], [0, c, -s], [0, s, c]], "y": [[c, 0, s], [0, 1, 0], [-s, 0, c]],
         "z": [[c, -s, 0], [s, c, 0], [0, 0, 1]]}[axis]  # fmt: skip
    T = np.eye(4)
    T[:3, :3] = R
    return T


def _trans(x: float, y: float, z: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [x, y, z]
    return T


def _se3(tau: list[float]) -> np.ndarray:
    """tau = [rx, ry, rz, tx, ty, tz] -> T, R = Rz Ry Rx."""
    return _trans(*tau[3:]) @ _rot("z", tau[2]) @ _rot("y", tau[1]) @ _rot("x", tau[0])


def _by_hand(tau_d: list[float], dh: list[list[float]], tau_s: list[float], theta: np.ndarray) -> np.ndarray:
    """T_cs = T_de inv(A_1 ... A_L) T_bs with A_l = Rz(theta_l) Tz(d_l) Tx(a_l) Rx(alpha_l)."""
    T_be = np.eye(4)
    for (d, a, alpha), th in zip(dh, theta, strict=True):
        T_be = T_be @ _rot("z", th) @ _trans(0, 0, d) @ _trans(a, 0, 0) @ _rot("x", alpha)
    return _se3(tau_d) @ np.linalg.inv(T_be) @ _se3(tau_s)


def _rigid(rng: np.random.Generator) -> np.ndarray:
    return chain.se3_from_tau(np.concatenate([rng.uniform(-math.pi, math.pi, 3), rng.uniform(-0.3, 0.3, 3)]))


def _matrix(T: np.ndarray) -> list[list[float]]:
    return [[float(x) for x in row] for row in T]


def _write(path: Path, d: dict[str, Any]) -> Path:
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    return path


# ------------------------------------------------------------------------------- example clusters

T_C1S = chain.se3_from_tau(np.array([0.01, -0.02, 0.015, -0.12, 0.002, -0.001]))  # a stereo partner, 12 cm


def stereo_plus_gimbal() -> dict[str, Any]:
    """Static stereo pair cam0/cam1 and a 2-DOF gimbal camera cam2."""
    return {
        "cameras": {
            "cam0": {"mount": "static", **CAM, "rostopic": "/cam0/image_raw"},
            "cam1": {"mount": "static", "T_cs": _matrix(T_C1S), **CAM},
            "cam2": {"mount": "gimbal", "tau_d": GIMBAL["tau_d"], **CAM},
        },
        "chains": {"gimbal": {"joints": 2, "tau_s": GIMBAL["tau_s"], "dh": GIMBAL["dh"]}},
    }


def two_on_one_chain() -> dict[str, Any]:
    """A 2-DOF gimbal carrying cam1 and cam2."""
    return {
        "cameras": {
            "cam0": {"mount": "static"},
            "cam1": {"mount": "pan_tilt", "tau_d": GIMBAL["tau_d"]},
            "cam2": {"mount": "pan_tilt", "tau_d": TAU_D2},
        },
        "chains": {"pan_tilt": {"joints": 2, "tau_s": GIMBAL["tau_s"], "dh": GIMBAL["dh"]}},
    }


def two_chains() -> dict[str, Any]:
    """cam1 on a 2-DOF gimbal, cam2 static, cam3 on a 1-DOF chain (chains in file order: gimbal, roll)."""
    return {
        "cameras": {
            "cam0": {"mount": "static"},
            "cam1": {"mount": "gimbal", "tau_d": GIMBAL["tau_d"]},
            "cam2": {"mount": "static", "T_cs": _matrix(T_C1S)},
            "cam3": {"mount": "roll", "tau_d": TAU_D2},
        },
        "chains": {
            "gimbal": {"joints": 2, "tau_s": GIMBAL["tau_s"], "dh": GIMBAL["dh"]},
            "roll": {"joints": 1, "tau_s": [0.0, 0.3, -0.2, 0.1, -0.05, 0.02], "dh": [[0.02, 0.01, 0.4]]},
        },
    }


# ------------------------------------------------------------------------ two-camera files: unchanged


def _calibrate_style(seed: int, n_joints: int) -> GimbalCalibration:
    """A calibration.yaml as dcc-fg calibrate writes it: stds (null where unobservable), observability,
    gauge, held directions, intrinsics, statistics."""
    cal, _ = random_mechanism(np.random.default_rng(seed), n_joints)
    n = chain.n_kin(n_joints)
    std = np.abs(np.random.default_rng(seed).normal(0.01, 0.003, n))
    std[[2, n - 1]] = np.nan
    cal.kin_std = std
    cal.observable = np.isfinite(std)
    cal.gauge_fixed = ~np.isfinite(std)
    cal.held_by_prior = [{"parameters": ["dh1.d"], "direction": [1.0], "held_at": [0.0], "prior_sigma": 1.0}]
    cal.static_camera = CameraModel((450.0, 451.0, 320.0, 240.0), "radtan", (0.1, -0.01, 0.001, 0.0), (640, 480))
    cal.dynamic_camera = CameraModel((500.0, 499.0, 330.0, 250.0), "equidistant", (0.1, 0.0, 0.0, 0.01), (752, 480))
    cal.statistics = {"reprojection_error_px": {"rms": 0.31}, "snapshots": 40}
    return cal


@pytest.mark.parametrize("n_joints", [0, 1, 2, 3])
def test_two_camera_files_load_and_mean_the_same(tmp_path: Path, n_joints: int) -> None:
    cal = _calibrate_style(n_joints, n_joints)
    path = tmp_path / "calibration.yaml"
    d = cal.to_dict()
    d["imu"] = ImuConfig().to_dict()  # a flight's calibration.yaml: other sections are left alone
    _write(path, d)
    back = load_calibration(path)
    assert back.layout is None and back.is_two_camera and back.camera_names == ["cam0", "cam1"]
    assert back.source == str(path) and back.require_two_cameras("VIO") is back
    assert "cameras" not in back.to_dict() and back.to_dict() == cal.to_dict()  # saves unchanged
    rng = np.random.default_rng(n_joints)
    for theta in rng.uniform(-math.pi, math.pi, size=(20, n_joints)):
        T = back.T_cs("cam1", theta)
        assert np.array_equal(T, back.T_ds(theta))  # bit for bit
        assert np.array_equal(T, cal.T_ds(theta))
        np.testing.assert_allclose(T, _by_hand(list(back.tau_d), back.dh.tolist(), list(back.tau_s), theta), atol=1e-12)
        assert np.array_equal(back.T_cs("cam0", theta), np.eye(4))
    assert np.array_equal(back.T_cs("cam0"), np.eye(4))
    # the cluster view: cam0 static reference, cam1 on chain "gimbal", the stds carried along
    cl = back.cluster()
    assert cl.camera_names == ["cam0", "cam1"] and cl.chain_names == ["gimbal"] and cl.joint_count == n_joints
    assert cl.camera("cam0").camera == cal.static_camera and cl.camera("cam1").camera == cal.dynamic_camera
    assert cl.chain("gimbal").tau_s_std is not None and np.isnan(cl.chain("gimbal").tau_s_std[2])
    assert cl.primary_gimbal_camera == "cam1" and cl.is_two_camera


def test_the_minimal_gimbal_yaml_and_the_validation_fixture(tmp_path: Path) -> None:
    """The gimbal.yaml of the README / tests/test_input_validation.py, with and without intrinsics."""
    for extra in ({}, {"cam0": CAM, "cam1": CAM}):
        path = _write(tmp_path / "gimbal.yaml", {**GIMBAL, **extra})
        cal = load_calibration(path)
        assert cal.to_dict() == {**GIMBAL, **extra}
        theta = np.array([0.3, -1.1])
        assert np.array_equal(cal.T_cs("cam1", theta), cal.T_ds(theta))
        assert np.array_equal(cal.T_cs("cam1", {"gimbal": theta}), cal.T_ds(theta))
        np.testing.assert_allclose(cal.T_ds(theta), _by_hand(GIMBAL["tau_d"], GIMBAL["dh"], GIMBAL["tau_s"], theta),
                                   atol=1e-12)  # fmt: skip
        with pytest.raises(KeyError, match="no camera 'cam2'"):
            cal.T_cs("cam2", theta)


# ---------------------------------------------------------------------------------- cluster files


def test_static_stereo_plus_gimbal_camera(tmp_path: Path) -> None:
    path = _write(tmp_path / "cluster.yaml", stereo_plus_gimbal())
    cal = load_calibration(path)
    assert cal.camera_names == ["cam0", "cam1", "cam2"] and not cal.is_two_camera
    cl = cal.cluster()
    assert cl.static_cameras == ["cam0", "cam1"] and cl.cameras_on("gimbal") == ["cam2"]
    assert cl.camera("cam0").rostopic == "/cam0/image_raw" and cl.camera("cam2").camera == cal.dynamic_camera
    rng = np.random.default_rng(1)
    for theta in rng.uniform(-math.pi, math.pi, size=(10, 2)):
        assert np.array_equal(cal.T_cs("cam1", theta), T_C1S) and np.array_equal(cal.T_cs("cam1"), T_C1S)
        T = cal.T_cs("cam2", theta)
        np.testing.assert_allclose(T, _by_hand(GIMBAL["tau_d"], GIMBAL["dh"], GIMBAL["tau_s"], theta), atol=1e-12)
        assert np.array_equal(T, cal.T_ds(theta))  # the primary pair: cam0 and the first chain camera, cam2
        assert np.array_equal(T, chain.T_ds(cl.kin_of("cam2"), theta, 2))
        # the stereo partner sees the gimbal camera at T_c2c1 = T_c2s inv(T_c1s)
        np.testing.assert_allclose(T @ np.linalg.inv(T_C1S) @ T_C1S, T, atol=1e-12)
    assert cl.primary_gimbal_camera == "cam2"


def test_two_cameras_on_one_chain(tmp_path: Path) -> None:
    cal = load_calibration(_write(tmp_path / "cluster.yaml", two_on_one_chain()))
    cl = cal.cluster()
    assert cl.cameras_on("pan_tilt") == ["cam1", "cam2"] and cl.joint_count == 2
    rng = np.random.default_rng(2)
    T_21 = None
    for theta in rng.uniform(-math.pi, math.pi, size=(10, 2)):
        T1, T2 = cal.T_cs("cam1", theta), cal.T_cs("cam2", {"pan_tilt": theta})
        np.testing.assert_allclose(T1, _by_hand(GIMBAL["tau_d"], GIMBAL["dh"], GIMBAL["tau_s"], theta), atol=1e-12)
        np.testing.assert_allclose(T2, _by_hand(TAU_D2, GIMBAL["dh"], GIMBAL["tau_s"], theta), atol=1e-12)
        # both ride on the end effector: their relative pose is T_c2e inv(T_c1e), whatever theta
        rel = T2 @ chain.inv_se3(T1)
        np.testing.assert_allclose(rel, _se3(TAU_D2) @ np.linalg.inv(_se3(GIMBAL["tau_d"])), atol=1e-12)
        T_21 = rel if T_21 is None else T_21
        np.testing.assert_allclose(rel, T_21, atol=1e-12)
        # factors.chain: the same points through transform_points
        p_s = rng.normal(size=(5, 3))
        p_d, _ = chain.transform_points(cl.kin_of("cam2"), theta, p_s, 2, jacobians=False)
        np.testing.assert_allclose(p_d, p_s @ T2[:3, :3].T + T2[:3, 3], atol=1e-12)


def test_two_chains_and_the_flat_joint_vector(tmp_path: Path) -> None:
    d = two_chains()
    cal = load_calibration(_write(tmp_path / "cluster.yaml", d))
    cl = cal.cluster()
    assert cl.chain_names == ["gimbal", "roll"] and cl.joint_count == 3
    assert cl.joint_slices() == {"gimbal": slice(0, 2), "roll": slice(2, 3)}
    roll = d["chains"]["roll"]
    rng = np.random.default_rng(3)
    for flat in rng.uniform(-math.pi, math.pi, size=(10, 3)):
        split = cl.split_theta(flat)
        assert np.array_equal(split["gimbal"], flat[:2]) and np.array_equal(split["roll"], flat[2:])
        T1, T3 = cal.T_cs("cam1", flat), cal.T_cs("cam3", flat)
        assert np.array_equal(T1, cal.T_cs("cam1", {"gimbal": flat[:2]}))
        assert np.array_equal(T3, cal.T_cs("cam3", {"roll": flat[2:], "gimbal": flat[:2]}))
        assert np.array_equal(T3, cal.T_cs("cam3", {"roll": float(flat[2])}))
        np.testing.assert_allclose(T1, _by_hand(GIMBAL["tau_d"], GIMBAL["dh"], GIMBAL["tau_s"], flat[:2]), atol=1e-12)
        np.testing.assert_allclose(T3, _by_hand(TAU_D2, roll["dh"], roll["tau_s"], flat[2:]), atol=1e-12)
        assert np.array_equal(T1, cal.T_ds(flat[:2]))
        assert np.array_equal(cal.T_cs("cam2", flat), T_C1S)
    with pytest.raises(ValueError, match=r"3 joint angles \(chains in order: gimbal \(2\), roll \(1\)\)"):
        cal.T_cs("cam3", [0.1, 0.2])
    with pytest.raises(ValueError, match="no joint angles for chain 'roll'"):
        cal.T_cs("cam3", {"gimbal": [0.1, 0.2]})
    with pytest.raises(ValueError, match=r"theta\['gimbal'\] must have 2 joint angles, got 3"):
        cal.T_cs("cam1", {"gimbal": [0.1, 0.2, 0.3]})


@pytest.mark.parametrize("make", [stereo_plus_gimbal, two_on_one_chain, two_chains])
def test_save_load_round_trip(tmp_path: Path, make: Any) -> None:
    d = make()
    d["chains"][next(iter(d["chains"]))]["tau_s_std"] = [0.01, None, 0.02, 0.001, 0.002, None]
    d["chains"][next(iter(d["chains"]))]["dh_std"] = [[0.001, None, 0.01], [0.002, 0.003, None]]
    d["cameras"]["cam2"]["rostopic"] = "/cam2/image_raw"
    if "tau_d" in d["cameras"]["cam2"]:
        d["cameras"]["cam2"]["tau_d_std"] = [0.01] * 6
    d["statistics"] = {"note": "hand-measured"}
    d["imu"] = ImuConfig().to_dict()
    first = load_calibration(_write(tmp_path / "in.yaml", d))
    first.save(tmp_path / "out.yaml")
    back = load_calibration(tmp_path / "out.yaml")
    assert back.to_dict() == first.to_dict()
    saved = yaml.safe_load((tmp_path / "out.yaml").read_text())
    assert list(saved) == ["cameras", "chains", "statistics"]
    assert saved["cameras"]["cam2"]["rostopic"] == "/cam2/image_raw"
    first_chain = next(iter(d["chains"]))
    assert saved["chains"][first_chain]["tau_s_std"] == d["chains"][first_chain]["tau_s_std"]
    assert saved["chains"][first_chain]["dh_std"] == d["chains"][first_chain]["dh_std"]
    cl = back.cluster()
    rng = np.random.default_rng(4)
    for theta in rng.uniform(-math.pi, math.pi, size=(5, cl.joint_count)):
        for cam in cl.camera_names:
            assert np.array_equal(back.T_cs(cam, theta), first.T_cs(cam, theta))


def test_the_cluster_follows_the_primary_pair() -> None:
    """``cluster()`` takes the primary chain and camera from ``kin`` (one source of truth)."""
    cal = GimbalCalibration.from_dict(two_chains(), "c.yaml")
    kin = cal.kin.copy()
    kin[3] += 0.5  # tau_s.tx of chain gimbal
    moved = GimbalCalibration(kin, 2, layout=cal.layout)
    assert moved.cluster().chain("gimbal").tau_s[3] == kin[3]
    assert np.array_equal(moved.T_cs("cam1", [0.1, 0.2, 0.3]), moved.T_ds([0.1, 0.2]))
    assert np.array_equal(moved.T_cs("cam3", [0.1, 0.2, 0.3]), cal.T_cs("cam3", [0.1, 0.2, 0.3]))


def test_cluster_dataclasses_check_themselves() -> None:
    gimbal = ChainSpec("gimbal", GIMBAL["tau_s"], GIMBAL["dh"])
    cam0, cam1 = CameraMount("cam0"), CameraMount("cam1", "gimbal", tau_d=np.array(GIMBAL["tau_d"]))
    cl = CameraCluster((cam0, cam1), (gimbal,))
    assert cl.is_two_camera and np.array_equal(cl.T_ds([0.1, 0.2]), cl.T_cs("cam1", [0.1, 0.2]))
    with pytest.raises(ValueError, match="duplicate camera name"):
        CameraCluster((cam0, cam1, cam1), (gimbal,))
    with pytest.raises(ValueError, match="duplicate chain name"):
        CameraCluster((cam0, cam1), (gimbal, gimbal))
    with pytest.raises(ValueError, match="unknown chain 'other'"):
        CameraCluster((cam0, CameraMount("cam1", "other", tau_d=np.zeros(6))), (gimbal,))
    with pytest.raises(ValueError, match="chains.spare: no camera is mounted"):
        CameraCluster((cam0, cam1), (gimbal, ChainSpec("spare", np.zeros(6), np.zeros((0, 3)))))
    with pytest.raises(ValueError, match="cam0.mount must be 'static'"):
        CameraCluster((CameraMount("cam0", "gimbal", tau_d=np.zeros(6)), cam1), (gimbal,))
    with pytest.raises(ValueError, match="needs T_cs"):
        CameraMount("cam2")
    with pytest.raises(ValueError, match="not 'static'"):
        ChainSpec("static", np.zeros(6), np.zeros((0, 3)))


# ---------------------------------------------------------------------------------- bad cluster files


def _mutate(d: dict[str, Any], path: tuple[Any, ...], value: Any) -> dict[str, Any]:
    out = copy.deepcopy(d)
    node = out
    for key in path[:-1]:
        node = node[key]
    if value is ...:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return out


NAN, INF = float("nan"), float("inf")
BAD_CLUSTERS = [
    (
        "unknown_chain",
        ("cameras", "cam3", "mount"),
        "rol",
        "cameras.cam3.mount: unknown chain 'rol' (chains: gimbal, roll",
    ),
    (
        "chain_without_camera",
        ("chains", "spare"),
        {"joints": 0, "tau_s": [0.0] * 6, "dh": []},
        "chains.spare: no camera is mounted on it",
    ),
    (
        "cam0_on_a_chain",
        ("cameras", "cam0"),
        {"mount": "gimbal", "tau_d": [0.0] * 6},
        "cameras.cam0.mount must be 'static': cam0 is the reference static camera",
    ),
    ("cam0_moved", ("cameras", "cam0", "T_cs"), _matrix(T_C1S), "cameras.cam0.T_cs must be the identity"),
    ("gap", ("cameras", "cam2"), ..., "cameras must be named cam0, cam1, cam2 in order, without gaps"),
    (
        "not_a_camera_name",
        ("cameras", "left"),
        {"mount": "static", "T_cs": _matrix(T_C1S)},
        "cameras.left: cameras are named cam0, cam1",
    ),
    ("no_cam0", ("cameras", "cam0"), ..., "the reference static camera cam0 is missing"),
    ("mount_missing", ("cameras", "cam1", "mount"), ..., "cameras.cam1.mount: missing field"),
    ("mount_number", ("cameras", "cam1", "mount"), 3, "cameras.cam1.mount must be 'static' or a chain name"),
    ("tau_d_5", ("cameras", "cam1", "tau_d"), [0.0] * 5, "cameras.cam1.tau_d must have 6 entries [rx, ry, rz, tx"),
    ("tau_d_nan", ("cameras", "cam3", "tau_d", 3), NAN, "cameras.cam3.tau_d[3] (tx) must be a number, got nan"),
    ("tau_d_missing", ("cameras", "cam3", "tau_d"), ..., "cameras.cam3.tau_d: missing field"),
    ("tau_d_on_static", ("cameras", "cam2", "tau_d"), [0.0] * 6, "cameras.cam2.tau_d: a static camera has no"),
    ("T_cs_on_chain", ("cameras", "cam1", "T_cs"), _matrix(T_C1S), "cameras.cam1.T_cs: a camera on chain gimbal"),
    ("T_cs_missing", ("cameras", "cam2", "T_cs"), ..., "cameras.cam2.T_cs: missing field"),
    (
        "T_cs_scaled",
        ("cameras", "cam2", "T_cs"),
        _matrix(np.diag([2.0, 1.0, 1.0, 1.0])),
        "cameras.cam2.T_cs: the 3x3 block is not a rotation",
    ),
    ("T_cs_inf", ("cameras", "cam2", "T_cs", 0, 3), INF, "cameras.cam2.T_cs[0][3] must be a number, got inf"),
    ("T_cs_3x4", ("cameras", "cam2", "T_cs"), _matrix(T_C1S)[:3], "cameras.cam2.T_cs must be a 4x4 matrix"),
    ("camera_typo", ("cameras", "cam1", "tau_D"), [0.0] * 6, "cameras.cam1: unknown field(s) tau_D (allowed: mount"),
    ("chain_typo", ("chains", "roll", "DH"), [], "chains.roll: unknown field(s) DH"),
    ("joints_negative", ("chains", "gimbal", "joints"), -1, "chains.gimbal.joints must be a non-negative integer"),
    (
        "joints_vs_dh",
        ("chains", "roll", "joints"),
        2,
        "chains.roll.dh must have one row [d, a, alpha] per joint (joints = 2), got 1 rows",
    ),
    ("tau_s_inf", ("chains", "roll", "tau_s", 0), INF, "chains.roll.tau_s[0] (rx) must be a number, got inf"),
    ("tau_s_text", ("chains", "roll", "tau_s"), "zero", "chains.roll.tau_s must be a list [rx, ry, rz, tx, ty, tz]"),
    ("dh_nan", ("chains", "gimbal", "dh", 1, 2), NAN, "chains.gimbal.dh[1][2] (alpha) must be a number, got nan"),
    ("dh_row", ("chains", "gimbal", "dh", 0), [0.0, 0.0], "chains.gimbal.dh[0] must have 3 entries [d, a, alpha]"),
    ("dh_missing", ("chains", "roll", "dh"), ..., "chains.roll.dh: missing field"),
    (
        "std_negative",
        ("chains", "roll", "tau_s_std"),
        [-0.1] + [0.0] * 5,
        "chains.roll.tau_s_std[0] (rx) must be a non-negative number, got -0.1",
    ),
    ("dh_std_rows", ("chains", "roll", "dh_std"), [], "chains.roll.dh_std must have one row [d, a, alpha] per joint"),
    ("tau_d_std_nan", ("cameras", "cam3", "tau_d_std"), [NAN] * 6, "cameras.cam3.tau_d_std[0] (rx) must be a non-neg"),
    (
        "chain_static",
        ("chains", "static"),
        {"joints": 0, "tau_s": [0.0] * 6, "dh": []},
        "chains.static: chain name 'static'",
    ),
    ("chain_cam", ("chains", "cam9"), {"joints": 0, "tau_s": [0.0] * 6, "dh": []}, "chains.cam9: chain name 'cam9'"),
    ("chain_not_mapping", ("chains", "roll"), [1, 2], "chains.roll must be a mapping with joints, tau_s, dh"),
    ("chains_missing", ("chains",), ..., "missing field 'chains'"),
    ("chains_empty", ("chains",), {}, "chains must be a non-empty mapping"),
    ("legacy_mixed", ("joints",), 2, "joints: not fields of the cameras:/chains: form"),
    ("legacy_cam1", ("cam1",), CAM, "cam1: not fields of the cameras:/chains: form"),
    (
        "intrinsics",
        ("cameras", "cam2"),
        {"mount": "static", "T_cs": _matrix(T_C1S), **CAM, "intrinsics": [-450.0, 450.0, 320.0, 240.0]},
        "cameras.cam2.intrinsics[0] (fu) must be a positive number",
    ),
    (
        "partial_kalibr",
        ("cameras", "cam2", "intrinsics"),
        [450.0, 450.0, 320.0, 240.0],
        "cameras.cam2.camera_model: missing field",
    ),
    ("rostopic", ("cameras", "cam2", "rostopic"), 5, "cameras.cam2.rostopic must be a topic name"),
]


@pytest.mark.parametrize(("path", "value", "needle"), [c[1:] for c in BAD_CLUSTERS], ids=[c[0] for c in BAD_CLUSTERS])
def test_bad_cluster_fields_are_refused(tmp_path: Path, path: tuple[Any, ...], value: Any, needle: str) -> None:
    bad = _write(tmp_path / "bad_cluster.yaml", _mutate(two_chains(), path, value))
    with pytest.raises(ValueError) as info:
        load_calibration(bad)
    assert f"{bad}: " in str(info.value) and needle in str(info.value), str(info.value)


def test_a_name_given_twice_is_refused(tmp_path: Path) -> None:
    """PyYAML keeps the last of two equal keys silently; a cluster file refuses them, naming the line."""
    text = yaml.safe_dump(two_on_one_chain(), sort_keys=False, default_flow_style=None)
    lines = text.splitlines()
    k = next(i for i, line in enumerate(lines) if line.startswith("  cam2:"))
    twice = tmp_path / "twice.yaml"
    twice.write_text("\n".join([*lines[: k + 1], *lines[k:]]) + "\n")  # cam2: twice
    with pytest.raises(ValueError, match=rf"{twice}: duplicate key 'cam2' \(line {k + 2}\)"):
        load_calibration(twice)
    chains = text.replace("chains:\n", "chains:\n  pan_tilt: {joints: 0, tau_s: [0, 0, 0, 0, 0, 0], dh: []}\n")
    twice.write_text(chains)
    with pytest.raises(ValueError, match=rf"{twice}: duplicate key 'pan_tilt'"):
        load_calibration(twice)


def test_degrees_are_warned(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = _write(tmp_path / "deg.yaml", _mutate(two_chains(), ("chains", "roll", "dh", 0, 2), 90.0))
    with caplog.at_level(logging.WARNING):
        load_calibration(path)
    assert "chains.roll.dh[0][2] (alpha) = 90" in caplog.text and "degrees" in caplog.text


# ------------------------------------------------------------------------------------ Kalibr camchain


def _camchain(tmp_path: Path, transforms: list[np.ndarray], drop: str | None = None) -> Path:
    d: dict[str, Any] = {}
    for n in range(len(transforms) + 1):
        entry = {**CAM, "rostopic": f"/cam{n}/image_raw"}
        if n:
            entry["T_cn_cnm1"] = _matrix(transforms[n - 1])
            entry["cam_overlaps"] = [n - 1]
        d[f"cam{n}"] = entry
    if drop:
        del d[drop]["T_cn_cnm1"]
    return _write(tmp_path / "camchain.yaml", d)


def test_cluster_from_a_kalibr_camchain(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    T10, T21, T32 = (_rigid(rng) for _ in range(3))
    path = _camchain(tmp_path, [T10, T21, T32])
    entries = load_camchain(path)
    got = camchain_transforms(entries, str(path))
    np.testing.assert_allclose(got["cam2"], T21 @ T10, rtol=0, atol=1e-14)
    np.testing.assert_allclose(got["cam3"], T32 @ T21 @ T10, rtol=0, atol=1e-14)
    # cam2 rides on the gimbal; cam1 and cam3 are static (cam3's path crosses cam2, held still during Kalibr)
    gimbal = ChainSpec("gimbal", GIMBAL["tau_s"], GIMBAL["dh"])
    cl = cluster_from_camchain(path, [gimbal], {"cam2": ("gimbal", GIMBAL["tau_d"])})
    assert cl.camera_names == ["cam0", "cam1", "cam2", "cam3"] and cl.static_cameras == ["cam0", "cam1", "cam3"]
    np.testing.assert_allclose(cl.T_cs("cam1"), T10, rtol=0, atol=1e-14)
    np.testing.assert_allclose(cl.T_cs("cam3"), T32 @ T21 @ T10, rtol=0, atol=1e-12)
    assert cl.camera("cam3").rostopic == "/cam3/image_raw" and cl.camera("cam3").camera == entries["cam3"].camera
    theta = np.array([0.4, -0.2])
    np.testing.assert_allclose(cl.T_cs("cam2", theta), _by_hand(GIMBAL["tau_d"], GIMBAL["dh"], GIMBAL["tau_s"], theta),
                               atol=1e-12)  # fmt: skip
    # saved as a calibration, it loads back to the same transforms
    GimbalCalibration.from_cluster(cl).save(tmp_path / "cluster.yaml")
    back = load_calibration(tmp_path / "cluster.yaml")
    for cam in cl.camera_names:
        np.testing.assert_allclose(back.T_cs(cam, theta), cl.T_cs(cam, theta), rtol=0, atol=1e-15)
    # two cameras on the gimbal, the entries instead of the path
    cl2 = cluster_from_camchain(entries, [gimbal], {"cam2": ("gimbal", GIMBAL["tau_d"]), "cam3": ("gimbal", TAU_D2)})
    assert cl2.cameras_on("gimbal") == ["cam2", "cam3"]


def test_bad_camchain_clusters(tmp_path: Path) -> None:
    rng = np.random.default_rng(8)
    gimbal = ChainSpec("gimbal", GIMBAL["tau_s"], GIMBAL["dh"])
    path = _camchain(tmp_path, [_rigid(rng), _rigid(rng)], drop="cam1")
    with pytest.raises(ValueError, match=rf"{path}: cam1.T_cn_cnm1: missing field \(needed to place cam1"):
        cluster_from_camchain(path, [gimbal], {"cam2": ("gimbal", TAU_D2)})
    # cam1 on the gimbal: its T_cn_cnm1 is not needed
    cl = cluster_from_camchain(path, [gimbal], {"cam1": ("gimbal", TAU_D2), "cam2": ("gimbal", TAU_D2)})
    assert cl.static_cameras == ["cam0"]
    path = _camchain(tmp_path, [_rigid(rng)])
    with pytest.raises(ValueError, match=rf"{path}: gimbal camera\(s\) cam5 not in the camchain"):
        cluster_from_camchain(path, [gimbal], {"cam5": ("gimbal", TAU_D2)})
    with pytest.raises(ValueError, match=rf"{path}: cameras.cam1.mount: unknown chain 'other'"):
        cluster_from_camchain(path, [gimbal], {"cam1": ("other", TAU_D2)})
    with pytest.raises(ValueError, match=rf"{path}: chains.gimbal: no camera is mounted on it"):
        cluster_from_camchain(path, [gimbal], {})
    with pytest.raises(ValueError, match="cam0 is the reference static camera"):
        cluster_from_camchain(path, [gimbal], {"cam0": ("gimbal", TAU_D2)})


# ------------------------------------------------------------------------ two-camera-only code paths


def test_vio_checks_an_n_camera_cluster_before_any_work(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``dcc-fg vio`` takes a file whose cam1 is a static stereo partner (N-camera VIO,
    tests/test_vio_cluster.py); a camera the file does not have is refused by name before the bag is read."""
    d = stereo_plus_gimbal()
    d["imu"] = ImuConfig().to_dict()
    cal_path = _write(tmp_path / "cluster.yaml", d)
    bag = tmp_path / "flight.bag"
    bag.write_bytes(b"")
    out = tmp_path / "run"
    args = ["vio", str(bag), "--calibration", str(cal_path), "--out", str(out), "-q"]
    assert main([*args, "--cameras", "cam7"]) == 2
    err = capsys.readouterr().err
    assert f"{cal_path}: no camera cam7 in the cluster (cameras: cam0, cam1, cam2)" in err, err
    assert main(args) == 2  # the calibration is fine: the empty bag is what is refused
    err = capsys.readouterr().err
    assert str(bag) in err and "cluster" not in err, err
    assert not out.exists()


def test_kalibr_export_refuses_an_n_camera_cluster(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cal_path = _write(tmp_path / "cluster.yaml", two_on_one_chain())
    out = tmp_path / "camchain.yaml"
    assert main(["export", str(cal_path), "--format", "kalibr", "--out", str(out), "--joints", "0,0"]) == 2
    err = capsys.readouterr().err
    assert str(cal_path) in err and "N-camera Kalibr export is not supported yet" in err, err
    assert not out.exists()


def test_cam0_cam1_of_a_larger_cluster_where_that_is_all_that_is_needed(caplog: pytest.LogCaptureFixture) -> None:
    cal = GimbalCalibration.from_dict(two_chains(), "rig.yaml")
    with caplog.at_level(logging.INFO, logger="dcc_fg.model"):
        assert cal.require_two_cameras("VIO", allow_subset=True) is cal
    assert "rig.yaml: VIO uses cam0 (static) and cam1 (chain gimbal) only; cam2, cam3 not used" in caplog.text
    with pytest.raises(ValueError, match="rig.yaml: a 4-camera cluster .*N-camera calibration is not supported yet"):
        cal.require_two_cameras("calibration")
    # a cluster file of exactly two cameras is a two-camera calibration, whatever its chain is called
    pair = GimbalCalibration.from_dict(_mutate(two_on_one_chain(), ("cameras", "cam2"), ...), "pair.yaml")
    assert pair.is_two_camera and pair.require_two_cameras("calibration") is pair


def test_the_calibration_refuses_an_n_camera_initial_guess() -> None:
    """The estimator's first check, before it looks at the data."""
    cal = GimbalCalibration.from_dict(two_on_one_chain(), "g.yaml")
    with pytest.raises(ValueError, match="g.yaml: a 3-camera cluster .*N-camera calibration is not supported yet"):
        calibrate(None, cal)  # type: ignore[arg-type]


def test_calibrate_refuses_an_n_camera_gimbal_file_before_reading_the_data(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``dcc-fg calibrate --gimbal`` with a 3-camera file: exit 2 naming the file and the Python API, before the
    data are looked at (the data folder here does not even exist) and without an output folder."""
    cal_path = _write(tmp_path / "rig.yaml", stereo_plus_gimbal())
    out = tmp_path / "cal"
    argv = ["calibrate", str(tmp_path / "no_data"), "--gimbal", str(cal_path), "--out", str(out), "-q"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "rig.yaml: a 3-camera cluster" in err and "calibrate_cluster" in err and "no_data" not in err
    assert not out.exists()


def test_init_file_needs_a_cluster(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--init file`` is the N-camera start from the ``--cluster`` file: without one it is refused by name."""
    argv = ["calibrate", str(tmp_path), "--init", "file", "--joints", "2", "--out", str(tmp_path / "c"), "-q"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "--init file starts an N-camera calibration from its --cluster file: give --cluster" in err
