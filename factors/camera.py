"""Camera projection models with analytic Jacobians (Kalibr's model names).

``pinhole`` with ``radtan`` distortion (k1, k2, p1, p2) or ``equidistant`` distortion
(k1..k4, the Kannala-Brandt / OpenCV fisheye model), or ``none``.
Points are in the camera frame (x right, y down, z forward), metres; pixels are (u, v).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

DISTORTION_MODELS = ("radtan", "equidistant", "none")
MIN_DEPTH = 1e-6
#: points per block of :meth:`CameraModel.undistort_points` (its arrays stay in the CPU cache)
UNDISTORT_BLOCK = 1 << 15


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics of one camera.

    Attributes:
        intrinsics: ``[fx, fy, cx, cy]`` in pixels.
        distortion_model: ``radtan`` | ``equidistant`` | ``none``.
        distortion_coeffs: radtan ``[k1, k2, p1, p2]``; equidistant ``[k1, k2, k3, k4]``.
        resolution: ``(width, height)`` in pixels.
        camera_model: only ``pinhole`` is supported.
    """

    intrinsics: tuple[float, float, float, float]
    distortion_model: str = "radtan"
    distortion_coeffs: tuple[float, ...] = field(default=(0.0, 0.0, 0.0, 0.0))
    resolution: tuple[int, int] = (640, 480)
    camera_model: str = "pinhole"

    def __post_init__(self) -> None:
        if self.camera_model != "pinhole":
            raise ValueError(f"camera_model '{self.camera_model}' is not supported (only 'pinhole')")
        if self.distortion_model not in DISTORTION_MODELS:
            raise ValueError(f"distortion_model '{self.distortion_model}' is not one of {', '.join(DISTORTION_MODELS)}")
        if len(self.intrinsics) != 4:
            raise ValueError(f"intrinsics must be [fx, fy, cx, cy], got {list(self.intrinsics)}")
        if self.distortion_model != "none" and len(self.distortion_coeffs) != 4:
            raise ValueError(
                f"{self.distortion_model} distortion needs 4 coefficients, got {list(self.distortion_coeffs)}"
            )

    @property
    def K(self) -> FloatArray:
        """3x3 camera matrix."""
        fx, fy, cx, cy = self.intrinsics
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @property
    def opencv_dist(self) -> FloatArray:
        """Distortion vector in OpenCV's order (radtan: k1 k2 p1 p2; equidistant: k1..k4)."""
        if self.distortion_model == "none":
            return np.zeros(4)
        return np.asarray(self.distortion_coeffs, dtype=float)

    def distort(self, xy: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Distort normalized coordinates ``xy`` (N, 2); returns distorted (N, 2) and d/dxy (N, 2, 2)."""
        x, y = xy[:, 0], xy[:, 1]
        n = xy.shape[0]
        J = np.zeros((n, 2, 2))
        if self.distortion_model == "none":
            J[:, 0, 0] = 1.0
            J[:, 1, 1] = 1.0
            return xy.copy(), J
        c = self.distortion_coeffs
        if self.distortion_model == "radtan":
            k1, k2, p1, p2 = c
            r2 = x * x + y * y
            radial = 1.0 + k1 * r2 + k2 * r2 * r2
            d_radial = k1 + 2.0 * k2 * r2  # d radial / d r2
            xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
            yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
            J[:, 0, 0] = radial + x * d_radial * 2.0 * x + 2.0 * p1 * y + p2 * 6.0 * x
            J[:, 0, 1] = x * d_radial * 2.0 * y + 2.0 * p1 * x + p2 * 2.0 * y
            J[:, 1, 0] = y * d_radial * 2.0 * x + p1 * 2.0 * x + 2.0 * p2 * y
            J[:, 1, 1] = radial + y * d_radial * 2.0 * y + p1 * 6.0 * y + 2.0 * p2 * x
            return np.stack([xd, yd], axis=1), J
        # equidistant: theta_d = th (1 + k1 th^2 + k2 th^4 + k3 th^6 + k4 th^8), xd = theta_d / r * x
        k1, k2, k3, k4 = c
        r = np.sqrt(x * x + y * y)
        th = np.arctan(r)
        th2 = th * th
        poly = 1.0 + th2 * (k1 + th2 * (k2 + th2 * (k3 + th2 * k4)))
        theta_d = th * poly
        d_theta_d = 1.0 + th2 * (3.0 * k1 + th2 * (5.0 * k2 + th2 * (7.0 * k3 + th2 * 9.0 * k4)))
        small = r < 1e-9
        r_safe = np.where(small, 1.0, r)
        scale = np.where(small, 1.0, theta_d / r_safe)
        # d scale / d r = (d theta_d/d th * d th/d r * r - theta_d) / r^2, d th / d r = 1 / (1 + r^2)
        d_scale_dr = np.where(small, 0.0, (d_theta_d / (1.0 + r * r) * r_safe - theta_d) / (r_safe * r_safe))
        ux, uy = x / r_safe, y / r_safe
        J[:, 0, 0] = scale + x * d_scale_dr * ux
        J[:, 0, 1] = x * d_scale_dr * uy
        J[:, 1, 0] = y * d_scale_dr * ux
        J[:, 1, 1] = scale + y * d_scale_dr * uy
        return np.stack([x * scale, y * scale], axis=1), J

    def project(self, p_c: FloatArray, jacobian: bool = True) -> tuple[FloatArray, FloatArray | None]:
        """Project camera-frame points (N, 3) to pixels (N, 2); Jacobian d uv / d p_c is (N, 2, 3).

        Points at depth <= 1e-6 m are projected with a clamped depth; callers that care should
        check :meth:`in_front`.
        """
        p_c = np.asarray(p_c, dtype=float).reshape(-1, 3)
        z = np.maximum(p_c[:, 2], MIN_DEPTH)
        inv_z = 1.0 / z
        xy = p_c[:, :2] * inv_z[:, None]
        xyd, J_dist = self.distort(xy)
        fx, fy, cx, cy = self.intrinsics
        uv = np.empty_like(xyd)
        uv[:, 0] = fx * xyd[:, 0] + cx
        uv[:, 1] = fy * xyd[:, 1] + cy
        if not jacobian:
            return uv, None
        # d xy / d p_c = [[1, 0, -x], [0, 1, -y]] / z, so J_dist times it column by column
        J = np.empty((p_c.shape[0], 2, 3))
        J[:, :, 0] = J_dist[:, :, 0] * inv_z[:, None]
        J[:, :, 1] = J_dist[:, :, 1] * inv_z[:, None]
        J[:, :, 2] = -(J_dist[:, :, 0] * xy[:, 0:1] + J_dist[:, :, 1] * xy[:, 1:2]) * inv_z[:, None]
        J[:, 0, :] *= fx
        J[:, 1, :] *= fy
        return uv, J

    def in_front(self, p_c: FloatArray) -> NDArray[np.bool_]:
        """True for points with positive depth."""
        return np.asarray(p_c)[:, 2] > MIN_DEPTH

    def in_image(self, uv: FloatArray, margin: float = 0.0) -> NDArray[np.bool_]:
        """True for pixels inside the image (with ``margin`` pixels of border)."""
        w, h = self.resolution
        return (uv[:, 0] >= margin) & (uv[:, 0] <= w - 1 - margin) & (uv[:, 1] >= margin) & (uv[:, 1] <= h - 1 - margin)

    def undistort_points(self, uv: FloatArray, iterations: int = 20) -> FloatArray:
        """Pixels (N, 2) to normalized image coordinates (N, 2): inverse of K and the distortion.

        Newton iterations on ``distort(xy) = K^-1 uv`` with the analytic 2x2 Jacobian (inverted in
        closed form), started at the distorted coordinates (converges in a few steps for the mild
        distortion of real lenses).  Each point stops once its step is below ``1e-14 (1 + |xy|)``
        (normalized units); only the points still moving are iterated, in blocks of
        ``UNDISTORT_BLOCK`` points (cache-sized).  A point that has not converged after
        ``iterations`` steps is returned at its last iterate (check the round trip through
        :meth:`project` if that matters).

        Raises:
            numpy.linalg.LinAlgError: a Newton step met an exactly singular distortion Jacobian.
        """
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        fx, fy, cx, cy = self.intrinsics
        target = np.stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy], axis=1)
        out = target.copy()
        for i0 in range(0, target.shape[0], UNDISTORT_BLOCK):
            block = slice(i0, i0 + UNDISTORT_BLOCK)
            out[block] = self._undistort_block(target[block], iterations)
        return out

    def _undistort_block(self, target: FloatArray, iterations: int) -> FloatArray:
        """Newton iterations ``xy <- xy + J^-1 (target - distort(xy))`` on the unconverged points only.

        ``target`` are distorted normalized coordinates (N, 2); returns undistorted ones (N, 2).
        """
        xy = target.copy()
        if self.distortion_model == "none":
            return xy
        idx = np.arange(target.shape[0])  # the points still iterated, compacted into x / tgt
        x, tgt = xy.copy(), target
        for _ in range(iterations):
            if idx.size == 0:
                break
            xyd, J = self.distort(x)
            rx = tgt[:, 0] - xyd[:, 0]
            ry = tgt[:, 1] - xyd[:, 1]
            a, b, c, d = J[:, 0, 0], J[:, 0, 1], J[:, 1, 0], J[:, 1, 1]
            det = a * d - b * c
            if not np.all(det != 0.0):
                raise np.linalg.LinAlgError("Singular matrix")
            inv_det = 1.0 / det
            sx = (d * rx - b * ry) * inv_det
            sy = (a * ry - c * rx) * inv_det
            x[:, 0] += sx
            x[:, 1] += sy
            size = 1.0 + np.maximum(np.abs(x[:, 0]), np.abs(x[:, 1]))
            moving = np.maximum(np.abs(sx), np.abs(sy)) >= 1e-14 * size
            if not np.all(moving):
                xy[idx[~moving]] = x[~moving]
                idx, x, tgt = idx[moving], x[moving], tgt[moving]
        xy[idx] = x
        return xy
