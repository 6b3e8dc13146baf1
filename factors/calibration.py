"""GTSAM factors of the batch calibration graph, one vectorised factor per snapshot.

Variables (gtsam keys chosen by the caller):

* ``kin``: a Vector of the *free* kinematic parameters; :class:`KinLayout` maps it into the full
  ``[tau_s, tau_d, dh]`` vector of :mod:`factors.chain` (gauge-fixed entries are constants).
* ``theta_i``: a Vector of the L joint angles of snapshot i (radians); constant in ``encoders`` mode.
* ``T_st_i``: a Pose3, the target pose in the static camera (bundle formulation only).

Two formulations:

* :func:`bundle_factor` - maximum likelihood: the known target points ``p_t`` go through the
  target pose into the static camera, ``u_s = pi_s(T_st p_t)``, and through the chain into the
  dynamic camera, ``u_d = pi_d(T_ds(theta_i) T_st p_t)``.
* :func:`two_way_factor` - the paper's eqs. 1, 2 and 6: points reconstructed by each camera's PnP
  are projected into the other camera, ``e_d = z_d - pi_d(T_ds P_s)`` and
  ``e_s = z_s - pi_s(inv(T_ds) P_d)``.

Residuals are whitened by the pixel sigma inside the factor and optionally passed through a
per-corner robust loss (:class:`RobustLoss`), so every corner gets its own weight although a
whole snapshot is one factor. The factors use a unit noise model.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors import chain
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class KinLayout:
    """Which kinematic parameters are variables, and the values of the fixed ones.

    Attributes:
        full: (12 + 3L,) values used for the fixed entries (and the initial guess).
        free: boolean mask of the entries that are estimated.
        n_joints: L.
    """

    full: FloatArray
    free: NDArray[np.bool_]
    n_joints: int

    @property
    def free_index(self) -> NDArray[np.int64]:
        return np.flatnonzero(self.free)

    def expand(self, kin_free: FloatArray | None) -> FloatArray:
        """Full kinematic vector from the free part (or the constants when ``kin_free`` is None)."""
        out = self.full.copy()
        if kin_free is not None:
            out[self.free] = kin_free
        return out


@dataclass(frozen=True)
class RobustLoss:
    """Per-corner robust loss on the whitened 2D residual r of one corner.

    ``kind`` is ``huber`` or ``cauchy`` and ``k`` its threshold in sigmas. The residual is replaced
    by ``g(s) r`` with ``s = |r|^2`` and ``g = sqrt(rho(s) / s)``, so that the squared norm of the
    new residual equals the robust cost ``rho(s)``; its Jacobian is exact:
    ``d(g r) = (g I + 2 g'(s) r r^T) dr``.
    """

    kind: str
    k: float

    def __post_init__(self) -> None:
        if self.kind not in ("huber", "cauchy"):
            raise ValueError(f"robust loss '{self.kind}' is not one of huber, cauchy")
        if self.k <= 0:
            raise ValueError("robust loss threshold must be positive")

    def rho(self, s: FloatArray) -> tuple[FloatArray, FloatArray]:
        """rho(s) and rho'(s) for squared norms s (rho(s) ~ s near 0)."""
        k2 = self.k * self.k
        if self.kind == "huber":
            r = np.sqrt(s)
            inside = r <= self.k
            rho = np.where(inside, s, 2.0 * self.k * r - k2)
            drho = np.where(inside, 1.0, self.k / np.maximum(r, 1e-300))
            return rho, drho
        rho = k2 * np.log1p(s / k2)
        return rho, 1.0 / (1.0 + s / k2)

    def scale(self, r: FloatArray) -> FloatArray:
        """g(s) = sqrt(rho(s) / s) per corner for residuals r (N, 2)."""
        s = np.sum(r * r, axis=1)
        rho, _ = self.rho(s)
        return np.where(s < 1e-12, 1.0, np.sqrt(rho / np.where(s < 1e-12, 1.0, s)))

    def apply(self, r: FloatArray, J: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Transform per-corner residuals r (N, 2) and Jacobians J (N, 2, n)."""
        s = np.sum(r * r, axis=1)
        rho, drho = self.rho(s)
        tiny = s < 1e-12
        s_safe = np.where(tiny, 1.0, s)
        g = np.where(tiny, 1.0, np.sqrt(rho / s_safe))
        # g' = (rho' s - rho) / (2 s^2 g)
        dg = np.where(tiny, 0.0, (drho * s_safe - rho) / (2.0 * s_safe * s_safe * g))
        r_new = g[:, None] * r
        M = g[:, None, None] * np.eye(2) + 2.0 * dg[:, None, None] * r[:, :, None] * r[:, None, :]
        return r_new, np.einsum("nij,njk->nik", M, J)

    def weights(self, r: FloatArray) -> FloatArray:
        """Effective IRLS weight rho'(s) per corner (1 = inlier)."""
        return self.rho(np.sum(r * r, axis=1))[1]


def pose_point_jacobian(R_st: FloatArray, p_t: FloatArray) -> FloatArray:
    """d (T_st p_t) / d xi for the gtsam Pose3 retraction T_st Exp(xi), xi = [omega, v]: (N, 3, 6)."""
    n = p_t.shape[0]
    x, y, z = p_t[:, 0], p_t[:, 1], p_t[:, 2]
    neg_skew = np.zeros((n, 3, 3))  # -[p]x: column k is e_k x p
    neg_skew[:, 0, 1], neg_skew[:, 0, 2], neg_skew[:, 1, 2] = z, -y, x
    neg_skew[:, 1, 0], neg_skew[:, 2, 0], neg_skew[:, 2, 1] = -z, y, -x
    J = np.empty((n, 3, 6))
    J[:, :, 0:3] = R_st @ neg_skew
    J[:, :, 3:6] = R_st
    return J


@dataclass(frozen=True)
class SnapshotMeasurements:
    """Corners of one snapshot, already matched to target points.

    Attributes:
        p_t_static / z_static: target points (N_s, 3) and pixels (N_s, 2) seen by camera s.
        p_t_dynamic / z_dynamic: the same for camera d.
    """

    p_t_static: FloatArray
    z_static: FloatArray
    p_t_dynamic: FloatArray
    z_dynamic: FloatArray


def camera_sigmas(sigma: float | tuple[float, float]) -> tuple[float, float]:
    """``(static, dynamic)`` pixel sigmas from one sigma for both cameras or a pair."""
    if np.isscalar(sigma):
        return float(sigma), float(sigma)  # type: ignore[arg-type]
    s_static, s_dynamic = sigma  # type: ignore[misc]
    return float(s_static), float(s_dynamic)


def _finish(
    blocks: list[tuple[FloatArray, list[FloatArray]]],
    sigmas: tuple[float, ...],
    robust: RobustLoss | None,
    H: list[FloatArray] | None,
) -> FloatArray:
    """Stack per-camera residual blocks (N, 2) + Jacobian blocks (N, 2, n_key), whiten each block by
    its camera's sigma (``sigmas[b]`` for ``blocks[b]``, px), robustify."""
    r = np.concatenate([b[0] / s for b, s in zip(blocks, sigmas, strict=True)], axis=0)
    if H is None:
        return (r if robust is None else robust.scale(r)[:, None] * r).reshape(-1)
    n_keys = len(blocks[0][1])
    Js = [np.concatenate([b[1][k] / s for b, s in zip(blocks, sigmas, strict=True)], axis=0) for k in range(n_keys)]
    if robust is not None:
        widths = [J.shape[2] for J in Js]
        J_all = np.concatenate(Js, axis=2)
        r, J_all = robust.apply(r, J_all)
        Js = np.split(J_all, np.cumsum(widths)[:-1], axis=2)
    for k, J in enumerate(Js):
        H[k] = J.reshape(-1, J.shape[2])
    return r.reshape(-1)


def bundle_residuals(
    layout: KinLayout,
    kin_free: FloatArray | None,
    theta: FloatArray,
    T_st: FloatArray,
    meas: SnapshotMeasurements,
    cams: tuple[CameraModel, CameraModel],
    want_jacobians: bool,
) -> list[tuple[FloatArray, list[FloatArray]]]:
    """Unwhitened residual blocks ``h(x) - z`` of the bundle formulation and their Jacobians.

    Returns ``[(r_s, [J_kin, J_theta, J_pose]), (r_d, [...])]`` with Jacobian widths
    (n_free, L, 6); the caller drops the columns of keys that are constants.
    """
    L = layout.n_joints
    kin = layout.expand(kin_free)
    R_st, t_st = T_st[:3, :3], T_st[:3, 3]
    n_free = int(layout.free.sum())
    free = layout.free_index
    # static camera
    p_s = meas.p_t_static @ R_st.T + t_st
    uv_s, Jp_s = cams[0].project(p_s, jacobian=want_jacobians)
    blocks = []
    if want_jacobians:
        assert Jp_s is not None
        J_pose_s = np.einsum("nij,njk->nik", Jp_s, pose_point_jacobian(R_st, meas.p_t_static))
        ns = p_s.shape[0]
        blocks.append((uv_s - meas.z_static, [np.zeros((ns, 2, n_free)), np.zeros((ns, 2, L)), J_pose_s]))
    else:
        blocks.append((uv_s - meas.z_static, []))
    # dynamic camera
    p_s_d = meas.p_t_dynamic @ R_st.T + t_st
    p_d, Jc = chain.transform_points(kin, theta, p_s_d, L, jacobians=want_jacobians)
    uv_d, Jp_d = cams[1].project(p_d, jacobian=want_jacobians)
    if want_jacobians:
        assert Jc is not None and Jp_d is not None
        J_kin = np.einsum("nij,njk->nik", Jp_d, Jc.d_kin[:, :, free])
        J_theta = np.einsum("nij,njk->nik", Jp_d, Jc.d_theta)
        J_pose = np.einsum("nij,njk->nik", Jp_d @ Jc.d_point, pose_point_jacobian(R_st, meas.p_t_dynamic))
        blocks.append((uv_d - meas.z_dynamic, [J_kin, J_theta, J_pose]))
    else:
        blocks.append((uv_d - meas.z_dynamic, []))
    return blocks


def two_way_residuals(
    layout: KinLayout,
    kin_free: FloatArray | None,
    theta: FloatArray,
    P_s: FloatArray,
    z_d: FloatArray,
    P_d: FloatArray,
    z_s: FloatArray,
    cams: tuple[CameraModel, CameraModel],
    want_jacobians: bool,
) -> list[tuple[FloatArray, list[FloatArray]]]:
    """Residual blocks ``h(x) - z`` of the paper's two-way error (eqs. 1, 2) with Jacobians (kin, theta).

    ``P_s`` are static-camera points (from the static PnP) of the corners ``z_d`` seen by the
    dynamic camera; ``P_d`` are dynamic-camera points of the corners ``z_s`` seen by the static camera.
    """
    L = layout.n_joints
    kin = layout.expand(kin_free)
    free = layout.free_index
    p_d, Jd = chain.transform_points(kin, theta, P_s, L, jacobians=want_jacobians)
    uv_d, Jpd = cams[1].project(p_d, jacobian=want_jacobians)
    p_s, Js = chain.inverse_transform_points(kin, theta, P_d, L, jacobians=want_jacobians)
    uv_s, Jps = cams[0].project(p_s, jacobian=want_jacobians)
    if not want_jacobians:
        return [(uv_d - z_d, []), (uv_s - z_s, [])]
    assert Jd is not None and Jpd is not None and Js is not None and Jps is not None
    return [
        (
            uv_d - z_d,
            [np.einsum("nij,njk->nik", Jpd, Jd.d_kin[:, :, free]), np.einsum("nij,njk->nik", Jpd, Jd.d_theta)],
        ),
        (
            uv_s - z_s,
            [np.einsum("nij,njk->nik", Jps, Js.d_kin[:, :, free]), np.einsum("nij,njk->nik", Jps, Js.d_theta)],
        ),
    ]


def _select(
    blocks: list[tuple[FloatArray, list[FloatArray]]], keep: list[bool]
) -> list[tuple[FloatArray, list[FloatArray]]]:
    return [(r, [J for J, k in zip(Js, keep, strict=True) if k]) for r, Js in blocks]


def bundle_factor(
    layout: KinLayout,
    meas: SnapshotMeasurements,
    cams: tuple[CameraModel, CameraModel],
    sigma: float | tuple[float, float],
    pose_key: int,
    kin_key: int | None,
    theta_key: int | None,
    theta_const: FloatArray | None = None,
    robust: RobustLoss | None = None,
) -> gtsam.CustomFactor:
    """Maximum-likelihood factor of one snapshot on keys ``[kin?, theta?, T_st]``.

    ``kin_key=None`` holds the kinematics at ``layout.full`` (validation); ``theta_key=None``
    holds the joint angles at ``theta_const`` (encoder readings). ``sigma``: pixel sigma of both
    cameras, or ``(static, dynamic)``.
    """
    if theta_key is None and theta_const is None:
        raise ValueError("either theta_key or theta_const is needed")
    sigmas = camera_sigmas(sigma)  # the blocks of bundle_residuals: static, dynamic
    keep = [kin_key is not None, theta_key is not None, True]
    keys = [k for k, use in zip((kin_key, theta_key, pose_key), keep, strict=True) if use]

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[FloatArray] | None) -> FloatArray:
        kin_free = values.atVector(kin_key) if kin_key is not None else None
        theta = values.atVector(theta_key) if theta_key is not None else theta_const
        T_st = values.atPose3(pose_key).matrix()
        blocks = bundle_residuals(layout, kin_free, theta, T_st, meas, cams, H is not None)
        if H is None:
            return _finish(blocks, sigmas, robust, None)
        return _finish(_select(blocks, keep), sigmas, robust, H)

    n_rows = 2 * (meas.z_static.shape[0] + meas.z_dynamic.shape[0])
    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(n_rows), keys, error)


