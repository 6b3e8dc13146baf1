"""Camera poses at their own exposure times: time offsets and unsynchronized cameras in the VIO smoother.

A keyframe k holds the body state at its time ``t_k`` on the IMU clock: ``T_WI`` (body -> W),
``v_W`` (m/s in W) and, with a gimbal, the joint angles ``theta_k`` (rad). A camera image with
header stamp ``t_stamp`` (ns, the camera's clock) was exposed at the IMU time

    ``t_exposure = t_stamp + t_c``     (OpenVINS' ``calib_camimu_dt``, Kalibr's ``timeshift_cam_imu``)

with ``t_c`` the camera's time offset (s; ``t_s`` for the static camera, ``t_d`` for the gimbal
camera). The image is ``delta = (t_stamp - t_k) + t_c`` seconds away from its keyframe. Over so short
an interval (a frame period plus the offset, tens of ms) the body moves with the keyframe's twist
``xi = [omega_I, R_WI^T v_W]`` (body rates in I: the bias-corrected gyro, and the velocity), and the
joints move at a known rate ``theta_dot`` (rad/s, from the smoother's estimates):

    ``T_WI(t_k + delta) = T_WI Exp(delta xi)``,
    ``theta(t_k + delta) = theta_k + delta theta_dot``,
    ``T_Wc = T_WI(t_k + delta) T_Ic(theta(t_k + delta))``,

with ``T_Ic`` the camera mount: ``T_Is = T_sI^-1`` for the static camera and
``T_Id(theta) = (T_ds(theta) T_sI)^-1`` for the gimbal camera (paper eq. 13).

:func:`exposure_pose_factor` ties an auxiliary camera pose ``T_Wc`` (on which gtsam's C++ projection
factors sit) to these states with ``e = Log((T_WI Exp(delta xi) T_Ic)^-1 T_Wc)`` and a tight noise;
the offsets are a ``Vector`` variable of the smoother (one entry per camera), so every image
contributes to their estimate. Its Jacobians are analytic (derived in :func:`exposure_pose_factor`)
and tested against numerical differentiation in ``tests/test_exposure_factor.py``.

Units: seconds, metres, radians; Pose3 tangents ``[omega, v]`` (gtsam's order).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors.chain import inv_se3, skew
from factors.vio import ChainCache

FloatArray = NDArray[np.float64]


class CameraMount:
    """``T_Ic`` of one camera: constant (static camera, locked gimbal) or ``(T_ds(theta) T_sI)^-1``.

    ``mount(theta)`` returns ``(T_Ic (4, 4), G (6, L))`` with ``T_Ic(theta + d) ~= T_Ic(theta) Exp(G d)``.
    """

    def __init__(
        self, T_Ic: FloatArray | None = None, cache: ChainCache | None = None, T_sI: FloatArray | None = None
    ) -> None:
        if (T_Ic is None) == (cache is None):
            raise ValueError("a camera mount is either a constant T_Ic or a gimbal chain (cache and T_sI)")
        self.T_Ic = None if T_Ic is None else np.asarray(T_Ic, float)
        self.cache = cache
        self.T_sI = None if T_sI is None else np.asarray(T_sI, float)
        self.n_joints = 0 if cache is None else cache.L
        self._memo: tuple[bytes, gtsam.Pose3, FloatArray, FloatArray] | None = None
        if self.T_Ic is not None:
            X = gtsam.Pose3(self.T_Ic)
            self._memo = (b"", X, X.inverse().AdjointMap(), np.zeros((6, 0)))

    @property
    def on_gimbal(self) -> bool:
        return self.cache is not None

    def __call__(self, theta: FloatArray | None) -> tuple[FloatArray, FloatArray]:
        if self.cache is None:
            assert self.T_Ic is not None
            return self.T_Ic, np.zeros((6, 0))
        assert theta is not None and self.T_sI is not None
        T_ds, J = self.cache.get(np.asarray(theta, float))
        # T_sd(theta + d) = T_sd Exp(-Ad(T_ds) J d) and T_Id = T_Is T_sd
        G = -gtsam.Pose3(T_ds).AdjointMap() @ J
        return inv_se3(T_ds @ self.T_sI), G

    def pose(self, theta: FloatArray | None) -> tuple[gtsam.Pose3, FloatArray, FloatArray]:
        """``(T_Ic as Pose3, Ad(T_Ic^-1), G)``, memoized for the last joint angles (a factor is
        linearized at the same angles many times; the static mount is computed once)."""
        if self.cache is None:
            assert self._memo is not None
            return self._memo[1], self._memo[2], self._memo[3]
        key = np.asarray(theta, float).tobytes()
        if self._memo is None or self._memo[0] != key:
            T_Ic, G = self(theta)
            X = gtsam.Pose3(T_Ic)
            self._memo = (key, X, X.inverse().AdjointMap(), G)
        return self._memo[1], self._memo[2], self._memo[3]


def exposure_rate(
    T_WI: FloatArray,
    v_W: FloatArray,
    omega_I: FloatArray,
    T_Ic: FloatArray,
    G: FloatArray,
    theta_rate: FloatArray,
) -> FloatArray:
    """``d T_Wc / d t`` as a right-perturbation twist of the camera (6,): ``Ad(T_Ic^-1) xi + G theta_rate``
    (``T_Wc(t + dt) ~= T_Wc Exp(u dt)``), rad/s and m/s. A stamp error ``dt`` moves the modelled camera
    pose by ``u dt``: :func:`exposure_pose_factor` adds this direction to its noise for stamp jitter."""
    xi = twist(T_WI, v_W, omega_I)
    Ad = gtsam.Pose3(np.asarray(T_Ic, float)).inverse().AdjointMap()
    return Ad @ xi + np.asarray(G, float) @ np.asarray(theta_rate, float)


def twist(T_WI: FloatArray, v_W: FloatArray, omega_I: FloatArray) -> FloatArray:
    """``xi = [omega_I, R_WI^T v_W]`` (6,): the body twist in I (rad/s, m/s)."""
    return np.r_[np.asarray(omega_I, float), np.asarray(T_WI, float)[:3, :3].T @ np.asarray(v_W, float)]


def exposure_pose(
    T_WI: FloatArray, v_W: FloatArray, omega_I: FloatArray, delta_s: float, T_Ic: FloatArray
) -> FloatArray:
    """``T_Wc = T_WI Exp(delta xi) T_Ic`` (4, 4): the camera pose ``delta_s`` seconds after the keyframe."""
    M = gtsam.Pose3.Expmap(delta_s * twist(T_WI, v_W, omega_I)).matrix()
    return np.asarray(T_WI, float) @ M @ np.asarray(T_Ic, float)


@dataclass(frozen=True)
class ExposureKeys:
    """Keys of one exposure factor: keyframe pose ``x`` (Pose3 T_WI) and velocity ``v`` (Vector3),
    the camera pose ``c`` (Pose3 T_Wc), the offsets ``offsets`` (Vector, entry ``offset_index``; None:
    fixed), and for a gimbal camera the keyframe's joint angles ``theta``."""

    pose: int
    velocity: int
    camera: int
    offsets: int | None = None
    offset_index: int = 0
    theta: int | None = None


