"""Two-view geometry checks on undistorted normalized image coordinates.

All points are normalized coordinates ``(x/z, y/z)`` of a calibrated camera (no intrinsics,
no distortion).  ``T_ba`` maps points of camera frame ``a`` into camera frame ``b`` (metres),
``R_ba`` is its rotation.  Errors are in normalized units (multiply by a focal length for pixels,
or read them as angles in radians near the image centre).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from factors.chain import skew

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


def homogeneous(xy: FloatArray) -> FloatArray:
    """(N, 2) normalized coordinates -> (N, 3) bearing rays ``[x, y, 1]``."""
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    return np.hstack([xy, np.ones((xy.shape[0], 1))])


def essential(T_ba: FloatArray) -> FloatArray:
    """Essential matrix ``E = [t]x R`` with ``x_b^T E x_a = 0`` for ``T_ba = [R t]``."""
    return skew(T_ba[:3, 3]) @ T_ba[:3, :3]


def epipolar_distance(E: FloatArray, xy_a: FloatArray, xy_b: FloatArray) -> FloatArray:
    """Symmetric-free distance of ``xy_b`` from the epipolar line ``E x_a`` in image b (N,).

    The line ``l = E x_a`` is normalized by ``|l[:2]|``; a zero-length line (a ray through the
    epipole) gives distance 0.
    """
    ha, hb = homogeneous(xy_a), homogeneous(xy_b)
    lines = ha @ E.T
    norm = np.linalg.norm(lines[:, :2], axis=1)
    return np.abs(np.sum(lines * hb, axis=1)) / np.maximum(norm, 1e-12)


def sampson_distance(E: FloatArray, xy_a: FloatArray, xy_b: FloatArray) -> FloatArray:
    """First-order geometric (Sampson) error of correspondences under ``E`` (N,), normalized units."""
    ha, hb = homogeneous(xy_a), homogeneous(xy_b)
    Ea = ha @ E.T
    Etb = hb @ E
    num = np.sum(hb * Ea, axis=1)
    den = Ea[:, 0] ** 2 + Ea[:, 1] ** 2 + Etb[:, 0] ** 2 + Etb[:, 1] ** 2
    return np.abs(num) / np.sqrt(np.maximum(den, 1e-24))


def rotation_prediction(R_ba: FloatArray, xy_a: FloatArray) -> tuple[FloatArray, BoolArray]:
    """Where points of image a at infinite depth appear in image b: (N, 2) and in-front mask."""
    rays = homogeneous(xy_a) @ R_ba.T
    front = rays[:, 2] > 1e-6
    z = np.where(front, rays[:, 2], 1.0)
    return rays[:, :2] / z[:, None], front


def depth_segment_distance(T_ba: FloatArray, xy_a: FloatArray, xy_b: FloatArray, min_depth: float) -> FloatArray:
    """Distance of ``xy_b`` from the image in b of the ray of ``xy_a`` for depths in [min_depth, inf).

    The ray's points ``z * [x_a, y_a, 1]`` with ``z >= min_depth`` (metres, along the optical axis
    of a) project into b on a segment from ``pi(R x_a)`` (infinite depth) to
    ``pi(R x_a min_depth + t)``.  This is the epipolar check restricted to plausible depths, the
    right test between two cameras a few centimetres apart.  Points whose near end falls behind
    camera b use only the far end.  Returns (N,) normalized distances (inf if both ends are behind b).
    """
    R, t = T_ba[:3, :3], T_ba[:3, 3]
    rays = homogeneous(xy_a) @ R.T
    near = rays * min_depth + t
    out = np.full(rays.shape[0], np.inf)
    p = np.asarray(xy_b, dtype=float).reshape(-1, 2)
    far_ok = rays[:, 2] > 1e-9
    near_ok = near[:, 2] > 1e-9
    a = np.where(far_ok[:, None], rays[:, :2] / np.where(far_ok, rays[:, 2], 1.0)[:, None], np.nan)
    b = np.where(near_ok[:, None], near[:, :2] / np.where(near_ok, near[:, 2], 1.0)[:, None], np.nan)
    both = far_ok & near_ok
    if np.any(both):
        ab = b[both] - a[both]
        ap = p[both] - a[both]
        s = np.clip(np.sum(ap * ab, axis=1) / np.maximum(np.sum(ab * ab, axis=1), 1e-24), 0.0, 1.0)
        out[both] = np.linalg.norm(ap - s[:, None] * ab, axis=1)
    only_far = far_ok & ~near_ok
    out[only_far] = np.linalg.norm(p[only_far] - a[only_far], axis=1)
    only_near = near_ok & ~far_ok
    out[only_near] = np.linalg.norm(p[only_near] - b[only_near], axis=1)
    return out


def kabsch_rotation(u: FloatArray, v: FloatArray) -> FloatArray:
    """Rotation R minimizing ``sum |v_i - R u_i|^2`` for unit vectors (N, 3); batched over leading
    axes: (..., N, 3) -> (..., 3, 3)."""
    H = np.swapaxes(u, -1, -2) @ v
    U, _, Vt = np.linalg.svd(H)
    V, Ut = np.swapaxes(Vt, -1, -2), np.swapaxes(U, -1, -2)
    sign = np.sign(np.linalg.det(V @ Ut))
    D = np.zeros(H.shape)
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = np.where(sign == 0, 1.0, sign)
    return V @ D @ Ut


def _segment_distance_batch(
    R: FloatArray, t: FloatArray, xy_a: FloatArray, xy_b: FloatArray, zmin: float
) -> FloatArray:
    """:func:`depth_segment_distance` for a batch of rotations (B, 3, 3) sharing ``t``: (B, N)."""
    rays = np.einsum("bij,nj->bni", R, homogeneous(xy_a))
    near = rays * zmin + t
    far_z = np.where(rays[..., 2] > 1e-9, rays[..., 2], np.nan)
    near_z = np.where(near[..., 2] > 1e-9, near[..., 2], np.nan)
    a = rays[..., :2] / far_z[..., None]
    b = near[..., :2] / near_z[..., None]
    b = np.where(np.isnan(b), a, b)
    ab = b - a
    ap = xy_b[None] - a
    s = np.clip(np.sum(ap * ab, axis=-1) / np.maximum(np.sum(ab * ab, axis=-1), 1e-24), 0.0, 1.0)
    out = np.linalg.norm(ap - s[..., None] * ab, axis=-1)
    return np.where(np.isnan(out), np.inf, out)


def rotation_ransac(
    xy_a: FloatArray,
    xy_b: FloatArray,
    threshold: float,
    t_ba: FloatArray | None = None,
    min_depth: float = 0.3,
    max_iterations: int = 64,
    confidence: float = 0.999,
    seed: int = 0,
) -> tuple[FloatArray | None, BoolArray]:
    """Fit the rotation ``R_ba`` between two cameras robustly from correspondences.

    Hypotheses come from two correspondences (bearings aligned by :func:`kabsch_rotation`), drawn
    in batches of 16 until the usual RANSAC bound for ``confidence`` is met.  With no translation
    (``t_ba`` None) a correspondence is an inlier when the rotated bearing of a is within
    ``threshold`` radians of the bearing of b (right when the baseline is small against the scene
    depth).  With a translation ``t_ba`` (metres, e.g. from an extrinsic estimate whose rotation is
    out of date) the test is :func:`depth_segment_distance` under ``[R | t_ba]`` for depths
    >= ``min_depth``, which tolerates the parallax of near points.  Returns (R or None, inlier
    mask); None when fewer than 3 correspondences agree.
    """
    xy_a = np.asarray(xy_a, dtype=float).reshape(-1, 2)
    xy_b = np.asarray(xy_b, dtype=float).reshape(-1, 2)
    n = xy_a.shape[0]
    none = np.zeros(n, dtype=bool)
    if n < 3:
        return None, none
    u = homogeneous(xy_a)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = homogeneous(xy_b)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    cos_thr = np.cos(threshold)
    t = None if t_ba is None else np.asarray(t_ba, dtype=float).reshape(3)

    def inliers_of(R: FloatArray) -> BoolArray:  # (B, 3, 3) -> (B, N)
        if t is None:
            return np.einsum("bij,nj,ni->bn", R, u, v) > cos_thr
        return _segment_distance_batch(R, t, xy_a, xy_b, min_depth) < threshold

    rng = np.random.default_rng(seed)
    best, best_inl = None, none
    done, needed = 0, max_iterations
    while done < min(needed, max_iterations):
        batch = 16
        i = rng.integers(0, n, size=(batch, 2))
        i[:, 1] = (i[:, 0] + 1 + rng.integers(0, n - 1, size=batch)) % n
        R = kabsch_rotation(u[i], v[i])
        inl = inliers_of(R)
        k = int(np.argmax(inl.sum(axis=1)))
        if inl[k].sum() > best_inl.sum():
            best, best_inl = R[k], inl[k]
            w = best_inl.mean()
            needed = int(np.ceil(np.log(1 - confidence) / np.log(max(1 - w * w, 1e-12)))) if w < 1 else 1
        done += batch
    if best is None or best_inl.sum() < 3:
        return None, none
    R = kabsch_rotation(u[best_inl], v[best_inl])
    inl = inliers_of(R[None])[0]
    if inl.sum() >= best_inl.sum():
        best, best_inl = R, inl
    return best, best_inl