def two_way_factor(
    layout: KinLayout,
    P_s: FloatArray,
    z_d: FloatArray,
    P_d: FloatArray,
    z_s: FloatArray,
    cams: tuple[CameraModel, CameraModel],
    sigma: float | tuple[float, float],
    kin_key: int | None,
    theta_key: int | None,
    theta_const: FloatArray | None = None,
    robust: RobustLoss | None = None,
) -> gtsam.CustomFactor:
    """The paper's two-way reprojection factor (eqs. 1, 2, 6) of one snapshot on keys ``[kin?, theta?]``;
    ``sigma``: pixel sigma of both cameras, or ``(static, dynamic)``."""
    if kin_key is None and theta_key is None:
        raise ValueError("a two-way factor needs at least one variable")
    if theta_key is None and theta_const is None:
        raise ValueError("either theta_key or theta_const is needed")
    s_static, s_dynamic = camera_sigmas(sigma)
    sigmas = (s_dynamic, s_static)  # the blocks of two_way_residuals: dynamic image, then static image
    keep = [kin_key is not None, theta_key is not None]
    keys = [k for k, use in zip((kin_key, theta_key), keep, strict=True) if use]

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[FloatArray] | None) -> FloatArray:
        kin_free = values.atVector(kin_key) if kin_key is not None else None
        theta = values.atVector(theta_key) if theta_key is not None else theta_const
        blocks = two_way_residuals(layout, kin_free, theta, P_s, z_d, P_d, z_s, cams, H is not None)
        if H is None:
            return _finish(blocks, sigmas, robust, None)
        return _finish(_select(blocks, keep), sigmas, robust, H)

    n_rows = 2 * (z_d.shape[0] + z_s.shape[0])
    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(n_rows), keys, error)


