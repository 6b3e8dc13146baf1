"""A randomized family of gimbal mechanisms, cameras and targets (issue 14).

``family_member(seed)`` draws one complete calibration scenario; ``simulate_member`` simulates its
corner-level data set (:func:`dcc_fg.sim.calibration_scene.simulate_calibration`), and
``dcc-fg simulate calibration --random-mechanism SEED`` renders it into images. The family is meant
to test the calibration on geometries it was not developed on.

Frames and symbols as in ``docs/architecture.md``: ``s`` static camera (x right, y down, z along the
optical axis), ``d`` dynamic (gimbal) camera, ``b`` gimbal base, DH links
``A_l = Rz(theta_l) Tz(d_l) Tx(a_l) Rx(alpha_l)``; metres, radians (degrees where a name says so),
pixels where a name says so.

Random streams: ``np.random.SeedSequence([FAMILY_STREAM, seed]).spawn(4)`` gives four independent
generators, one each for the kinematics (L, DH parameters, joint ranges), the mounts (base pose,
dynamic camera placement), the two cameras' intrinsics and the target. So a caller who fixes
``n_joints`` changes only the kinematics: the same seed keeps its cameras, target and mounts for
every L. (The corner-level scene of the member is then simulated from ``default_rng(seed)`` by
``simulate_calibration``; the family's own streams keep the mechanism draws from being the same
numbers as the scene's joint-sample jitter.) ``n_joints`` and ``n_snapshots`` are fixed by the
caller when given.

The family:

* joints L: uniform in {1, 2, 3} unless ``n_joints`` is given;
* link offsets: with probability 1/4 the joint axes intersect exactly in one point (the "wrist",
  as on commercial yaw-roll-pitch gimbals): ``a_l = 0`` for l < L and ``d_l = 0`` for
  2 <= l < L; ``d_1`` (slides the wrist along joint 1's axis) and the last link's ``d_L, a_L``
  (absorbed by the camera mount ``tau_d``) stay free. Otherwise (and for those free entries) each
  ``|d_l|``, ``|a_l|`` is log-uniform in [1 mm, 10 cm] with a random sign. For L = 1 there is no
  second axis: ``intersecting_axes`` then only records the draw;
* twists: per mechanism, with probability 1/2 every ``alpha_l`` is "near 90 deg"
  (``+-(90 + U(-5, 5))`` deg, random sign per joint), else every ``|alpha_l|`` is uniform in
  [20, 160] deg with a random sign (consecutive axes are never within 20 deg of parallel);
* joint ranges: per joint a centre uniform in [-180, 180) deg and a half width uniform in
  [8, 60] deg; ``ranges`` holds ``centre -+ half``, rad. For L = 3, joint 2's range keeps joints
  1 and 3 at least ``WRIST_CLEARANCE_DEG`` (20 deg) from parallel (gimbal lock, where the joint
  angles are not determined; commercial gimbals keep their range clear of it): its centre is
  redrawn, and its half width narrowed by 10 % steps where no centre works;
* base mount: ``R_bs`` uniformly random; the wrist point (intersecting axes) or the base origin
  (otherwise) at a uniformly random direction, 5-15 cm from the static camera centre;
* dynamic camera: the mount ``tau_d`` puts the dynamic camera, with the joints at the range
  centre, 5-20 cm from the static camera in a uniformly random direction in the static camera's
  x-y plane (plus U(-2, 2) cm along z), rotated from the static camera by at most 5 deg (random
  axis): both cameras look roughly the same way at the range centre;
* intrinsics, per camera independently: resolution uniform from (640, 480), (752, 480),
  (1024, 768), (1280, 720); horizontal field of view uniform in [50, 90] deg, from which
  ``fx = (W / 2) / tan(hfov / 2)`` (radtan) or ``fx = (W / 2) / (hfov / 2)`` (equidistant, where
  the image radius is proportional to the ray angle); ``fy = fx * (1 + U(-1, 1) %)``; principal
  point within 3 % of the image size from the centre; distortion with probability 1/2 each
  ``radtan`` (k1 in [-0.3, 0.1], k2 in [-0.05, 0.05], p1, p2 in [-1e-3, 1e-3]) or ``equidistant``
  (k1 in [-0.05, 0.05], k2 in [-0.02, 0.02], k3, k4 in [-0.01, 0.01]). A draw whose radial
  distortion folds (derivative of the distorted radius below ``MIN_RADIAL_SLOPE``) anywhere up to
  the image corners, or whose pixels do not round-trip through undistortion, is redrawn (only the
  distortion coefficients; wide lenses therefore rarely get the strongest barrel k1);
* target, probability 1/2 each: a checkerboard with odd x even inner corners (one count from
  {7, 9, 11}, the other from {6, 8}, which one is columns is random; square uniform in [3, 8] cm,
  rounded to the millimetre) or a Kalibr AprilGrid (4-7 tags per side, tags uniform in [3, 8] cm
  rounded to the millimetre, spacing ratio 0.3);
* board distance: ``distance_range = (z_min, z_max)``. ``z_min`` is ``DISTANCE_SLACK`` (1.2) times
  the smallest distance (from ``1.1 (D + b) f / short_side`` of the narrower camera, growing by
  10 % steps, D the corner set's diagonal, b the camera baseline) at which the untilted board,
  aimed as the scene aims it (half way between both optical axes), has every corner at least
  ``2 * margin_px`` inside both images with the joints at the range centre, both there and at
  twice that distance. ``z_max = min(2 z_min, z_detect)`` where at ``z_detect`` a checkerboard
  square is ``MIN_SQUARE_PX`` (10) px, an AprilGrid tag ``MIN_TAG_PX`` (24) px, at the smaller
  focal length of the two cameras (what a detector needs in the wider camera); a target with
  ``z_detect < 1.3 z_min`` (too fine for this camera pair) is redrawn (same kind: the kind is
  drawn once, so each kind keeps probability 1/2; counts and sizes redrawn), up to ``TARGET_TRIES``
  (100) times; if none is coarse enough (very different focal lengths) the draw with the largest
  ``z_detect / z_min`` is kept with ``z_max = 1.3 z_min``. The board then covers
  roughly 35-75 % of the narrower image's short side;
* scene: ``n_snapshots`` calibration snapshots on the scene's jittered grid over the ranges, no
  validation set, ``pixel_sigma = 0.3`` px (corner-level use only; rendered images carry detector
  noise), the scene's default board tilt (20 deg), roll (15 deg), margin (10 px) and initial-value
  perturbation.

Achieved joint spread: large ranges turn the gimbal camera away from the board. The scene then
moves such joint samples towards the centre (``JOINT_SHRINK`` in
:mod:`dcc_fg.sim.calibration_scene`), so the true angles used can span less than the requested
range. ``description["half_range_deg"]`` is the requested (drawn) half width;
:func:`achieved_spread` gives the spread of the angles actually simulated (``simulate calibration
--random-mechanism`` writes both into ``ground_truth.yaml``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dcc_fg.model import GimbalCalibration
from dcc_fg.sim.calibration_scene import SceneConfig, SimulatedCalibration, simulate_calibration
from dcc_fg.targets import TargetGeometry
from factors import chain
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]
DEG = np.pi / 180.0

FAMILY_STREAM = 14  # first entry of the family's seed sequence (issue 14)
RESOLUTIONS = ((640, 480), (752, 480), (1024, 768), (1280, 720))
HFOV_DEG = (50.0, 90.0)
LINK_RANGE_M = (1e-3, 0.10)
P_INTERSECTING = 0.25
P_NEAR_90 = 0.5
NEAR_90_DEG = 5.0
TWIST_DEG = (20.0, 160.0)
HALF_RANGE_DEG = (8.0, 60.0)
BASE_DISTANCE_M = (0.05, 0.15)
BASELINE_M = (0.05, 0.20)
MOUNT_ROTATION_DEG = 5.0
PIXEL_SIGMA = 0.3
#: the near end of the distance range is this factor beyond the closest fitting distance (room for tilts)
DISTANCE_SLACK = 1.2
#: smallest accepted d(distorted radius)/d(radius) up to the image corners (1 = no distortion)
MIN_RADIAL_SLOPE = 0.2
DISTORTION_TRIES = 100
#: smallest checkerboard square / AprilGrid tag side, pixels, in the wider camera at the far distance
MIN_SQUARE_PX = 10.0
MIN_TAG_PX = 24.0
TARGET_TRIES = 100
MIN_DEPTH_SPAN = 1.3  # z_max / z_min at least


@dataclass(frozen=True)
class FamilyMember:
    """One drawn scenario.

    Attributes:
        seed: the family seed (also the seed of the corner-level scene, see :func:`simulate_member`).
        truth: true kinematics with the member's own ``static_camera`` / ``dynamic_camera``.
        ranges: (L, 2) lower / upper joint limits, rad.
        scene: the corner-level scene (target, distance range, ``n_calibration`` = snapshots,
            ``n_validation`` = 0).
        target_kind: ``checkerboard`` or ``aprilgrid``.
        description: JSON/YAML-able summary of the draw (plain floats, ints, bools, strings).
    """

    seed: int
    truth: GimbalCalibration
    ranges: FloatArray
    scene: SceneConfig
    target_kind: str
    description: dict[str, Any]


WRIST_CLEARANCE_DEG = 20.0  # L = 3: joints 1 and 3 stay this far from parallel (gimbal lock)


def _random_rotation(rng: np.random.Generator) -> FloatArray:
    """Uniformly distributed rotation matrix (normalized Gaussian quaternion)."""
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _axis_angle(axis: FloatArray, angle: float) -> FloatArray:
    axis = axis / np.linalg.norm(axis)
    K = chain.skew(axis)
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K


def _unit_vector(rng: np.random.Generator) -> FloatArray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _log_uniform_signed(rng: np.random.Generator, size: int) -> FloatArray:
    lo, hi = np.log(LINK_RANGE_M[0]), np.log(LINK_RANGE_M[1])
    return rng.choice([-1.0, 1.0], size=size) * np.exp(rng.uniform(lo, hi, size=size))


def _radial_profile_ok(camera: CameraModel) -> bool:
    """The radial distortion is monotonic (slope >= MIN_RADIAL_SLOPE) up to beyond the image corners."""
    fx, fy, cx, cy = camera.intrinsics
    w, h = camera.resolution
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    r_corner = float(np.max(np.hypot((corners[:, 0] - cx) / fx, (corners[:, 1] - cy) / fy)))
    need = 1.05 * r_corner  # distorted radius (normalized) the profile must reach, monotonically
    c = camera.distortion_coeffs
    if camera.distortion_model == "radtan":
        r = np.linspace(0.0, 5.0, 20001)
        r_d = r * (1.0 + c[0] * r**2 + c[1] * r**4)
        slope = 1.0 + 3.0 * c[0] * r**2 + 5.0 * c[1] * r**4
    else:  # equidistant: distorted radius = theta_d(theta), theta the ray angle < 90 deg
        th = np.linspace(0.0, 0.5 * np.pi - 1e-3, 20001)
        r_d = th * (1.0 + c[0] * th**2 + c[1] * th**4 + c[2] * th**6 + c[3] * th**8)
        slope = 1.0 + 3.0 * c[0] * th**2 + 5.0 * c[1] * th**4 + 7.0 * c[2] * th**6 + 9.0 * c[3] * th**8
    reach = np.nonzero(r_d >= need)[0]
    if reach.size == 0:
        return False
    return bool(np.all(slope[: reach[0] + 1] >= MIN_RADIAL_SLOPE))


def distortion_is_monotonic(camera: CameraModel) -> bool:
    """True when the lens model does not fold over the image.

    Two checks: the radial profile (distorted against undistorted radius, or against the ray angle
    for ``equidistant``) has slope >= ``MIN_RADIAL_SLOPE`` from the centre to 5 % beyond the image
    corners' radius; and a 17 x 13 grid of pixels over the whole image (borders included)
    round-trips through :meth:`~factors.camera.CameraModel.undistort_points` and back to 1e-6 px
    with a distortion Jacobian determinant >= ``MIN_RADIAL_SLOPE**2``.
    """
    if camera.distortion_model == "none":
        return True
    if not _radial_profile_ok(camera):
        return False
    w, h = camera.resolution
    uu, vv = np.meshgrid(np.linspace(-0.5, w - 0.5, 17), np.linspace(-0.5, h - 0.5, 13))
    uv = np.stack([uu.ravel(), vv.ravel()], axis=1)
    xy = camera.undistort_points(uv)
    if not np.all(np.isfinite(xy)):
        return False
    if camera.distortion_model == "equidistant" and np.max(np.hypot(xy[:, 0], xy[:, 1])) > 1e3:
        return False
    back, _ = camera.project(np.column_stack([xy, np.ones(len(xy))]), jacobian=False)
    _, J = camera.distort(xy)
    return bool(np.max(np.abs(back - uv)) < 1e-6 and np.min(np.linalg.det(J)) >= MIN_RADIAL_SLOPE**2)


def _draw_camera(rng: np.random.Generator) -> tuple[CameraModel, float]:
    """One random camera (see the module docstring) and its horizontal field of view, deg."""
    w, h = RESOLUTIONS[int(rng.integers(len(RESOLUTIONS)))]
    hfov = float(rng.uniform(*HFOV_DEG))
    model = "radtan" if rng.uniform() < 0.5 else "equidistant"
    half = 0.5 * hfov * DEG
    fx = 0.5 * w / (np.tan(half) if model == "radtan" else half)
    fy = fx * (1.0 + rng.uniform(-0.01, 0.01))
    cx = 0.5 * (w - 1) + rng.uniform(-0.03, 0.03) * w
    cy = 0.5 * (h - 1) + rng.uniform(-0.03, 0.03) * h
    intr = (float(fx), float(fy), float(cx), float(cy))
    for _ in range(DISTORTION_TRIES):
        if model == "radtan":
            coeffs = (
                rng.uniform(-0.3, 0.1), rng.uniform(-0.05, 0.05), rng.uniform(-1e-3, 1e-3), rng.uniform(-1e-3, 1e-3)
            )  # fmt: skip
        else:
            coeffs = (
                rng.uniform(-0.05, 0.05), rng.uniform(-0.02, 0.02), rng.uniform(-0.01, 0.01), rng.uniform(-0.01, 0.01)
            )  # fmt: skip
        cam = CameraModel(intr, model, tuple(float(c) for c in coeffs), (w, h))
        if distortion_is_monotonic(cam):
            return cam, hfov
    raise RuntimeError(f"no monotonic {model} distortion in {DISTORTION_TRIES} draws (hfov {hfov:.1f} deg)")


def _draw_target(rng: np.random.Generator, kind: str) -> TargetGeometry:
    """A random board of the given kind (see the module docstring)."""
    if kind == "checkerboard":
        odd = int(rng.choice([7, 9, 11]))
        even = int(rng.choice([6, 8]))
        cols, rows = (odd, even) if rng.uniform() < 0.5 else (even, odd)
        square = round(float(rng.uniform(0.03, 0.08)), 3)
        return TargetGeometry.checkerboard(cols, rows, square)
    cols, rows = (int(x) for x in rng.integers(4, 8, size=2))
    tag = round(float(rng.uniform(0.03, 0.08)), 3)
    return TargetGeometry.aprilgrid(cols, rows, tag, 0.3)


def _board_fits(
    T_ds: FloatArray, pts: FloatArray, cams: tuple[CameraModel, CameraModel], dist: float, margin: float
) -> bool:
    """Untilted board (corners ``pts`` (M, 3) in the target frame, m) aimed as the scene aims it (half
    way between the optical axes at ``dist``): every corner in front of and ``margin`` px inside both
    images."""
    R_sd = T_ds[:3, :3].T
    c_d = -R_sd @ T_ds[:3, 3]
    aim = 0.5 * (np.array([0.0, 0.0, dist]) + c_d + dist * R_sd[:, 2])
    p_s = pts - pts.mean(axis=0) + aim
    p_d = p_s @ T_ds[:3, :3].T + T_ds[:3, 3]
    for cam, p in zip(cams, (p_s, p_d), strict=True):
        uv, _ = cam.project(p, jacobian=False)
        if not (np.all(cam.in_front(p)) and np.all(cam.in_image(uv, margin))):
            return False
    return True


def _feature_m(target: TargetGeometry) -> tuple[float, float]:
    """(size of the detector's feature in metres, smallest size in pixels it needs): a checkerboard
    square, an AprilGrid tag."""
    if target.target_type == "checkerboard":
        return min(target.col_spacing, target.row_spacing), MIN_SQUARE_PX
    return target.tag_size, MIN_TAG_PX


def _distance_range(
    T_ds_mid: FloatArray, target: TargetGeometry, cams: tuple[CameraModel, CameraModel], margin: float
) -> tuple[float, float]:
    """(z_min, z_detect), metres (see the module docstring)."""
    pts = target.points
    diag = float(np.hypot(*np.ptp(pts[:, :2], axis=0)))
    baseline = float(np.linalg.norm(T_ds_mid[:3, 3]))
    z = max(1.1 * (diag + baseline) * max(c.intrinsics[:2]) / min(c.resolution) for c in cams)
    for _ in range(60):
        if _board_fits(T_ds_mid, pts, cams, z, 2.0 * margin) and _board_fits(
            T_ds_mid, pts, cams, 2.0 * z, 2.0 * margin
        ):
            z *= DISTANCE_SLACK
            size, min_px = _feature_m(target)
            return z, min(min(c.intrinsics[:2]) for c in cams) * size / min_px
        z *= 1.1
    raise RuntimeError("no board distance fits both images at the range centre")


def _axes_1_3_cosine(alphas: FloatArray, theta_2: FloatArray) -> FloatArray:
    """cos of the angle between joint 1's and joint 3's axes at joint-2 angles ``theta_2`` (rad):
    ``e_z . Rx(alpha_1) Rz(theta_2) Rx(alpha_2) e_z`` (joint 1's angle turns about its own axis)."""
    a1, a2 = float(alphas[0]), float(alphas[1])
    return -np.sin(a1) * np.cos(theta_2) * np.sin(a2) + np.cos(a1) * np.cos(a2)


def _clear_of_wrist_singularity(
    alphas: FloatArray, centre: float, half_deg: float, rng: np.random.Generator
) -> tuple[float, float]:
    """Joint 2's range centre (rad) and half width (deg) such that joints 1 and 3 stay at least
    ``WRIST_CLEARANCE_DEG`` from parallel over the range (where they are parallel, a 3-axis gimbal
    loses a degree of freedom: gimbal lock; real gimbals keep their range clear of it). The centre
    is redrawn, and the half width narrowed when no centre works."""
    limit = np.cos(np.deg2rad(WRIST_CLEARANCE_DEG))
    for _ in range(200):
        grid = centre + np.deg2rad(half_deg) * np.linspace(-1.0, 1.0, 41)
        if np.max(np.abs(_axes_1_3_cosine(alphas, grid))) <= limit:
            return centre, half_deg
        centre = float(rng.uniform(-np.pi, np.pi))
        half_deg = max(HALF_RANGE_DEG[0], 0.9 * half_deg)
    raise RuntimeError(f"twists {np.rad2deg(alphas[:2])} deg leave joints 1 and 3 near parallel everywhere")


def _camera_dict(cam: CameraModel, hfov_deg: float) -> dict[str, Any]:
    return {
        "model": cam.distortion_model,
        "resolution": [int(x) for x in cam.resolution],
        "intrinsics": [float(x) for x in cam.intrinsics],
        "distortion": [float(x) for x in cam.distortion_coeffs],
        "hfov_deg": float(hfov_deg),
    }


def family_member(seed: int, n_joints: int | None = None, n_snapshots: int = 40) -> FamilyMember:
    """Draw member ``seed`` of the family (see the module docstring).

    Args:
        seed: >= 0.
        n_joints: L in {1, 2, 3}; None draws it uniformly.
        n_snapshots: calibration snapshots of the scene (>= 1).
    """
    if seed < 0:
        raise ValueError(f"the family seed must be >= 0, got {seed}")
    if n_joints is not None and n_joints not in (1, 2, 3):
        raise ValueError(f"the mechanism family has 1 to 3 joints, got {n_joints}")
    if n_snapshots < 1:
        raise ValueError(f"n_snapshots must be >= 1, got {n_snapshots}")
    rng, rng_mount, rng_cam, rng_target = (
        np.random.default_rng(s) for s in np.random.SeedSequence([FAMILY_STREAM, seed]).spawn(4)
    )
    drawn_L = int(rng.integers(1, 4))
    L = drawn_L if n_joints is None else n_joints

    # DH links
    intersecting = bool(rng.uniform() < P_INTERSECTING)
    d = _log_uniform_signed(rng, L)
    a = _log_uniform_signed(rng, L)
    if intersecting:
        a[: L - 1] = 0.0
        d[1 : L - 1] = 0.0
    near_90 = bool(rng.uniform() < P_NEAR_90)
    signs = rng.choice([-1.0, 1.0], size=L)
    if near_90:
        twist_deg = signs * (90.0 + rng.uniform(-NEAR_90_DEG, NEAR_90_DEG, size=L))
    else:
        twist_deg = signs * rng.uniform(*TWIST_DEG, size=L)
    dh = np.column_stack([d, a, twist_deg * DEG])

    # joint ranges
    centre = rng.uniform(-np.pi, np.pi, size=L)
    half_deg = rng.uniform(*HALF_RANGE_DEG, size=L)
    if L == 3:
        centre[1], half_deg[1] = _clear_of_wrist_singularity(
            dh[:, 2], centre[1], half_deg[1], np.random.default_rng([FAMILY_STREAM, seed, 3])
        )
    ranges = np.column_stack([centre - half_deg * DEG, centre + half_deg * DEG])

    # base mount: wrist point (intersecting axes) or base origin 5-15 cm from the static camera
    R_bs = _random_rotation(rng_mount)
    point_s = _unit_vector(rng_mount) * rng_mount.uniform(*BASE_DISTANCE_M)
    origin_s = point_s - d[0] * R_bs[2, :] if intersecting else point_s  # R_bs[2, :] = base z axis in s
    T_bs = np.eye(4)
    T_bs[:3, :3] = R_bs
    T_bs[:3, 3] = -R_bs @ origin_s
    tau_s = chain.tau_from_se3(T_bs)

    # dynamic camera at the range centre: 5-20 cm to the side, looking along the static optical axis
    phi = rng_mount.uniform(0.0, 2.0 * np.pi)
    baseline = rng_mount.uniform(*BASELINE_M)
    c_s = np.array([baseline * np.cos(phi), baseline * np.sin(phi), rng_mount.uniform(-0.02, 0.02)])
    R_ds = _axis_angle(_unit_vector(rng_mount), rng_mount.uniform(0.0, MOUNT_ROTATION_DEG) * DEG)
    T_ds_mid = np.eye(4)
    T_ds_mid[:3, :3] = R_ds
    T_ds_mid[:3, 3] = -R_ds @ c_s
    T_de = T_ds_mid @ chain.inv_se3(chain.T_eb(dh, centre) @ chain.se3_from_tau(tau_s))
    tau_d = chain.tau_from_se3(T_de)

    static, hfov_s = _draw_camera(rng_cam)
    dynamic, hfov_d = _draw_camera(rng_cam)
    truth = GimbalCalibration.from_parts(tau_s, tau_d, dh, static_camera=static, dynamic_camera=dynamic)
    margin = SceneConfig().margin_px
    kind = "checkerboard" if rng_target.uniform() < 0.5 else "aprilgrid"
    best: tuple[float, TargetGeometry, float] | None = None
    for _ in range(TARGET_TRIES):
        target = _draw_target(rng_target, kind)
        z_min, z_detect = _distance_range(truth.T_ds(centre), target, (static, dynamic), margin)
        if best is None or z_detect / z_min > best[0]:
            best = (z_detect / z_min, target, z_min)
        if z_detect >= MIN_DEPTH_SPAN * z_min:
            break
    assert best is not None
    _, target, z_min = best
    z_max = float(np.clip(best[0], MIN_DEPTH_SPAN, 2.0)) * z_min
    distance = (round(z_min, 3), round(z_max, 3))
    scene = SceneConfig(
        n_joints=L,
        n_calibration=n_snapshots,
        n_validation=0,
        pixel_sigma=PIXEL_SIGMA,
        distance_range=distance,
        target=target,
    )
    description: dict[str, Any] = {
        "seed": int(seed),
        "joints": int(L),
        "intersecting_axes": intersecting,
        "twists": "near 90 deg" if near_90 else "20-160 deg",
        "dh": [[float(x) for x in row] for row in dh],
        "twists_deg": [float(x) for x in twist_deg],
        "range_centre_deg": [float(x) for x in centre / DEG],
        "half_range_deg": [float(x) for x in half_deg],
        "baseline_m": float(np.linalg.norm(c_s)),
        "target": {"kind": kind, **target.to_kalibr()},
        "cameras": {"static": _camera_dict(static, hfov_s), "dynamic": _camera_dict(dynamic, hfov_d)},
        "distance_range_m": [float(x) for x in distance],
        "snapshots": int(n_snapshots),
    }
    return FamilyMember(int(seed), truth, ranges, scene, kind, description)


def simulate_member(member: FamilyMember) -> SimulatedCalibration:
    """The member's corner-level data set: ``simulate_calibration(member.seed, member.scene,
    mechanism=(member.truth, member.ranges))`` (calibration set only; Gaussian corner noise of
    ``member.scene.pixel_sigma`` px)."""
    return simulate_calibration(member.seed, member.scene, mechanism=(member.truth, member.ranges))


def achieved_spread(sim: SimulatedCalibration) -> dict[str, list[float]]:
    """Spread of the true joint angles actually simulated (after the scene's shrink fallback).

    Returns ``{"half_range_deg": [(max - min) / 2 per joint], "std_deg": [std per joint]}``, degrees,
    over the calibration snapshots.
    """
    th = sim.joints_calibration
    if th.size == 0:
        return {"half_range_deg": [], "std_deg": []}
    return {
        "half_range_deg": [float(x) for x in 0.5 * np.ptp(th, axis=0) / DEG],
        "std_deg": [float(x) for x in np.std(th, axis=0) / DEG],
    }


def describe(member: FamilyMember) -> str:
    """One line: joints, axes, twists, requested ranges, target, cameras, distances."""
    d = member.description
    axes = "intersecting axes" if d["intersecting_axes"] and d["joints"] > 1 else "offset axes"
    twists = "/".join(f"{t:.0f}" for t in d["twists_deg"])
    half = "/".join(f"{h:.0f}" for h in d["half_range_deg"])
    t = d["target"]
    if member.target_kind == "checkerboard":
        board = f"checkerboard {t['targetCols']}x{t['targetRows']} @ {100 * t['colSpacingMeters']:.1f} cm"
    else:
        board = f"aprilgrid {t['tagCols']}x{t['tagRows']} @ {100 * t['tagSize']:.1f} cm"
    cams = ", ".join(
        f"{name} {c['resolution'][0]}x{c['resolution'][1]} {c['hfov_deg']:.0f} deg {c['model']}"
        for name, c in d["cameras"].items()
    )
    z = d["distance_range_m"]
    return (
        f"mechanism {d['seed']}: L={d['joints']}, {axes}, twists {twists} deg, ranges +-{half} deg, {board}, "
        f"{cams}, board {z[0]:.2f}-{z[1]:.2f} m"
    )
