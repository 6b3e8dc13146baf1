"""``dcc-fg export``: URDF, Kalibr camchain and joint-state bags of a calibration (issue 17, item 1).

* the URDF loads in ``yourdfpy`` and its forward kinematics from the static to the gimbal camera link
  is ``T_sd(theta) = inv(T_ds(theta))`` to 1e-9 over random angles for random L = 1, 2, 3 mechanisms;
* the Kalibr camchain (and camchain-imucam) reads back through :mod:`dcc_fg.io.camchain` with
  ``T_cn_cnm1 = T_ds(theta)`` to 1e-9;
* the joint-state bags (ROS1 and ROS2) read back with rosbags: stamps, names, positions;
* an N-camera cluster (cameras:/chains: form) as a URDF: yourdfpy's forward kinematics from cam0 to
  every camera link is ``inv(T_cs(camera, theta))`` to 1e-9 (static stereo + gimbal camera, two cameras
  on one chain, two chains), by the CLI too, and its joint-state bag has the URDF's joint names;
* the CLI end to end on a calibration.yaml of ``dcc-fg calibrate`` (a small rendered data set);
* bad input is refused with exit code 2 and a message naming the file, field or option.
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
import yourdfpy

from dcc_fg.cli import main
from dcc_fg.cluster import CameraCluster, CameraMount, ChainSpec
from dcc_fg.commands.vio import camchain_T_sI, camchain_time_offsets
from dcc_fg.data.vio import ImuConfig
from dcc_fg.export.joint_states import read_joint_angles, write_joint_state_bag
from dcc_fg.export.kalibr import camchain_text, frozen_camchain, imucam_path, parse_joint_angles
from dcc_fg.export.naming import cluster_names, layout_names
from dcc_fg.export.urdf import (
    cluster_joints,
    layout_joints,
    layout_urdf_text,
    observed_limits,
    relative_pose,
    rpy_from_rotation,
    urdf_text,
)
from dcc_fg.io.bag_writer import BagWriter
from dcc_fg.io.bags import JOINT_STATE, open_bag
from dcc_fg.io.camchain import load_camchain
from dcc_fg.io.outputs import read_joint_angles_csv, write_joint_angles_csv
from dcc_fg.model import GimbalCalibration, load_calibration
from dcc_fg.sim.calibration_scene import random_mechanism
from dcc_fg.sim.write_dataset import CalibrationSimSpec, RenderedCalibration, write_calibration_dataset
from factors import chain

TOL = 1e-9
STAMP0 = 1_600_000_000_123_456_789  # beyond float64's integer precision: stamps must stay exact


def _mechanism(n_joints: int, seed: int) -> GimbalCalibration:
    cal, _ = random_mechanism(np.random.default_rng(seed), n_joints)
    return cal


def _load_urdf(path: Path) -> yourdfpy.URDF:
    return yourdfpy.URDF.load(str(path), load_meshes=False, build_collision_scene_graph=False)


def _urdf_T(
    robot: yourdfpy.URDF, joints: tuple[str, ...], theta: np.ndarray, frame_from: str, frame_to: str
) -> np.ndarray:
    """yourdfpy's pose of ``frame_to`` in ``frame_from`` with the joints at ``theta`` (rad)."""
    robot.update_cfg(dict(zip(joints, (float(x) for x in theta), strict=True)))
    return robot.get_transform(frame_to, frame_from)


# ------------------------------------------------------------------------------------------- URDF