def exposure_pose_factor(
    keys: ExposureKeys,
    mount: CameraMount,
    stamp_gap_s: float,
    omega_I: FloatArray,
    fixed_offset_s: float = 0.0,
    theta_rate: FloatArray | None = None,
    sigma_rotation: float = 1e-4,
    sigma_translation: float = 1e-4,
    jitter: FloatArray | None = None,
) -> gtsam.CustomFactor:
    """``e = Log(C^-1 T_Wc)``, ``C = T_WI Exp(delta xi) T_Ic(theta')`` (module docstring), in rad and m.

    ``delta = stamp_gap_s + t_c`` (``t_c`` the offset variable's entry, or ``fixed_offset_s``);
    ``theta' = theta_k + delta theta_rate``. ``omega_I`` and ``theta_rate`` (rad/s) are constants of
    the factor (a joint-rate *variable*, through the previous keyframe's angles, made gtsam's
    Cholesky fail on the tightly constrained system). Noise: ``sigma_rotation`` (rad) and
    ``sigma_translation`` (m) per axis, plus ``jitter jitter^T`` when ``jitter`` (6,) is given: the
    camera's motion during one standard deviation of the stamp jitter (``u sigma_jitter``,
    :func:`exposure_rate`), so that an image whose stamp is off by its jitter is not a contradiction
    of the tight tie. Jacobians, with ``M = Exp(delta xi)``, ``X = T_Ic(theta')``,
    ``D = C^-1 T_Wc``, ``A = -J_r^-1(e) Ad(D^-1)`` (the derivative of ``e`` by a right perturbation
    ``C Exp(eta)``), ``J_M = J_r(delta xi)``:

    * ``T_Wc``: ``J_r^-1(e)``;
    * ``T_WI`` (right perturbation ``[phi, rho]``): ``A [Ad((M X)^-1) + Ad(X^-1) J_M delta dxi/dphi]``,
      ``dxi/dphi = [[0, 0], [[R^T v]_x, 0]]`` (the velocity in I turns with the body);
    * ``v_W``: ``A Ad(X^-1) J_M delta [0; R^T]``;
    * ``t_c``: ``A (Ad(X^-1) xi + G theta_rate)``;
    * ``theta_k``: ``A G`` (``G`` from :class:`CameraMount`).
    """
    omega = np.asarray(omega_I, float).reshape(3)
    key_list = [keys.pose, keys.velocity, keys.camera]
    if keys.offsets is not None:
        key_list.append(keys.offsets)
    gimbal = mount.on_gimbal
    if gimbal:
        if keys.theta is None:
            raise ValueError("a gimbal-camera exposure factor needs the keyframe's joint-angle key")
        key_list.append(keys.theta)
    rate = np.zeros(mount.n_joints) if theta_rate is None else np.asarray(theta_rate, float).reshape(mount.n_joints)
    sigmas = np.r_[np.full(3, sigma_rotation), np.full(3, sigma_translation)]
    noise: gtsam.noiseModel.Base = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
    if jitter is not None and np.any(jitter):
        w = np.asarray(jitter, float).reshape(6)
        noise = gtsam.noiseModel.Gaussian.Covariance(np.diag(sigmas**2) + np.outer(w, w))

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[FloatArray] | None) -> FloatArray:
        T_WI = values.atPose3(keys.pose)
        R = T_WI.rotation().matrix()
        v = values.atVector(keys.velocity)
        T_Wc = values.atPose3(keys.camera)
        t_c = fixed_offset_s if keys.offsets is None else float(values.atVector(keys.offsets)[keys.offset_index])
        delta = stamp_gap_s + t_c
        theta_c = values.atVector(keys.theta) + delta * rate if gimbal else None
        X, AdXinv, G = mount.pose(theta_c)
        v_I = R.T @ v
        xi = np.r_[omega, v_I]
        M = gtsam.Pose3.Expmap(delta * xi)
        MX = M.compose(X)
        D = T_WI.compose(MX).between(T_Wc)
        e = gtsam.Pose3.Logmap(D)
        if H is not None:
            Jinv = gtsam.Pose3.LogmapDerivative(e)
            A = -Jinv @ D.inverse().AdjointMap()
            AdXinv_J = AdXinv @ gtsam.Pose3.ExpmapDerivative(delta * xi)
            B = A @ AdXinv_J  # d e / d xi, per unit delta
            dxi_dpose = np.zeros((6, 6))
            dxi_dpose[3:, :3] = skew(v_I)
            out = [A @ (AdXinv @ M.inverse().AdjointMap()) + delta * B @ dxi_dpose]
            dxi_dv = np.zeros((6, 3))
            dxi_dv[3:, :] = R.T
            out.append(delta * B @ dxi_dv)
            out.append(Jinv)
            if keys.offsets is not None:
                d_offset = A @ (AdXinv @ xi + G @ rate)
                row = np.zeros((6, values.atVector(keys.offsets).shape[0]))
                row[:, keys.offset_index] = d_offset
                out.append(row)
            if gimbal:
                out.append(A @ G)
            for i, h in enumerate(out):
                H[i] = h
        return e

    return gtsam.CustomFactor(noise, key_list, error)