def mean_prior_factor(keys: list[int], component: int, value: float, sigma: float) -> gtsam.CustomFactor:
    """Prior on the mean over ``keys`` of one component of Vector variables (fixes a joint-angle offset)."""
    n = len(keys)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[FloatArray] | None) -> FloatArray:
        vecs = [values.atVector(k) for k in keys]
        if H is not None:
            for i, v in enumerate(vecs):
                J = np.zeros((1, v.shape[0]))
                J[0, component] = 1.0 / (n * sigma)
                H[i] = J
        return np.array([(np.mean([v[component] for v in vecs]) - value) / sigma])

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(1), keys, error)


def linear_prior_factor(key: int, W: FloatArray, x0: FloatArray) -> gtsam.CustomFactor:
    """Whitened linear prior ``r = W (x - x0)`` on a Vector variable ``x`` (``W``: (k, n), already
    whitened, so the factor has a unit noise model; Jacobian ``W``). Holds the directions spanned by
    the rows of ``W`` at ``x0`` (weak priors on degenerate directions, nominal-geometry priors)."""
    W = np.atleast_2d(np.asarray(W, dtype=float))
    x0 = np.asarray(x0, dtype=float).reshape(-1)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list[FloatArray] | None) -> FloatArray:
        x = values.atVector(key)
        if H is not None:
            H[0] = W.copy()
        return W @ (x - x0)

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(W.shape[0]), [key], error)