@pytest.mark.parametrize("n_joints", [1, 2, 3])
@pytest.mark.parametrize("body_frames", [False, True])
def test_urdf_forward_kinematics_is_T_sd(tmp_path: Path, n_joints: int, body_frames: bool) -> None:
    rng = np.random.default_rng(100 + n_joints)
    for member in range(3):
        cal = _mechanism(n_joints, 10 * n_joints + member)
        names = cluster_names(n_joints, prefix="rig_")
        limits = np.sort(rng.uniform(-3.0, 3.0, size=(n_joints, 2)), axis=1)
        path = tmp_path / f"m{member}.urdf"
        path.write_text(urdf_text(cal, names, limits, body_frames=body_frames))
        robot = _load_urdf(path)
        assert robot.validate()
        assert robot.base_link == (names.static_body if body_frames else names.static_optical)
        assert robot.actuated_joint_names == list(names.joints)
        for k, name in enumerate(names.joints):
            joint = robot.joint_map[name]
            assert joint.type == "revolute" and np.array_equal(joint.axis, [0.0, 0.0, 1.0])
            assert (joint.limit.lower, joint.limit.upper) == (limits[k, 0], limits[k, 1])
        for _ in range(25):
            theta = rng.uniform(-math.pi, math.pi, size=n_joints)
            T_sd = _urdf_T(robot, names.joints, theta, names.static_optical, names.gimbal_optical)
            np.testing.assert_allclose(T_sd, chain.inv_se3(cal.T_ds(theta)), rtol=0, atol=TOL)
            # the paper's frames are in the tree: b at T_sb, e at T_sb A_1 ... A_L
            T_sb = _urdf_T(robot, names.joints, theta, names.static_optical, names.base)
            np.testing.assert_allclose(T_sb, chain.inv_se3(cal.T_bs()), rtol=0, atol=TOL)
            T_be = _urdf_T(robot, names.joints, theta, names.base, names.end_effector)
            np.testing.assert_allclose(T_be, chain.inv_se3(chain.T_eb(cal.dh, theta)), rtol=0, atol=TOL)
        if body_frames:  # ROS camera convention: optical z (forward) = body x, optical x (right) = body -y
            for body, optical in ((names.static_body, names.static_optical), (names.gimbal_body, names.gimbal_optical)):
                R = _urdf_T(robot, names.joints, np.zeros(n_joints), body, optical)[:3, :3]
                np.testing.assert_allclose(R @ [0, 0, 1], [1, 0, 0], atol=1e-15)
                np.testing.assert_allclose(R @ [1, 0, 0], [0, -1, 0], atol=1e-15)
                np.testing.assert_allclose(R @ [0, 1, 0], [0, 0, -1], atol=1e-15)


def test_urdf_rigid_pair_and_own_forward_kinematics(tmp_path: Path) -> None:
    """L = 0 (a rigid pair) is only fixed joints; the module's own FK agrees with yourdfpy."""
    cal = _mechanism(2, 3)
    rigid = GimbalCalibration.from_parts(cal.tau_s, cal.tau_d, np.zeros((0, 3)))
    names = cluster_names(0)
    path = tmp_path / "rigid.urdf"
    path.write_text(urdf_text(rigid, names))
    robot = _load_urdf(path)
    assert robot.actuated_joint_names == []
    T = robot.get_transform(names.gimbal_optical, names.static_optical)
    np.testing.assert_allclose(T, chain.inv_se3(rigid.T_ds(np.zeros(0))), rtol=0, atol=TOL)
    from_module = relative_pose(cluster_joints(rigid, names), {}, names.static_optical, names.gimbal_optical)
    np.testing.assert_allclose(from_module, T, rtol=0, atol=1e-12)


def test_rpy_is_exact_at_and_near_gimbal_lock() -> None:
    rng = np.random.default_rng(0)
    pitches = [math.pi / 2, -math.pi / 2, math.pi / 2 - 1e-8, -math.pi / 2 + 1e-12, 0.3, math.pi / 2 - 1e-4]
    for pitch in pitches:
        for _ in range(20):
            roll, yaw = rng.uniform(-math.pi, math.pi, size=2)
            R = chain.rot_z(yaw) @ chain.rot_y(pitch) @ chain.rot_x(roll)
            r, p, y = rpy_from_rotation(R)
            np.testing.assert_allclose(chain.rot_z(y) @ chain.rot_y(p) @ chain.rot_x(r), R, rtol=0, atol=2e-15)


def test_observed_limits() -> None:
    angles = np.array([[0.1, -0.5], [0.3, 0.2], [-0.2, 0.0]])
    np.testing.assert_array_equal(observed_limits(angles), [[-0.2, 0.3], [-0.5, 0.2]])
    np.testing.assert_allclose(observed_limits(angles, 0.1), [[-0.3, 0.4], [-0.6, 0.3]])


def test_names_are_checked() -> None:
    with pytest.raises(ValueError, match="not a usable URDF"):
        cluster_names(2, joints=["a", "b c"])
    with pytest.raises(ValueError, match="both be named"):
        cluster_names(1, static_frame="same", gimbal_frame="same")


# ------------------------------------------------------------------------------- N-camera clusters


