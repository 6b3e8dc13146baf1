"""Corner-level simulator of the paper's calibration study (section V-A).

Pinned geometry (accuracy depends on it, so it is fixed and documented here):

* two 640x480 pinhole cameras with fx = fy = 460 px (the paper's PointGrey Firefly MV),
  principal point near the centre and mild radial-tangential distortion;
* a 9x7 inner-corner checkerboard with 0.06 m squares (0.48 m x 0.36 m of corners);
* gimbal base ``b`` 0.10 m to the right of the static camera (the paper's ~10 cm baseline),
  joint 1 ("roll") about an axis close to the static camera's optical axis, joint 2
  ("pitch") perpendicular to it through DH twist alpha_1 = 90 deg; joint 1 is centred at
  90 deg so that joint 2 tilts the gimbal camera about its x axis;
* joint ranges: joint 1 in 90 +- 30 deg, joint 2 in +- 12 deg (see :func:`joint_ranges`);
  a mechanism with L = 1 has only the roll joint;
* L = 3 is a different, pan-tilt-roll mechanism (see :func:`true_kinematics`): joint 1 pans about
  an axis close to the static camera's y axis (90 +- 20 deg), joint 2 tilts about the camera's x
  axis (-90 +- 20 deg), joint 3 rolls about the dynamic camera's optical axis (+- 90 deg, which
  keeps the board in view whatever the roll); the links are offset (d, a = 5/6 cm and 4/7 cm) so
  that the axes do not intersect. Three non-parallel axes span all rotations, so the rotation of
  T_ds alone cannot tell the joint angles from small rotations of the mounts and DH twists; only
  the translation (lever arms of a few cm against ~1 mm of per-snapshot translation precision)
  separates them. The joint angles of an L = 3 mechanism are therefore much less precise than for
  L = 2 at the same number of snapshots: with 81 snapshots the offset-free joint-angle CRB is
  5.6e-3 / 6.6e-3 / 8.9e-3 rad (RMS), with 243 snapshots 3.6e-3 / 3.8e-3 / 5.0e-3 rad;
* per snapshot the board is placed 0.6-1.2 m away, between both optical axes, tilted by up to
  20 deg and rolled by up to 15 deg, and re-drawn until every corner is inside both images with
  a 10 px margin (both cameras see the whole board); a joint sample at which 2,000 draws all fail
  (near the corners of the L = 3 ranges) is moved towards the centre of the samples;
* 81 calibration snapshots on a jittered 9 x 9 grid of the joint space (approximately
  uniform), 81 validation snapshots at uniformly random joint angles;
* zero-mean Gaussian pixel noise of 0.4 px per axis;
* initial values: every translation parameter perturbed by N(0, 0.03 m), every rotation
  parameter (Euler angles, DH twists) and every joint angle by N(0, 10 deg).

Everything is seeded. The output is the same :class:`~dcc_fg.data.CalibrationDataset` a real
data set produces; ground truth travels alongside in :class:`SimulatedCalibration`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import gtsam
import numpy as np
from numpy.typing import NDArray

from dcc_fg.data import CalibrationDataset, Observation, Snapshot
from dcc_fg.model import GimbalCalibration
from dcc_fg.targets import TargetGeometry
from factors import chain
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]
DEG = np.pi / 180.0
# Board placement: random target poses drawn per snapshot until one is visible in both cameras. Near
# the corners of the L = 3 joint ranges only ~0.3% of the draws are (seeds 12 and 17 failed with 200
# draws). Moving the joint sample towards the centre is the last resort: JOINT_SHRINK are the
# fractions of its offset from the centre kept, first 1 (the requested sample).
BOARD_TRIES = 2000
JOINT_SHRINK = (1.0, 0.75, 0.5, 0.25, 0.0)


@dataclass(frozen=True)
class SceneConfig:
    """Parameters of the simulated study (defaults = the pinned geometry above)."""

    n_joints: int = 2
    n_calibration: int = 81
    n_validation: int = 81
    pixel_sigma: float = 0.4
    init_translation_sigma: float = 0.03
    init_rotation_sigma: float = 10.0 * DEG
    init_joint_sigma: float = 10.0 * DEG
    distance_range: tuple[float, float] = (0.6, 1.2)
    board_tilt: float = 20.0 * DEG
    board_roll: float = 15.0 * DEG
    margin_px: float = 10.0
    target: TargetGeometry = field(default_factory=lambda: TargetGeometry.checkerboard(9, 7, 0.06))


@dataclass
class SimulatedCalibration:
    """A simulated data set with its ground truth.

    Attributes:
        calibration_set / validation_set: measurements (snapshot ``joints`` hold the perturbed
            initial joint angles).
        truth: the true kinematics.
        initial: the perturbed kinematics (the "hand-measured" starting point).
        joints_calibration / joints_validation: true joint angles (K, L), radians.
        T_st_calibration / T_st_validation: true target poses in the static camera (K, 4, 4).
    """

    calibration_set: CalibrationDataset
    validation_set: CalibrationDataset
    truth: GimbalCalibration
    initial: GimbalCalibration
    joints_calibration: FloatArray
    joints_validation: FloatArray
    T_st_calibration: FloatArray
    T_st_validation: FloatArray
    config: SceneConfig


def default_cameras() -> tuple[CameraModel, CameraModel]:
    """The pinned static and dynamic camera intrinsics."""
    static = CameraModel((460.0, 460.0, 320.5, 240.5), "radtan", (-0.05, 0.01, 0.0005, -0.0003), (640, 480))
    dynamic = CameraModel((461.0, 459.0, 318.0, 242.0), "radtan", (-0.04, 0.008, -0.0004, 0.0002), (640, 480))
    return static, dynamic


def joint_ranges(n_joints: int) -> FloatArray:
    """(L, 2) lower/upper joint limits of the pinned mechanism, radians.

    For L = 3 (pan-tilt-roll), pan and tilt are limited to +- 20 deg by the requirement that both
    cameras see the whole board; the roll about the optical axis does not move the view, so it
    spans +- 90 deg. Joint 2 is centred at -90 deg, where the three axes are mutually
    perpendicular and the roll axis is the dynamic camera's optical axis.
    """
    ranges = {
        0: [],
        1: [(60.0, 120.0)],
        2: [(60.0, 120.0), (-12.0, 12.0)],
        3: [(78.0, 102.0), (-110.0, -70.0), (-55.0, 55.0)],
    }
    if n_joints not in ranges:
        raise ValueError(f"the pinned scene supports 0 to 3 joints, got {n_joints}")
    return np.deg2rad(np.array(ranges[n_joints], dtype=float)).reshape(n_joints, 2)


def true_kinematics(n_joints: int) -> GimbalCalibration:
    """The pinned true mechanism for ``n_joints`` in {0, 1, 2, 3}.

    The dynamic camera sits 0.10 m to the right of the static camera and looks roughly along the
    static camera's optical axis at the centre of the joint ranges; small rotations make the
    geometry generic.
    """
    dh_all = np.array(
        [
            [0.030, 0.020, 90.0 * DEG],  # joint 1: roll axis ~ static optical axis, twist to pitch axis
            [0.012, 0.015, -90.0 * DEG],  # joint 2: pitch
            [0.010, 0.012, 90.0 * DEG],  # joint 3 (L = 3 only)
        ]
    )
    dh = dh_all[:n_joints]
    # base frame: axes ~ static camera axes (small rotation), origin 0.10 m to the right
    tau_s = np.array([1.5 * DEG, -2.0 * DEG, 3.0 * DEG, -0.10, 0.012, 0.025])
    if n_joints == 3:
        # pan-tilt-roll: base z (pan axis) ~ the static camera's y axis (tau_s.rx ~ 90 deg); twists
        # of 90 deg make tilt and roll axes perpendicular. Three intersecting axes would form a
        # spherical wrist whose joint angles absorb any rotation of the mounts exactly (a gauge),
        # so the links are offset by several cm.
        dh = np.array([[0.120, 0.100, 90.0 * DEG], [0.120, 0.050, 90.0 * DEG], [0.010, 0.012, 0.0]])
        tau_s[0] += 90.0 * DEG
    theta_mid = joint_ranges(n_joints).mean(axis=1) if n_joints else np.zeros(0)
    # desired T_ds at mid-range: dynamic camera centre at (0.10, -0.005, 0.01) in s, small rotation
    R_ds = chain.rot_z(2.0 * DEG) @ chain.rot_y(-1.5 * DEG) @ chain.rot_x(1.0 * DEG)
    c_s = np.array([0.10, -0.005, 0.01])
    T_ds_mid = np.eye(4)
    T_ds_mid[:3, :3] = R_ds
    T_ds_mid[:3, 3] = -R_ds @ c_s
    T_eb_mid = chain.T_eb(dh, theta_mid)
    T_de = T_ds_mid @ chain.inv_se3(T_eb_mid @ chain.se3_from_tau(tau_s))
    tau_d = chain.tau_from_se3(T_de)
    static, dynamic = default_cameras()
    return GimbalCalibration.from_parts(tau_s, tau_d, dh, static_camera=static, dynamic_camera=dynamic)


def perturb_kinematics(cal: GimbalCalibration, cfg: SceneConfig, rng: np.random.Generator) -> GimbalCalibration:
    """Initial guess: translations + N(0, sigma_t), rotations + N(0, sigma_r)."""
    is_angle = chain.kin_is_angle(cal.n_joints)
    sigma = np.where(is_angle, cfg.init_rotation_sigma, cfg.init_translation_sigma)
    kin = cal.kin + rng.normal(size=cal.kin.shape) * sigma
    return GimbalCalibration(kin, cal.n_joints, cal.static_camera, cal.dynamic_camera)


def grid_joint_samples(n: int, ranges: FloatArray, rng: np.random.Generator) -> FloatArray:
    """~Uniform coverage of the joint space: a jittered grid with ``n`` cells (n^(1/L) per axis)."""
    L = ranges.shape[0]
    if L == 0:
        return np.zeros((n, 0))
    per_axis = max(1, int(round(n ** (1.0 / L))))
    axes = [np.arange(per_axis) for _ in range(L)]
    cells = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, L)
    if cells.shape[0] < n:  # pad with random cells when n is not a perfect power
        extra = rng.integers(0, per_axis, size=(n - cells.shape[0], L))
        cells = np.vstack([cells, extra])
    cells = cells[:n]
    u = (cells + rng.uniform(0.1, 0.9, size=cells.shape)) / per_axis
    return ranges[:, 0] + u * (ranges[:, 1] - ranges[:, 0])


def _place_board(
    T_ds: FloatArray,
    target: TargetGeometry,
    cams: tuple[CameraModel, CameraModel],
    cfg: SceneConfig,
    rng: np.random.Generator,
    tries: int = BOARD_TRIES,
) -> FloatArray | None:
    """Draw a target pose T_st fully visible (with margin) in both cameras; None after ``tries`` draws.

    Each draw consumes the same random numbers, so a pose found within the first n draws does not
    depend on ``tries`` >= n.
    """
    pts_t = target.points
    centre_t = pts_t.mean(axis=0)
    R_sd = T_ds[:3, :3].T
    c_d = -R_sd @ T_ds[:3, 3]  # dynamic camera centre in s
    for _ in range(tries):
        dist = rng.uniform(*cfg.distance_range)
        aim = 0.5 * (np.array([0.0, 0.0, dist]) + c_d + dist * R_sd[:, 2])
        aim += rng.normal(scale=0.02, size=3)
        # board faces the cameras: board z axis points away from the cameras (towards +z_s)
        tilt_axis = rng.normal(size=2)
        tilt_axis /= np.linalg.norm(tilt_axis)
        tilt = rng.uniform(0.0, cfg.board_tilt)
        R_tilt = _axis_angle(np.array([tilt_axis[0], tilt_axis[1], 0.0]), tilt)
        R_st = R_tilt @ chain.rot_z(rng.uniform(-cfg.board_roll, cfg.board_roll))
        T_st = np.eye(4)
        T_st[:3, :3] = R_st
        T_st[:3, 3] = aim - R_st @ centre_t
        p_s = pts_t @ R_st.T + T_st[:3, 3]
        p_d = p_s @ T_ds[:3, :3].T + T_ds[:3, 3]
        ok = True
        for cam, p in zip(cams, (p_s, p_d), strict=True):
            uv, _ = cam.project(p, jacobian=False)
            ok &= bool(np.all(cam.in_front(p)) and np.all(cam.in_image(uv, cfg.margin_px)))
        if ok:
            return T_st
    return None


def _axis_angle(axis: FloatArray, angle: float) -> FloatArray:
    axis = axis / np.linalg.norm(axis)
    K = chain.skew(axis)
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K


def simulate_snapshots(
    truth: GimbalCalibration,
    joints: FloatArray,
    cfg: SceneConfig,
    rng: np.random.Generator,
    source: str,
    t0_ns: int = 1_000_000_000,
) -> tuple[CalibrationDataset, FloatArray, FloatArray]:
    """Render corner measurements for the given true joint angles (K, L), rad.

    A joint sample at which ``BOARD_TRIES`` random board poses all leave a corner outside an image
    is moved towards the mean of ``joints`` (fractions ``JOINT_SHRINK`` of its offset kept) until
    the board fits; joints that are the same in every sample (a locked joint) stay unchanged.

    Returns the data set (snapshot ``joints`` = true angles + N(0, init_joint_sigma)), the true
    joint angles actually used (K, L) and the true target poses T_st (K, 4, 4).
    """
    cams = (truth.static_camera, truth.dynamic_camera)
    assert cams[0] is not None and cams[1] is not None
    pts_t = cfg.target.points
    ids = np.arange(pts_t.shape[0])
    snaps, poses = [], []
    joints = np.array(joints, dtype=float).reshape(len(joints), truth.n_joints)
    centre = joints.mean(axis=0) if len(joints) else np.zeros(truth.n_joints)
    for k in range(len(joints)):
        T_st = None
        for shrink in JOINT_SHRINK:
            # a joint sample where no board pose is visible to both cameras moves towards the centre
            theta = joints[k] if shrink == 1.0 else centre + shrink * (joints[k] - centre)
            T_ds = truth.T_ds(theta)
            T_st = _place_board(T_ds, cfg.target, (cams[0], cams[1]), cfg, rng)
            if T_st is not None:
                joints[k] = theta
                break
        if T_st is None:
            raise RuntimeError(
                f"could not place the board in view of both cameras at joint angles {joints[k]} rad, nor closer "
                "to the centre of the requested angles; check the scene geometry"
            )
        p_s = pts_t @ T_st[:3, :3].T + T_st[:3, 3]
        p_d = p_s @ T_ds[:3, :3].T + T_ds[:3, 3]
        uv_s = cams[0].project(p_s, jacobian=False)[0] + rng.normal(scale=cfg.pixel_sigma, size=(len(ids), 2))
        uv_d = cams[1].project(p_d, jacobian=False)[0] + rng.normal(scale=cfg.pixel_sigma, size=(len(ids), 2))
        guess = theta + rng.normal(scale=cfg.init_joint_sigma, size=theta.shape)
        snaps.append(Snapshot(t0_ns + k * 100_000_000, Observation(ids, uv_s), Observation(ids, uv_d), guess))
        poses.append(T_st)
    data = CalibrationDataset(cams[0], cams[1], pts_t, snaps, source)
    return data, joints, np.array(poses)


def mechanism_with_camera_at(
    tau_s: FloatArray, dh: FloatArray, theta_mid: FloatArray, T_ds_mid: FloatArray
) -> GimbalCalibration:
    """The mechanism whose end-effector mount ``tau_d`` puts the dynamic camera at ``T_ds_mid``
    when the joints are at ``theta_mid`` (pinned cameras)."""
    T_de = T_ds_mid @ chain.inv_se3(chain.T_eb(dh, theta_mid) @ chain.se3_from_tau(tau_s))
    static, dynamic = default_cameras()
    return GimbalCalibration.from_parts(
        tau_s, chain.tau_from_se3(T_de), dh, static_camera=static, dynamic_camera=dynamic
    )


def random_mechanism(
    rng: np.random.Generator,
    n_joints: int,
    max_link: float = 0.10,
    half_range_deg: tuple[float, float] = (8.0, 15.0),
    twist_deg: tuple[float, float] = (20.0, 160.0),
) -> tuple[GimbalCalibration, FloatArray]:
    """A random DCC mechanism and joint ranges with both cameras seeing the board.

    * base mount: uniformly random rotation (any joint-1 axis direction), base origin within
      0.15 m of the static camera;
    * DH links: d, a uniform in [-max_link, max_link] m; twists alpha of random sign with magnitude
      uniform in ``twist_deg`` (deg). A gimbal's consecutive axes are not parallel (parallel axes
      would not give the camera an independent rotation; they make the DH d of the link and the
      split of the rotation between the joints unobservable at these joint ranges), so twists
      within 20 deg of 0 or 180 deg are not drawn;
    * joint ranges: random centre, half width uniform in ``half_range_deg`` (deg) per joint;
    * the dynamic camera mount ``tau_d`` is whatever puts the dynamic camera ~0.10 m to the
      right of the static camera, looking along its optical axis (+- 5 deg, +- 2 cm) at the
      centre of the ranges: the cameras must share the view of the board.

    Degenerate draws (nearly parallel axes, Euler singularities) are possible and not filtered.
    """
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    R_bs = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    T_bs = np.eye(4)
    T_bs[:3, :3] = R_bs
    T_bs[:3, 3] = -R_bs @ (np.array([0.10, 0.0, 0.0]) + rng.uniform(-0.05, 0.05, size=3))
    tau_s = chain.tau_from_se3(T_bs)
    dh = np.column_stack(
        [
            rng.uniform(-max_link, max_link, size=n_joints),
            rng.uniform(-max_link, max_link, size=n_joints),
            rng.choice([-1.0, 1.0], size=n_joints) * rng.uniform(*twist_deg, size=n_joints) * DEG,
        ]
    )
    centre = rng.uniform(-np.pi, np.pi, size=n_joints)
    half = np.deg2rad(rng.uniform(*half_range_deg, size=n_joints))
    ranges = np.column_stack([centre - half, centre + half])
    R_ds = _axis_angle(rng.normal(size=3), np.deg2rad(rng.uniform(0.0, 5.0)))
    c_s = np.array([0.10, 0.0, 0.0]) + rng.uniform(-0.02, 0.02, size=3)
    T_ds_mid = np.eye(4)
    T_ds_mid[:3, :3] = R_ds
    T_ds_mid[:3, 3] = -R_ds @ c_s
    return mechanism_with_camera_at(tau_s, dh, centre, T_ds_mid), ranges


def simulate_calibration(
    seed: int = 0,
    config: SceneConfig | None = None,
    mechanism: tuple[GimbalCalibration, FloatArray] | None = None,
) -> SimulatedCalibration:
    """Simulate the paper's study: calibration + validation sets, truth and perturbed initial values.

    ``mechanism``: (true kinematics, joint ranges (L, 2) rad) to use instead of the pinned one
    (for example from :func:`random_mechanism`); ``config.n_joints`` is then ignored.
    """
    cfg = config or SceneConfig()
    rng = np.random.default_rng(seed)
    if mechanism is None:
        truth = true_kinematics(cfg.n_joints)
        ranges = joint_ranges(cfg.n_joints)
    else:
        truth, ranges = mechanism
        cfg = replace(cfg, n_joints=truth.n_joints)
    theta_cal = grid_joint_samples(cfg.n_calibration, ranges, rng)
    theta_val = ranges[:, 0] + rng.uniform(size=(cfg.n_validation, cfg.n_joints)) * (ranges[:, 1] - ranges[:, 0])
    cal_set, th_c, T_c = simulate_snapshots(truth, theta_cal, cfg, rng, f"simulation(seed={seed}, calibration)")
    val_set, th_v, T_v = simulate_snapshots(
        truth, theta_val, cfg, rng, f"simulation(seed={seed}, validation)", t0_ns=100_000_000_000
    )
    initial = perturb_kinematics(truth, cfg, rng)
    return SimulatedCalibration(cal_set, val_set, truth, initial, th_c, th_v, T_c, T_v, cfg)


def yaw_roll_pitch_gimbal(
    seed: int, n_snapshots: int = 20, offset_m: float = 0.0, pixel_sigma: float = 0.3
) -> SimulatedCalibration:
    """A yaw-roll-pitch camera gimbal: three axes that intersect in one point (a spherical wrist: DH
    a = d = 0 except d_1 up to 3 cm, twists +-90 deg), joint 2 centred at 90 deg (clear of gimbal
    lock), half ranges 25 / 20 / 25 deg, a random base mount ~8 cm from the static camera and the
    dynamic camera 10 cm beside the wrist. ``offset_m > 0``: the axes miss each other by random link
    offsets (a_1, d_2, a_2) up to that many metres (drawn last, so the intersecting scene of a seed
    stays the same). Gaussian corner noise ``pixel_sigma`` px; ``seed`` draws the mechanism and the scene."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=4)
    R_bs = gtsam.Rot3.Quaternion(*(q / np.linalg.norm(q))).matrix()
    T_bs = np.eye(4)
    T_bs[:3, :3] = R_bs
    T_bs[:3, 3] = -R_bs @ (np.array([0.08, 0.0, 0.0]) + rng.uniform(-0.02, 0.02, size=3))
    dh = np.zeros((3, 3))
    dh[0, 0] = rng.uniform(-0.03, 0.03)
    dh[:, 2] = rng.choice([-1.0, 1.0], size=3) * np.pi / 2
    centre = np.array([rng.uniform(-np.pi, np.pi), np.pi / 2, rng.uniform(-np.pi, np.pi)])
    half = np.deg2rad([25.0, 20.0, 25.0])
    T_ds_mid = np.eye(4)
    T_ds_mid[:3, 3] = [-0.10, 0.0, 0.0]
    if offset_m > 0.0:
        dh[0, 1], dh[1, 0], dh[1, 1] = rng.uniform(-offset_m, offset_m, size=3)
    truth = mechanism_with_camera_at(chain.tau_from_se3(T_bs), dh, centre, T_ds_mid)
    ranges = np.column_stack([centre - half, centre + half])
    cfg = SceneConfig(n_calibration=n_snapshots, n_validation=1, pixel_sigma=pixel_sigma)
    return simulate_calibration(seed, cfg, mechanism=(truth, ranges))
