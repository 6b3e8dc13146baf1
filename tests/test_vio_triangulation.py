"""Landmark triangulation of the smoother (linear DLT over the window's observations)."""

from __future__ import annotations

import gtsam
import numpy as np

from dcc_fg.vio.backend import triangulate
from factors.chain import inv_se3


def _views(p_W: np.ndarray, n: int, seed: int, sigma: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    T_Wc, xy = [], []
    for _ in range(n):
        T = np.eye(4)
        T[:3, :3] = gtsam.Rot3.Expmap(rng.normal(0.0, 0.1, 3)).matrix()
        T[:3, 3] = rng.normal(0.0, 0.5, 3)
        T_cW = inv_se3(T)
        p_c = T_cW[:3, :3] @ p_W + T_cW[:3, 3]
        T_Wc.append(T)
        xy.append(p_c[:2] / p_c[2] + rng.normal(0.0, sigma, 2))
    return np.array(T_Wc), np.array(xy)


def test_noise_free_views_give_the_point() -> None:
    p = np.array([1.0, -2.0, 8.0])
    for n in (2, 3, 7):
        T_Wc, xy = _views(p, n, n)
        assert np.allclose(triangulate(T_Wc, xy), p, atol=1e-9)


def test_noisy_views_scatter_as_the_geometry_predicts() -> None:
    """0.5 px (at 460 px focal length) on 6 views 0.5 m apart, point 8 m away: the depth error is
    about sigma * depth^2 / baseline ~ 1.1e-3 * 64 / 1 ~ 7 cm; lateral much less."""
    p = np.array([0.5, 0.2, 8.0])
    err = np.array([triangulate(*_views(p, 6, s, 0.5 / 460.0)) - p for s in range(200)])
    assert np.all(np.isfinite(err))
    assert np.linalg.norm(np.median(err, axis=0)) < 0.03
    assert 0.01 < np.sqrt(np.mean(err[:, 2] ** 2)) < 0.3
    assert np.sqrt(np.mean(err[:, :2] ** 2)) < np.sqrt(np.mean(err[:, 2] ** 2))