def _cluster(kind: str, seed: int) -> CameraCluster:
    """Random mechanisms as clusters: ``stereo`` (cam0, cam1 static; cam2 on a 2-DOF gimbal), ``shared``
    (cam1 and cam2 on one 2-DOF gimbal), ``two_chains`` (cam1 on a 3-DOF gimbal, cam2 static, cam3 on a
    1-DOF chain)."""
    rng = np.random.default_rng(seed)
    a, b = _mechanism(3 if kind == "two_chains" else 2, seed), _mechanism(1, seed + 50)
    T_static = chain.se3_from_tau(np.concatenate([rng.uniform(-0.5, 0.5, 3), rng.uniform(-0.2, 0.2, 3)]))
    gimbal = ChainSpec("gimbal", a.tau_s, a.dh)
    cam0 = CameraMount("cam0")
    if kind == "stereo":
        cams = [cam0, CameraMount("cam1", T_cs=T_static), CameraMount("cam2", "gimbal", tau_d=a.tau_d)]
        return CameraCluster(tuple(cams), (gimbal,))
    if kind == "shared":
        cams = [cam0, CameraMount("cam1", "gimbal", tau_d=a.tau_d), CameraMount("cam2", "gimbal", tau_d=b.tau_d)]
        return CameraCluster(tuple(cams), (gimbal,))
    cams = [cam0, CameraMount("cam1", "gimbal", tau_d=a.tau_d), CameraMount("cam2", T_cs=T_static),
            CameraMount("cam3", "roll", tau_d=b.tau_d)]  # fmt: skip
    return CameraCluster(tuple(cams), (gimbal, ChainSpec("roll", b.tau_s, b.dh)))


@pytest.mark.parametrize("kind", ["stereo", "shared", "two_chains"])
@pytest.mark.parametrize("body_frames", [False, True])
def test_cluster_urdf_forward_kinematics_is_T_cs(tmp_path: Path, kind: str, body_frames: bool) -> None:
    rng = np.random.default_rng(len(kind))
    for member in range(2):
        cl = _cluster(kind, 20 + member)
        names = layout_names(cl.camera_names, [(c.name, c.n_joints) for c in cl.chains], prefix="rig_")
        J = cl.joint_count
        limits = np.sort(rng.uniform(-3.0, 3.0, size=(J, 2)), axis=1)
        path = tmp_path / f"{kind}_{member}.urdf"
        path.write_text(layout_urdf_text(cl, names, limits, body_frames=body_frames))
        robot = _load_urdf(path)
        assert robot.validate()
        assert robot.base_link == ("rig_cam0" if body_frames else "rig_cam0_optical")
        expected = ["rig_gimbal_joint_1", "rig_gimbal_joint_2", "rig_gimbal_joint_3", "rig_roll_joint_1"]
        assert (
            robot.actuated_joint_names
            == list(names.joints)
            == (expected if kind == "two_chains" else ["rig_joint_1", "rig_joint_2"])
        )
        for k, name in enumerate(names.joints):
            assert (robot.joint_map[name].limit.lower, robot.joint_map[name].limit.upper) == tuple(limits[k])
        for _ in range(15):
            theta = rng.uniform(-math.pi, math.pi, size=J)
            for cam in cl.camera_names:
                T = _urdf_T(robot, names.joints, theta, names.optical["cam0"], names.optical[cam])
                np.testing.assert_allclose(T, chain.inv_se3(cl.T_cs(cam, theta)), rtol=0, atol=TOL)
            for ch in cl.chains:  # each chain's b and e frames are in the tree
                T_sb = _urdf_T(robot, names.joints, theta, names.optical["cam0"], names.base[ch.name])
                np.testing.assert_allclose(T_sb, chain.inv_se3(ch.T_bs()), rtol=0, atol=TOL)
        own = relative_pose(layout_joints(cl, names, limits, body_frames), {}, names.optical["cam0"],
                            names.optical[cl.camera_names[-1]])  # fmt: skip
        np.testing.assert_allclose(own, chain.inv_se3(cl.T_cs(cl.camera_names[-1], np.zeros(J))), atol=1e-12)


