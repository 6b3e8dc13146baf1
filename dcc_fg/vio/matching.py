"""Descriptor matching of tracked features between the static and the gimbal camera.

Features are KLT-tracked corners (pixels of the distorted image, OpenCV's convention).  They get
rotation-invariant ORB descriptors: the orientation is the intensity-centroid angle of a 31-pixel
disc (Rublee et al.), computed here because ``ORB.compute`` keeps the angle it is given and the
gimbal camera may be rolled against the static one.  Matches are mutual nearest neighbours that
pass Lowe's ratio test and a Hamming-distance bound.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

PATCH = 31
_HALF = PATCH // 2
_yy, _xx = np.mgrid[-_HALF : _HALF + 1, -_HALF : _HALF + 1]
_DISC = (_xx**2 + _yy**2) <= _HALF**2
_WX = (_xx * _DISC).astype(np.float32).ravel()
_WY = (_yy * _DISC).astype(np.float32).ravel()


def orientation_deg(gray: NDArray[np.uint8], pts: FloatArray) -> FloatArray:
    """Intensity-centroid orientation (degrees, OpenCV's keypoint convention) at pixels (N, 2)."""
    n = pts.shape[0]
    if n == 0:
        return np.zeros(0)
    padded = cv2.copyMakeBorder(gray, _HALF, _HALF, _HALF, _HALF, cv2.BORDER_REFLECT_101)
    cx = np.clip(np.rint(pts[:, 0]).astype(np.int64), 0, gray.shape[1] - 1)
    cy = np.clip(np.rint(pts[:, 1]).astype(np.int64), 0, gray.shape[0] - 1)
    # (N, 31, 31) patches centred on the points: the padded image's window view, gathered per point
    patches = np.lib.stride_tricks.sliding_window_view(padded, (PATCH, PATCH))[cy, cx]
    flat = patches.reshape(n, PATCH * PATCH).astype(np.float32)
    m10 = flat @ _WX
    m01 = flat @ _WY
    return np.degrees(np.arctan2(m01, m10)) % 360.0


class OrbDescriber:
    """ORB descriptors at given pixel locations (32 bytes each)."""

    def __init__(self) -> None:
        self._orb = cv2.ORB_create(edgeThreshold=_HALF + 1, patchSize=PATCH)

    def describe(self, gray: NDArray[np.uint8], pts: FloatArray) -> tuple[IntArray, NDArray[np.uint8]]:
        """Descriptors of the points that are far enough from the border.

        Returns (indices into ``pts`` of the described points, (M, 32) uint8 descriptors).
        """
        if pts.shape[0] == 0:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 32), dtype=np.uint8)
        angles = orientation_deg(gray, pts)
        kps = [
            cv2.KeyPoint(float(x), float(y), float(PATCH), float(a), 0.0, 0, int(i))
            for i, ((x, y), a) in enumerate(zip(pts, angles, strict=True))
        ]
        kps, desc = self._orb.compute(gray, kps)
        if desc is None or len(kps) == 0:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 32), dtype=np.uint8)
        return np.array([k.class_id for k in kps], dtype=np.int64), desc


def mutual_ratio_matches(
    desc_a: NDArray[np.uint8], desc_b: NDArray[np.uint8], ratio: float, max_distance: int
) -> tuple[IntArray, IntArray, IntArray]:
    """Mutual nearest neighbours (Hamming) passing the ratio test in both directions and a distance bound.

    Returns (indices into a, indices into b, Hamming distances).
    """
    empty = np.zeros(0, dtype=np.int64)
    if desc_a.shape[0] == 0 or desc_b.shape[0] == 0:
        return empty, empty, empty
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)

    def best(q: NDArray[np.uint8], t: NDArray[np.uint8]) -> tuple[IntArray, FloatArray, FloatArray]:
        idx = np.full(q.shape[0], -1, dtype=np.int64)
        d1 = np.full(q.shape[0], np.inf)
        d2 = np.full(q.shape[0], np.inf)
        for m in bf.knnMatch(q, t, k=2):
            if not m:
                continue
            idx[m[0].queryIdx] = m[0].trainIdx
            d1[m[0].queryIdx] = m[0].distance
            if len(m) > 1:
                d2[m[0].queryIdx] = m[1].distance
        return idx, d1, d2

    ab, d1a, d2a = best(desc_a, desc_b)
    ba, d1b, d2b = best(desc_b, desc_a)
    ia = np.arange(desc_a.shape[0])
    ok = ab >= 0
    ok[ok] = ba[ab[ok]] == ia[ok]
    ok &= (d1a <= max_distance) & (d1a < ratio * d2a)
    ok[ok] &= d1b[ab[ok]] < ratio * d2b[ab[ok]]
    sel = np.flatnonzero(ok)
    return sel.astype(np.int64), ab[sel], d1a[sel].astype(np.int64)
