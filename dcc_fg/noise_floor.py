"""The model-independent noise floor of a calibration data set: per image a free target pose.

Every image's target pose ``T_ct`` is refined on the pixel error (PnP start, damped Gauss-Newton), so
the residuals hold only the corner noise (and whatever the intrinsics get wrong) of each camera, with
``2 N - 6`` degrees of freedom per image of N corners. :mod:`dcc_fg.calibrate` weights each camera's
corners by its floor sigma; :mod:`dcc_fg.calibration_health` compares models against the floor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from dcc_fg.calibration_graph import snapshot_measurements
from dcc_fg.data import CalibrationDataset
from dcc_fg.init import pnp_pose
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]
#: Gauss-Newton iterations of the per-image pose refinement on the pixel error (starts at PnP).
FLOOR_ITERATIONS = 8


def _rotation_exp(omega: FloatArray) -> FloatArray:
    """Rotation matrices (M, 3, 3) of rotation vectors (M, 3), rad (Rodrigues)."""
    theta = np.linalg.norm(omega, axis=1)
    small = theta < 1e-12
    safe = np.where(small, 1.0, theta)
    k = omega / safe[:, None]
    Kx = np.zeros((len(omega), 3, 3))
    Kx[:, 0, 1], Kx[:, 0, 2], Kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    Kx[:, 1, 0], Kx[:, 2, 0], Kx[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(theta)[:, None, None], (1.0 - np.cos(theta))[:, None, None]
    R = np.eye(3)[None] + s * Kx + c * (Kx @ Kx)
    R[small] = np.eye(3)
    return R


def pose_residual_jacobian(camera: CameraModel, p_c: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Pixels (N, 2) of camera-frame points (N, 3), m, and their Jacobian (N, 2, 6) with respect to a
    left perturbation ``[omega, v]`` of the pose ``T_ct`` (``p_c -> Exp(omega) p_c + v``)."""
    uv, J_p = camera.project(p_c, jacobian=True)
    assert J_p is not None
    D = np.zeros((len(p_c), 3, 6))
    D[:, 0, 1], D[:, 0, 2], D[:, 1, 2] = p_c[:, 2], -p_c[:, 1], p_c[:, 0]
    D[:, 1, 0], D[:, 2, 0], D[:, 2, 1] = -p_c[:, 2], p_c[:, 1], -p_c[:, 0]
    D[:, :, 3:] = np.eye(3)
    return uv, J_p @ D