def test_cli_cluster_urdf_and_joint_states(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cl = _cluster("two_chains", 3)
    cal_path = tmp_path / "cluster" / "calibration.yaml"
    cal_path.parent.mkdir()
    GimbalCalibration.from_cluster(cl).save(cal_path)
    cal = load_calibration(cal_path)
    rng = np.random.default_rng(9)
    stamps = STAMP0 + np.arange(20, dtype=np.int64) * 50_000_000
    theta = rng.uniform(-2.0, 2.0, size=(20, 4))
    write_joint_angles_csv(cal_path.parent / "joint_angles.csv", stamps, theta)  # beside: the limits
    _, theta = read_joint_angles_csv(cal_path.parent / "joint_angles.csv")
    out = tmp_path / "cluster.urdf"
    assert main(["export", str(cal_path), "--format", "urdf", "--out", str(out), "--body-frames", "-q"]) == 0
    robot = _load_urdf(out)
    joints = ("gimbal_joint_1", "gimbal_joint_2", "gimbal_joint_3", "roll_joint_1")
    assert robot.base_link == "cam0" and tuple(robot.actuated_joint_names) == joints
    limits = [(robot.joint_map[j].limit.lower, robot.joint_map[j].limit.upper) for j in joints]
    np.testing.assert_array_equal(limits, observed_limits(theta))
    for th in theta[:5]:
        for cam in ("cam1", "cam2", "cam3"):
            T = _urdf_T(robot, joints, th, "cam0_optical", f"{cam}_optical")
            np.testing.assert_allclose(T, chain.inv_se3(cal.T_cs(cam, th)), rtol=0, atol=TOL)
    # joint names given, the flat order; per-camera links cannot be renamed with --static-frame
    argv = ["export", str(cal_path), "--format", "urdf", "--out", str(tmp_path / "n.urdf"), "-q"]
    assert main([*argv, "--joint-names", "pan,tilt,roll,aux"]) == 0
    assert _load_urdf(tmp_path / "n.urdf").actuated_joint_names == ["pan", "tilt", "roll", "aux"]
    assert main([*argv, "--joint-names", "pan,tilt", "--force"]) == 2
    assert "2 name(s) given, but" in capsys.readouterr().err
    assert main([*argv, "--static-frame", "left", "--force"]) == 2
    err = capsys.readouterr().err
    assert str(cal_path) in err and "camera links are named PREFIXcamN_optical" in err
    # joint states: the 4 columns of the flat order, the URDF's names
    bag = tmp_path / "states.bag"
    csv = cal_path.parent / "joint_angles.csv"
    assert main(["export", str(cal_path), "--format", "joint-states", "--joints-csv", str(csv), "--out", str(bag),
                 "-q"]) == 0  # fmt: skip
    _, _, _, names, pos = _read_joint_bag(bag)
    assert names == [list(joints)] * 20
    np.testing.assert_array_equal(pos, theta)


# ----------------------------------------------------------------------------------------- Kalibr


@pytest.mark.parametrize("n_joints", [1, 2, 3])
def test_kalibr_round_trips_through_the_camchain_reader(tmp_path: Path, n_joints: int) -> None:
    rng = np.random.default_rng(n_joints)
    imu = ImuConfig(T_sI=chain.se3_from_tau(rng.uniform(-1, 1, 6)), time_offsets=(0.004, -0.0125))
    for member in range(3):
        cal = _mechanism(n_joints, 7 * n_joints + member)
        theta = rng.uniform(-math.pi, math.pi, size=n_joints)
        T_ds = cal.T_ds(theta)
        out = tmp_path / f"camchain_{member}.yaml"
        out.write_text(camchain_text(frozen_camchain(cal, theta, "cal.yaml"), ["test"]))
        chain_back = load_camchain(out)
        assert sorted(chain_back) == ["cam0", "cam1"]
        assert chain_back["cam0"].camera == cal.static_camera and chain_back["cam1"].camera == cal.dynamic_camera
        assert chain_back["cam0"].rostopic == "/cam0/image_raw"
        np.testing.assert_allclose(chain_back["cam1"].extra["T_cn_cnm1"], T_ds, rtol=0, atol=TOL)
        assert "T_cam_imu" not in chain_back["cam0"].extra
        # camchain-imucam form: T_cam_imu per camera and the time shifts
        imucam = imucam_path(out)
        imucam.write_text(camchain_text(frozen_camchain(cal, theta, "cal.yaml", imu=imu), ["test"]))
        back = load_camchain(imucam)
        np.testing.assert_allclose(back["cam1"].extra["T_cn_cnm1"], T_ds, rtol=0, atol=TOL)
        np.testing.assert_allclose(back["cam0"].extra["T_cam_imu"], imu.T_sI, rtol=0, atol=TOL)
        np.testing.assert_allclose(back["cam1"].extra["T_cam_imu"], T_ds @ imu.T_sI, rtol=0, atol=TOL)
        # what dcc-fg vio reads from a camchain-imucam
        np.testing.assert_allclose(camchain_T_sI(imucam), imu.T_sI, rtol=0, atol=TOL)
        assert camchain_time_offsets(imucam) == (0.004, -0.0125)


def test_imucam_path_follows_kalibr_names(tmp_path: Path) -> None:
    assert imucam_path(tmp_path / "camchain.yaml").name == "camchain-imucam.yaml"
    assert imucam_path(tmp_path / "camchain-run3.yaml").name == "camchain-imucam-run3.yaml"
    assert imucam_path(tmp_path / "rig.yaml").name == "rig-imucam.yaml"


def test_parse_joint_angles() -> None:
    np.testing.assert_array_equal(parse_joint_angles("0.5, -0.25", 2, "c.yaml"), [0.5, -0.25])
    np.testing.assert_allclose(parse_joint_angles("90,-45deg", 2, "c.yaml"), [math.pi / 2, -math.pi / 4])
    np.testing.assert_array_equal(parse_joint_angles("1rad", 1, "c.yaml"), [1.0])
    assert parse_joint_angles("", 0, "c.yaml").shape == (0,)
    with pytest.raises(ValueError, match=r"1 joint angle\(s\) given, but c.yaml has 2 joint"):
        parse_joint_angles("0.5", 2, "c.yaml")
    with pytest.raises(ValueError, match="theta_1 = '5deg' is not a number"):
        parse_joint_angles("5deg,3", 2, "c.yaml")
    with pytest.raises(ValueError, match="beyond one turn; for degrees put 'deg'"):
        parse_joint_angles("90,5", 2, "c.yaml")
    with pytest.raises(ValueError, match="must be finite"):
        parse_joint_angles("nan", 1, "c.yaml")


# ----------------------------------------------------------------------------------- joint states


def _read_joint_bag(path: Path) -> tuple[list[str], list[int], list[int], list[list[str]], np.ndarray]:
    """(topics, record stamps, header stamps, names, positions) of every message."""
    topics, record, header, names, pos = [], [], [], [], []
    with open_bag(path) as reader:
        assert {c.msgtype for c in reader.connections} == {JOINT_STATE}
        for conn, t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            topics.append(conn.topic)
            record.append(int(t))
            header.append(int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec))
            names.append(list(msg.name))
            pos.append(np.asarray(msg.position, dtype=float))
            assert len(msg.velocity) == 0 and len(msg.effort) == 0
    return topics, record, header, names, np.array(pos)


