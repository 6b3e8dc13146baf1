"""Analytic Jacobians of the gimbal chain and the camera models against central finite differences."""

from __future__ import annotations

import cv2
import gtsam
import numpy as np
import pytest

from factors import chain
from factors.camera import CameraModel

H = 1e-6


def rel_err(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-12))


def random_kin(rng: np.random.Generator, L: int) -> np.ndarray:
    kin = rng.normal(size=chain.n_kin(L)) * 0.5
    return kin


@pytest.mark.parametrize("L", [0, 1, 2, 3])
@pytest.mark.parametrize("seed", range(5))
def test_chain_matches_composition(L: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    kin, th = random_kin(rng, L), rng.uniform(-np.pi, np.pi, L)
    tau_s, tau_d, dh = chain.split_kin(kin, L)
    A = np.eye(4)
    for (d, a, alpha), t in zip(dh, th, strict=True):
        A = A @ chain.dh_link(t, d, a, alpha)
    T = chain.se3_from_tau(tau_d) @ np.linalg.inv(A) @ chain.se3_from_tau(tau_s)
    np.testing.assert_allclose(chain.T_ds(kin, th, L), T, atol=1e-12)
    p = rng.normal(size=(7, 3))
    np.testing.assert_allclose(chain.transform_points(kin, th, p, L, False)[0], p @ T[:3, :3].T + T[:3, 3], atol=1e-12)


@pytest.mark.parametrize("L", [0, 1, 2, 3])
@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("inverse", [False, True])
def test_chain_point_jacobians(L: int, seed: int, inverse: bool) -> None:
    rng = np.random.default_rng(100 + seed)
    kin, th, p = random_kin(rng, L), rng.uniform(-np.pi, np.pi, L), rng.normal(size=(6, 3))
    f = chain.inverse_transform_points if inverse else chain.transform_points
    _, J = f(kin, th, p, L, True)
    assert J is not None
    for k in range(kin.size):
        e = np.zeros_like(kin)
        e[k] = H
        num = (f(kin + e, th, p, L, False)[0] - f(kin - e, th, p, L, False)[0]) / (2 * H)
        assert rel_err(J.d_kin[:, :, k], num) < 1e-6 or np.max(np.abs(J.d_kin[:, :, k] - num)) < 1e-8, chain.kin_names(
            L
        )[k]
    for k in range(L):
        e = np.zeros(L)
        e[k] = H
        num = (f(kin, th + e, p, L, False)[0] - f(kin, th - e, p, L, False)[0]) / (2 * H)
        assert rel_err(J.d_theta[:, :, k], num) < 1e-6
    for k in range(3):
        e = np.zeros(3)
        e[k] = H
        num = (f(kin, th, p + e, L, False)[0] - f(kin, th, p - e, L, False)[0]) / (2 * H)
        assert rel_err(np.broadcast_to(J.d_point[:, k], num.shape), num) < 1e-6


@pytest.mark.parametrize("L", [0, 1, 2, 3])
def test_T_ds_tangent_jacobian_matches_gtsam_local_coordinates(L: int) -> None:
    rng = np.random.default_rng(7)
    kin, th = random_kin(rng, L), rng.uniform(-np.pi, np.pi, L)
    Jk, Jt = chain.d_T_ds_tangent(kin, th, L)
    T0 = gtsam.Pose3(chain.T_ds(kin, th, L))
    for k in range(kin.size):
        e = np.zeros_like(kin)
        e[k] = H
        num = (
            T0.localCoordinates(gtsam.Pose3(chain.T_ds(kin + e, th, L)))
            - T0.localCoordinates(gtsam.Pose3(chain.T_ds(kin - e, th, L)))
        ) / (2 * H)
        assert np.max(np.abs(num - Jk[:, k])) < 1e-6 * max(1.0, np.max(np.abs(num)))
    for k in range(L):
        e = np.zeros(L)
        e[k] = H
        num = (
            T0.localCoordinates(gtsam.Pose3(chain.T_ds(kin, th + e, L)))
            - T0.localCoordinates(gtsam.Pose3(chain.T_ds(kin, th - e, L)))
        ) / (2 * H)
        assert rel_err(Jt[:, k], num) < 1e-6


@pytest.mark.parametrize("L", [0, 1, 2, 3])
@pytest.mark.parametrize("seed", range(3))
def test_batched_T_ds_tangent_jacobians_match_numerical_differentiation(L: int, seed: int) -> None:
    """d_T_ds_tangent_batch (adjoint form) against central differences of gtsam local coordinates,
    snapshot by snapshot, and T_ds_batch against T_ds."""
    rng = np.random.default_rng(300 + seed)
    kin, th = random_kin(rng, L), rng.uniform(-np.pi, np.pi, (4, L))
    T, Jk, Jt = chain.d_T_ds_tangent_batch(kin, th, L)
    np.testing.assert_allclose(chain.T_ds_batch(kin, th, L), T, atol=1e-14)
    for i in range(th.shape[0]):
        np.testing.assert_allclose(T[i], chain.T_ds(kin, th[i], L), atol=1e-12)
        T0 = gtsam.Pose3(T[i])

        def local(k: np.ndarray, t: np.ndarray, T0: gtsam.Pose3 = T0) -> np.ndarray:
            return T0.localCoordinates(gtsam.Pose3(chain.T_ds(k, t, L)))

        for k in range(kin.size):
            e = np.zeros_like(kin)
            e[k] = H
            num = (local(kin + e, th[i]) - local(kin - e, th[i])) / (2 * H)
            assert np.max(np.abs(num - Jk[i, :, k])) < 1e-6 * max(1.0, np.max(np.abs(num))), chain.kin_names(L)[k]
        for k in range(L):
            e = np.zeros(L)
            e[k] = H
            num = (local(kin, th[i] + e) - local(kin, th[i] - e)) / (2 * H)
            assert rel_err(Jt[i, :, k], num) < 1e-6
    with pytest.raises(ValueError, match="thetas"):
        chain.T_ds_batch(kin, np.zeros((3, L + 1)), L)


def test_tau_round_trip() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        tau = np.concatenate(
            [rng.uniform(-3, 3, 1), rng.uniform(-1.5, 1.5, 1), rng.uniform(-3, 3, 1), rng.normal(size=3)]
        )
        np.testing.assert_allclose(chain.tau_from_se3(chain.se3_from_tau(tau)), tau, atol=1e-10)


CAMERAS = [
    CameraModel((460.0, 455.0, 320.0, 240.0), "radtan", (-0.2, 0.05, 0.001, -0.002)),
    CameraModel((380.0, 381.0, 510.0, 505.0), "equidistant", (0.02, -0.01, 0.003, -0.001), (1024, 1024)),
    CameraModel((460.0, 460.0, 320.0, 240.0), "none", ()),
]


@pytest.mark.parametrize("cam", CAMERAS, ids=lambda c: c.distortion_model)
def test_projection_jacobian(cam: CameraModel) -> None:
    rng = np.random.default_rng(1)
    p = rng.normal(size=(50, 3)) * [0.4, 0.3, 0.2] + [0, 0, 1.0]
    _, J = cam.project(p)
    assert J is not None
    for k in range(3):
        e = np.zeros(3)
        e[k] = H
        num = (cam.project(p + e, False)[0] - cam.project(p - e, False)[0]) / (2 * H)
        assert rel_err(J[:, :, k], num) < 1e-6


@pytest.mark.parametrize("cam", CAMERAS[:2], ids=lambda c: c.distortion_model)
def test_projection_matches_opencv_and_undistort_inverts(cam: CameraModel) -> None:
    rng = np.random.default_rng(2)
    p = rng.normal(size=(40, 3)) * [0.3, 0.2, 0.1] + [0, 0, 1.0]
    uv, _ = cam.project(p, False)
    if cam.distortion_model == "equidistant":
        ref, _ = cv2.fisheye.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.opencv_dist)
    else:
        ref, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), cam.K, cam.opencv_dist)
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-9)
    np.testing.assert_allclose(cam.undistort_points(uv), p[:, :2] / p[:, 2:], atol=1e-10)