def refine_poses(
    camera: CameraModel, p_t: list[FloatArray], uv: list[FloatArray], T0: FloatArray, iterations: int = FLOOR_ITERATIONS
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per image, the target pose ``T_ct`` (M, 4, 4) minimizing the pixel error, its residual sum of
    squares (M,), px^2, and ``J^T J`` (M, 6, 6) at it (information of the left perturbation
    ``[omega, v]`` for unit pixel noise): damped Gauss-Newton from ``T0`` on all images at once (steps that do not
    lower an image's sum of squares are refused for that image)."""
    M = len(uv)
    counts = np.array([len(z) for z in uv])
    start = np.r_[0, np.cumsum(counts)[:-1]]
    P, Z = np.concatenate(p_t), np.concatenate(uv)
    img = np.repeat(np.arange(M), counts)
    R, t = T0[:, :3, :3].copy(), T0[:, :3, 3].copy()

    def evaluate(R: FloatArray, t: FloatArray, jac: bool) -> tuple[FloatArray, FloatArray, FloatArray | None]:
        p_c = np.einsum("nij,nj->ni", R[img], P) + t[img]
        if jac:
            uv_hat, J = pose_residual_jacobian(camera, p_c)
        else:
            uv_hat, J = camera.project(p_c, jacobian=False)[0], None
        r = uv_hat - Z
        return r, np.add.reduceat(np.sum(r * r, axis=1), start), J

    r, ss, J = evaluate(R, t, True)
    lam = np.full(M, 1e-6)
    for _ in range(iterations):
        assert J is not None
        A = np.zeros((M, 6, 6))
        b = np.zeros((M, 6))
        np.add.at(A, img, np.einsum("nki,nkj->nij", J, J))
        np.add.at(b, img, np.einsum("nki,nk->ni", J, r))
        diag = np.einsum("mii->mi", A)
        A_damped = A + (lam[:, None] * (diag + 1e-12))[:, :, None] * np.eye(6)[None]
        step = -np.linalg.solve(A_damped, b[:, :, None])[:, :, 0]
        dR = _rotation_exp(step[:, :3])
        R_new = dR @ R
        t_new = np.einsum("mij,mj->mi", dR, t) + step[:, 3:]
        r_new, ss_new, J_new = evaluate(R_new, t_new, True)
        better = np.isfinite(ss_new) & (ss_new < ss)
        R[better], t[better] = R_new[better], t_new[better]
        ss = np.where(better, ss_new, ss)
        lam = np.where(better, lam * 0.1, lam * 10.0)
        keep = better[img]
        r = np.where(keep[:, None], r_new, r)
        assert J_new is not None
        J = np.where(keep[:, None, None], J_new, J)
    T = np.tile(np.eye(4), (M, 1, 1))
    T[:, :3, :3], T[:, :3, 3] = R, t
    assert J is not None
    A = np.zeros((M, 6, 6))
    np.add.at(A, img, np.einsum("nki,nkj->nij", J, J))
    return T, ss, A


def _adjoint(T: FloatArray) -> FloatArray:
    """(M, 6, 6) adjoint maps of poses (M, 4, 4) for ``[omega, v]`` twists: ``[[R, 0], [t^ R, R]]``."""
    R, t = T[:, :3, :3], T[:, :3, 3]
    tx = np.zeros((len(T), 3, 3))
    tx[:, 0, 1], tx[:, 0, 2], tx[:, 1, 2] = -t[:, 2], t[:, 1], -t[:, 0]
    tx[:, 1, 0], tx[:, 2, 0], tx[:, 2, 1] = t[:, 2], -t[:, 1], t[:, 0]
    Ad = np.zeros((len(T), 6, 6))
    Ad[:, :3, :3], Ad[:, 3:, 3:], Ad[:, 3:, :3] = R, R, tx @ R
    return Ad


def translation_whitening(whitening: FloatArray) -> FloatArray:
    """(K, 3, 3) upper-triangular ``V_i`` with ``V_i^T V_i`` the information of the translation part ``v``
    (m) of a right perturbation ``[omega, v]`` whose information is ``W_i^T W_i`` (``whitening`` W, (K, 6, 6),
    e.g. :meth:`NoiseFloor.T_ds_whitening`), with ``omega`` marginalized: the inverse of the ``v`` block of
    ``(W_i^T W_i)^-1``.

    Use: a chain whose rotation reproduces the measured ``R_ds_i`` exactly has
    ``T_ds_i^-1 T_ds(chain) = [I, t_sd_i - t_sd(chain)]`` (``T_sd = T_ds^-1``, translations in s), so its
    right perturbation is ``[0, t_sd_i - t_sd(chain)]`` and ``|V_i (t_sd(chain) - t_sd_i)|^2`` weighs its
    lever-arm misfit by how well the two images determine it, the rotation noise included."""
    info = np.transpose(whitening, (0, 2, 1)) @ whitening
    cov_v = np.linalg.inv(info)[:, 3:, 3:]
    info_v = np.linalg.inv(0.5 * (cov_v + np.transpose(cov_v, (0, 2, 1))))
    info_v = 0.5 * (info_v + np.transpose(info_v, (0, 2, 1)))
    return np.transpose(np.linalg.cholesky(info_v), (0, 2, 1))


@dataclass
class NoiseFloor:
    """The model-independent noise floor: per snapshot a free target pose in each camera.

    Attributes:
        T_st / T_dt: (K, 4, 4) target poses in the static / dynamic camera, refined on pixels.
        ss: (K, 2) residual sums of squares, px^2, columns [static, dynamic].
        n: (K, 2) corner counts.
        info_st / info_dt: (K, 6, 6) ``J^T J`` of each pose (left perturbation ``[omega, v]``, unit
            pixel noise).
    """

    T_st: FloatArray
    T_dt: FloatArray
    ss: FloatArray
    n: NDArray[np.int64]
    info_st: FloatArray
    info_dt: FloatArray

    def T_ds_covariance(
        self,
        i_static: NDArray[np.int64],
        i_dynamic: NDArray[np.int64],
        variances: tuple[float, float] | None = None,
    ) -> FloatArray:
        """(M, 6, 6) covariances of the left perturbation ``[omega, v]`` of ``T_ds = T_dt[j] inv(T_st[i])``
        for the pairs (i, j): ``C_d + Ad(T_ds) C_s Ad(T_ds)^T`` with each pose's ``s2 (J^T J)^-1``
        (``s2``: ``variances`` of the [static, dynamic] corners, px^2; default each camera's floor variance)."""
        v_s, v_d = (self.variance(0), self.variance(1)) if variances is None else variances
        C_s = v_s * np.linalg.inv(self.info_st[i_static] + 1e-12 * np.eye(6))
        C_d = v_d * np.linalg.inv(self.info_dt[i_dynamic] + 1e-12 * np.eye(6))
        Ad = _adjoint(self.T_dt[i_dynamic] @ np.linalg.inv(self.T_st[i_static]))
        return C_d + Ad @ C_s @ np.transpose(Ad, (0, 2, 1))

    def T_ds_whitening(self) -> FloatArray:
        """(K, 6, 6) per snapshot an upper-triangular ``W_i`` with ``W_i^T W_i`` the information of
        ``T_ds_i = T_dt_i inv(T_st_i)`` in the *right* perturbation ``[omega, v]`` (rad, m; gtsam's
        ``Pose3.localCoordinates`` at ``T_ds_i``): ``Ad^T C^-1 Ad`` with ``C`` the left-perturbation
        covariance of :meth:`T_ds_covariance` and ``Ad = Ad(T_ds_i)`` (the left perturbation ``Ad xi``
        is the right one ``xi``). ``|W_i Log(T_ds_i^-1 T)|^2`` is then the chi-square of a chain's ``T``
        against the two images' poses: the pose-level image of the corner-level cost. A noiseless floor
        (variance below :data:`NOISELESS_VARIANCE`) uses unit pixel variances."""
        idx = np.arange(len(self.T_st))
        v = (self.variance(0), self.variance(1))
        C = self.T_ds_covariance(idx, idx, None if min(v) >= NOISELESS_VARIANCE else (1.0, 1.0))
        Ad = _adjoint(self.T_dt @ np.linalg.inv(self.T_st))
        info = np.transpose(Ad, (0, 2, 1)) @ np.linalg.inv(C) @ Ad
        info = 0.5 * (info + np.transpose(info, (0, 2, 1)))
        return np.transpose(np.linalg.cholesky(info), (0, 2, 1))

    def dof(self, cam: int) -> int:
        """Degrees of freedom of camera ``cam``'s floor: 2 N - 6 per image."""
        return int(np.sum(np.maximum(2 * self.n[:, cam] - 6, 0)))

    def variance(self, cam: int) -> float:
        """Floor variance per axis of camera ``cam``, px^2."""
        return float(self.ss[:, cam].sum() / max(self.dof(cam), 1))


def noise_floor(
    data: CalibrationDataset, T_st0: FloatArray | None = None, T_dt0: FloatArray | None = None
) -> NoiseFloor:
    """Per-image PnP of both cameras (``T_st0`` / ``T_dt0``: PnP starts, computed when None), refined
    on the pixel error; see :class:`NoiseFloor`."""
    meas = [snapshot_measurements(data, s) for s in data.snapshots]
    cams = (data.static_camera, data.dynamic_camera)
    if T_st0 is None:
        T_st0 = np.array([pnp_pose(cams[0], m.p_t_static, m.z_static) for m in meas])
    if T_dt0 is None:
        T_dt0 = np.array([pnp_pose(cams[1], m.p_t_dynamic, m.z_dynamic) for m in meas])
    T_st, ss_s, info_s = refine_poses(cams[0], [m.p_t_static for m in meas], [m.z_static for m in meas], T_st0)
    T_dt, ss_d, info_d = refine_poses(cams[1], [m.p_t_dynamic for m in meas], [m.z_dynamic for m in meas], T_dt0)
    n = np.array([[len(s.static), len(s.dynamic)] for s in data.snapshots], dtype=np.int64)
    return NoiseFloor(T_st, T_dt, np.column_stack([ss_s, ss_d]), n, info_s, info_d)


#: Floor variances (px^2) below this are round-off of noiseless data: the images are weighted alike.
NOISELESS_VARIANCE = 1e-16
#: Weight, in degrees of freedom, of the camera's variance in each image's variance (the prior of an
#: inverse-gamma / scaled chi-square model: an image of N corners has 2 N - 6 of its own).
CAMERA_PRIOR_DOF = 40.0


def relative_image_noise(floor: NoiseFloor) -> FloatArray:
    """(K, 2) corner noise of each image ``[static, dynamic]`` relative to the pooled noise of all
    images: ``sqrt(v_ic / v)``.

    ``v`` is the pooled floor variance (sum of squares over degrees of freedom of both cameras);
    ``v_ic = (ss_ic + k v_c) / (dof_ic + k)`` is image i's own variance shrunk towards its camera's
    ``v_c`` with ``k = CAMERA_PRIOR_DOF`` (an image's own estimate, ~80 degrees of freedom, scatters
    by ~16 %; cameras of different resolution, blur or lens, and images at different distance or
    obliquity, detect corners with noise that differs by up to ~2x). All ones when a camera has
    no degrees of freedom or the data are noiseless.

    The calibration whitens image i of camera c with ``sigma * scale_ic`` (weights 1 / scale_ic^2),
    the maximum-likelihood weighting of heteroscedastic corners; the a-posteriori variance factor
    then scales all of them."""
    K = floor.ss.shape[0]
    dof_img = np.maximum(2 * floor.n - 6, 0).astype(float)
    total_dof = float(dof_img.sum())
    total = float(floor.ss.sum()) / max(total_dof, 1.0)
    if min(floor.dof(0), floor.dof(1)) < 1 or not np.isfinite(total) or total < NOISELESS_VARIANCE:
        return np.ones((K, 2))
    v_cam = np.array([floor.variance(0), floor.variance(1)])
    if np.min(v_cam) < NOISELESS_VARIANCE:
        return np.ones((K, 2))
    v_img = (floor.ss + CAMERA_PRIOR_DOF * v_cam[None, :]) / (dof_img + CAMERA_PRIOR_DOF)
    return np.sqrt(v_img / total)