@pytest.mark.parametrize("out_name", ["joints.bag", "joints_ros2"])
def test_joint_state_bag_reads_back(tmp_path: Path, out_name: str) -> None:
    rng = np.random.default_rng(4)
    stamps = STAMP0 + np.arange(30, dtype=np.int64) * 33_333_333
    angles = rng.uniform(-3.0, 3.0, size=(30, 3))
    csv = tmp_path / "joint_angles.csv"
    order = rng.permutation(30)  # rows out of order: the bag is written in time order
    write_joint_angles_csv(csv, stamps[order], angles[order])
    t_csv, th_csv = read_joint_angles(csv, 3, "cal.yaml")
    names = ["pan", "tilt", "roll"]
    out = tmp_path / out_name
    assert write_joint_state_bag(out, t_csv, th_csv, names, topic="/gimbal/joint_states") == 30
    assert out.is_file() == out_name.endswith(".bag")
    topics, record, header, got_names, pos = _read_joint_bag(out)
    assert topics == ["/gimbal/joint_states"] * 30
    assert record == header == [int(s) for s in stamps]
    assert got_names == [names] * 30
    np.testing.assert_allclose(pos, angles, rtol=0, atol=1e-11)  # the CSV holds 12 significant digits


# ------------------------------------------------------------------------------------- CLI end to end


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """calibration.yaml + joint_angles.csv of ``dcc-fg calibrate`` on 12 rendered image pairs (2 joints)."""
    root = tmp_path_factory.mktemp("export")
    spec = CalibrationSimSpec("checkerboard", "folder", seed=5, n_snapshots=12)
    r: RenderedCalibration = write_calibration_dataset(root / "data", spec)
    out = root / "cal"
    argv = ["calibrate", str(r.data), "--camchain", str(r.camchain), "--target", str(r.target), "--gimbal"]
    assert main([*argv, str(r.gimbal), "--out", str(out), "-q"]) == 0
    return out


def test_cli_urdf(calibrated: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cal_path = calibrated / "calibration.yaml"
    cal = load_calibration(cal_path)
    t_ns, theta = read_joint_angles_csv(calibrated / "joint_angles.csv")
    out = tmp_path / "cluster.urdf"
    argv = ["export", str(cal_path), "--format", "urdf", "--out", str(out), "--prefix", "g0_", "--body-frames"]
    assert main(argv) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    robot = _load_urdf(out)
    assert robot.base_link == "g0_static_camera"
    assert robot.actuated_joint_names == ["g0_joint_1", "g0_joint_2"]
    limits = [(robot.joint_map[j].limit.lower, robot.joint_map[j].limit.upper) for j in robot.actuated_joint_names]
    np.testing.assert_array_equal(limits, observed_limits(theta))  # from the joint_angles.csv beside it
    for th in theta:
        T = _urdf_T(robot, ("g0_joint_1", "g0_joint_2"), th, "g0_static_camera_optical", "g0_gimbal_camera_optical")
        np.testing.assert_allclose(T, chain.inv_se3(cal.T_ds(th)), rtol=0, atol=TOL)
    # custom joint and camera frame names, a margin; no --force: an existing file is kept
    argv = ["export", str(cal_path), "--format", "urdf", "--out", str(out), "--joint-names", "yaw,pitch"]
    argv += ["--static-frame", "cam0", "--gimbal-frame", "cam1", "--limit-margin", "0.1", "-q"]
    assert main(argv) == 2 and "exists" in capsys.readouterr().err
    assert main([*argv, "--force"]) == 0
    robot = _load_urdf(out)
    assert robot.base_link == "cam0" and robot.actuated_joint_names == ["yaw", "pitch"]
    assert robot.joint_map["yaw"].limit.lower == pytest.approx(theta[:, 0].min() - 0.1, abs=1e-15)
    T = _urdf_T(robot, ("yaw", "pitch"), theta[3], "cam0", "cam1")
    np.testing.assert_allclose(T, chain.inv_se3(cal.T_ds(theta[3])), rtol=0, atol=TOL)


def test_cli_urdf_without_joint_angles_uses_pi(
    calibrated: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    alone = tmp_path / "alone"
    alone.mkdir()
    shutil.copy(calibrated / "calibration.yaml", alone / "calibration.yaml")
    out = tmp_path / "pi.urdf"
    assert main(["export", str(alone / "calibration.yaml"), "--format", "urdf", "--out", str(out)]) == 0
    assert "joint limits set to +-pi rad: no joint_angles.csv beside" in capsys.readouterr().err  # the logged note
    assert "joint limits: +-pi" in out.read_text()  # and the note in the file
    robot = _load_urdf(out)
    assert [robot.joint_map[j].limit.lower for j in robot.actuated_joint_names] == [-math.pi, -math.pi]
    assert [robot.joint_map[j].limit.upper for j in robot.actuated_joint_names] == [math.pi, math.pi]
    # an explicit --joints-csv gives the limits
    out2 = tmp_path / "csv.urdf"
    csv = calibrated / "joint_angles.csv"
    assert main(["export", str(alone / "calibration.yaml"), "--format", "urdf", "--out", str(out2), "--joints-csv",
                 str(csv), "-q"]) == 0  # fmt: skip
    _, theta = read_joint_angles_csv(csv)
    assert _load_urdf(out2).joint_map["joint_2"].limit.upper == theta[:, 1].max()


def test_cli_kalibr(calibrated: Path, tmp_path: Path) -> None:
    cal_path = calibrated / "calibration.yaml"
    cal = load_calibration(cal_path)
    _, theta = read_joint_angles_csv(calibrated / "joint_angles.csv")
    th = theta[2]
    out = tmp_path / "camchain.yaml"
    argv = [
        "export",
        str(cal_path),
        "--format",
        "kalibr",
        "--out",
        str(out),
        f"--joints={float(th[0])!r},{float(th[1])!r}",
        "-q",
    ]
    assert main(argv) == 0
    assert not imucam_path(out).exists()  # no imu: section
    back = load_camchain(out)
    np.testing.assert_allclose(back["cam1"].extra["T_cn_cnm1"], cal.T_ds(th), rtol=0, atol=TOL)
    assert back["cam0"].camera == cal.static_camera and back["cam1"].camera == cal.dynamic_camera
    # degrees, other topics
    deg = tmp_path / "deg.yaml"
    argv = ["export", str(cal_path), "--format", "kalibr", "--out", str(deg), "--joints", "90,-5deg"]
    assert main([*argv, "--image-topics", "/a/image,/b/image", "-q"]) == 0
    back = load_camchain(deg)
    np.testing.assert_allclose(back["cam1"].extra["T_cn_cnm1"], cal.T_ds(np.deg2rad([90.0, -5.0])), atol=TOL)
    assert (back["cam0"].rostopic, back["cam1"].rostopic) == ("/a/image", "/b/image")
    # with an imu: section, the camchain-imucam form beside it
    d = yaml.safe_load(cal_path.read_text())
    T_sI = chain.se3_from_tau(np.array([0.1, -0.2, 0.3, 0.01, 0.02, -0.03]))
    d["imu"] = ImuConfig(T_sI=T_sI, time_offsets=(0.002, 0.017)).to_dict()
    with_imu = tmp_path / "with_imu" / "calibration.yaml"
    with_imu.parent.mkdir()
    with_imu.write_text(yaml.safe_dump(d, sort_keys=False))
    out = tmp_path / "k" / "camchain.yaml"
    assert main(["export", str(with_imu), "--format", "kalibr", "--out", str(out), "--joints", "0.1,0.2", "-q"]) == 0
    imucam = tmp_path / "k" / "camchain-imucam.yaml"
    back = load_camchain(imucam)
    T_ds = cal.T_ds([0.1, 0.2])
    np.testing.assert_allclose(back["cam1"].extra["T_cam_imu"], T_ds @ T_sI, rtol=0, atol=TOL)
    np.testing.assert_allclose(camchain_T_sI(imucam), T_sI, rtol=0, atol=TOL)
    assert camchain_time_offsets(imucam) == (0.002, 0.017)
    assert "T_cam_imu" not in load_camchain(out)["cam0"].extra  # the plain camchain stays plain


@pytest.mark.parametrize(
    ("out_name", "storage"), [("states.bag", []), ("states", []), ("states", ["--storage", "mcap"])]
)
def test_cli_joint_states(calibrated: Path, tmp_path: Path, out_name: str, storage: list[str]) -> None:
    cal_path = calibrated / "calibration.yaml"
    csv = calibrated / "joint_angles.csv"
    t_ns, theta = read_joint_angles_csv(csv)
    out = tmp_path / out_name
    argv = ["export", str(cal_path), "--format", "joint-states", "--joints-csv", str(csv), "--out", str(out)]
    assert main([*argv, *storage, "--prefix", "g0_", "-q"]) == 0
    if storage:
        assert list(out.glob("*.mcap"))
    topics, record, header, names, pos = _read_joint_bag(out)
    assert set(topics) == {"/joint_states"}
    assert header == record == sorted(int(t) for t in t_ns)
    order = np.argsort(t_ns, kind="stable")
    assert names == [["g0_joint_1", "g0_joint_2"]] * len(t_ns)  # the URDF's names with the same --prefix
    np.testing.assert_array_equal(pos, theta[order])
    # the same names as the URDF exported with the same options
    urdf = tmp_path / "c.urdf"
    assert main(["export", str(cal_path), "--format", "urdf", "--out", str(urdf), "--prefix", "g0_", "-q"]) == 0
    assert _load_urdf(urdf).actuated_joint_names == names[0]
    # a second run replaces its own bag only with --force
    assert main([*argv, "-q"]) == 2
    assert main([*argv, "--topic", "/gimbal/joint_states", "--force", "-q"]) == 0
    assert set(_read_joint_bag(out)[0]) == {"/gimbal/joint_states"}


# ------------------------------------------------------------------------------------------ bad input


def _refused(argv: list[str], capsys: pytest.CaptureFixture[str], *needles: str) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("dcc-fg export: error:"), err
    for n in needles:
        assert n in err, (n, err)
    return err


def test_bad_input_is_refused(calibrated: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cal_path = calibrated / "calibration.yaml"
    cal_text = cal_path.read_text()
    csv = calibrated / "joint_angles.csv"
    base = ["export", str(cal_path)]
    kalibr = [*base, "--format", "kalibr", "--out", str(tmp_path / "k.yaml")]
    _refused(kalibr, capsys, "needs --joints", str(cal_path))
    _refused([*kalibr, "--joints", "0.1"], capsys, "1 joint angle(s) given", str(cal_path), "2 joint(s)")
    _refused([*kalibr, "--joints", "0.1,0.2,0.3"], capsys, "3 joint angle(s) given")
    _refused([*kalibr, "--joints", "a,b"], capsys, "theta_1 = 'a' is not a number")
    # a calibration without the gimbal (dynamic) camera
    d = yaml.safe_load(cal_text)
    del d["cam1"]
    no_cam1 = tmp_path / "no_cam1.yaml"
    no_cam1.write_text(yaml.safe_dump(d))
    _refused(["export", str(no_cam1), "--format", "kalibr", "--out", str(tmp_path / "x.yaml"), "--joints", "0,0"],
             capsys, str(no_cam1), "no 'cam1' entry", "gimbal (dynamic) camera")  # fmt: skip
    # CSVs with wrong columns or rows
    wrong = tmp_path / "wrong.csv"
    wrong.write_text("timestamp_ns,theta_1\n1,0.1\n")
    states = [*base, "--format", "joint-states", "--out", str(tmp_path / "s.bag"), "--joints-csv"]
    _refused([*states, str(wrong)], capsys, f"{wrong}:1: columns timestamp_ns,theta_1; expected "
             "timestamp_ns,theta_1,theta_2", str(cal_path))  # fmt: skip
    wrong.write_text("timestamp_ns,theta_1,theta_2\n1,0.1,0.2\n2,0.1\n")
    _refused([*states, str(wrong)], capsys, f"{wrong}:3: 2 fields, expected 3")
    wrong.write_text("timestamp_ns,theta_1,theta_2\n1.5,0.1,0.2\n")
    _refused([*states, str(wrong)], capsys, f"{wrong}:2: timestamp_ns '1.5' is not an integer")
    wrong.write_text("timestamp_ns,theta_1,theta_2\n1,90,0.2\n")
    _refused([*states, str(wrong)], capsys, f"{wrong}:2: theta_1 = 90 is beyond one turn")
    wrong.write_text("timestamp_ns,theta_1,theta_2\n")
    _refused([*states, str(wrong)], capsys, f"{wrong}: no rows")
    _refused([*states, str(tmp_path / "missing.csv")], capsys, "missing.csv")
    _refused([*base, "--format", "urdf", "--out", str(tmp_path / "u.urdf"), "--joints-csv", str(wrong)], capsys,
             str(wrong))  # fmt: skip
    _refused([*base, "--format", "joint-states", "--out", str(tmp_path / "s.bag")], capsys, "needs --joints-csv")
    _refused([*states, str(csv), "--storage", "mcap"], capsys, "--storage mcap applies to ROS2 bag folders")
    assert not (tmp_path / "s.bag").exists() and not (tmp_path / "u.urdf").exists()
    # --out equal to an input, or holding one: refused, the input unchanged
    _refused([*base, "--format", "urdf", "--out", str(cal_path), "--force"], capsys, "is the input CALIBRATION")
    _refused([*base, "--format", "kalibr", "--out", str(cal_path), "--joints", "0,0", "--force"], capsys,
             "is the input CALIBRATION")  # fmt: skip
    _refused([*states, str(csv), "--out", str(csv), "--force"], capsys, "is the input --joints-csv")
    _refused([*states, str(csv), "--out", str(calibrated), "--force"], capsys, "holds the input")
    assert cal_path.read_text() == cal_text and csv.is_file()
    # a recording is never replaced by a joint-state bag, not even with --force
    recording = tmp_path / "recording.bag"
    with BagWriter(recording, 1) as bag:
        bag.imu("/imu", STAMP0, np.zeros(3), np.zeros(3))
    _refused([*states, str(csv), "--out", str(recording), "--force"], capsys, "not a joint-state bag")
    _refused([*states, str(csv), "--out", str(tmp_path)], capsys, "exists and is not a joint-state bag")
    (tmp_path / "dir.bag").mkdir()
    _refused([*states, str(csv), "--out", str(tmp_path / "dir.bag")], capsys, "exists as a folder, but names a ROS1")
    # options of another format, names, missing files, a rigid pair has no joint states
    _refused([*base, "--format", "urdf", "--out", str(tmp_path / "u.urdf"), "--joints", "0,0"], capsys,
             "--joints does not apply to --format urdf")  # fmt: skip
    _refused([*base, "--format", "urdf", "--out", str(tmp_path / "u.urdf"), "--joint-names", "a"], capsys,
             "1 name(s) given", "2 joint(s)")  # fmt: skip
    _refused([*base, "--format", "urdf", "--out", str(tmp_path / "u.urdf"), "--joint-names", "a,a"], capsys,
             "distinct")  # fmt: skip
    _refused(["export", str(tmp_path / "nope.yaml"), "--format", "urdf", "--out", str(tmp_path / "u.urdf")], capsys,
             "nope.yaml")  # fmt: skip
    d = yaml.safe_load(cal_text)
    d.update(joints=0, dh=[])
    for key in ("dh_std", "observable", "gauge_fixed", "tau_s_std", "tau_d_std"):
        d.pop(key, None)
    rigid = tmp_path / "rigid.yaml"
    rigid.write_text(yaml.safe_dump(d))
    _refused(["export", str(rigid), "--format", "joint-states", "--joints-csv", str(csv), "--out",
              str(tmp_path / "r.bag")], capsys, str(rigid), "joints: 0")  # fmt: skip
