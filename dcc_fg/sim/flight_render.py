"""Render a world of textured planes (ground, walls) into a camera with its true lens model.

Per pixel, the camera ray (from :meth:`CameraModel.undistort_points` on the pixel grid, computed
once per camera, so the images carry the model's distortion) is intersected with every plane;
the nearest hit inside a plane's rectangle gives texture coordinates, and all planes' textures
live in one atlas sampled with one ``cv2.remap`` per mip level (the level is chosen per pixel from
the ray's footprint, which keeps distant ground from aliasing into flickering false corners).
Pixels that hit nothing show a flat sky.  Gaussian noise is added last.

The textures are procedural and deterministic in a seed: band-limited random noise summed over
several scales and pushed through a steep sigmoid, giving high-contrast blobs with sharp edges at
every scale, good corners for a KLT tracker.

Frames: world ``W`` (metres); ``T_cW`` maps world points into the camera frame (x right, y down,
z forward).  Pixels follow OpenCV's convention.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from dcc_fg.model import GimbalCalibration
from dcc_fg.sim.trajectory import FlightTruth, World
from factors.camera import CameraModel
from factors.chain import inv_se3

FloatArray = NDArray[np.float64]

SKY = 215.0
_PAD = 32  # texels between textures in the atlas (mip levels bleed by 2^level texels)


@dataclass(frozen=True)
class TexturedPlane:
    """A textured rectangle ``origin + a * u_axis + b * v_axis``, ``0 <= a <= size[0]``, ``0 <= b <= size[1]``.

    ``u_axis`` and ``v_axis`` are orthonormal (world frame); ``size`` in metres; ``seed`` picks the
    texture.
    """

    origin: tuple[float, float, float]
    u_axis: tuple[float, float, float]
    v_axis: tuple[float, float, float]
    size: tuple[float, float]
    seed: int = 0

    @property
    def normal(self) -> FloatArray:
        n = np.cross(np.asarray(self.u_axis, float), np.asarray(self.v_axis, float))
        return n / np.linalg.norm(n)


def procedural_texture(
    height: int, width: int, texel: float, seed: int, scales: tuple[float, ...] = (1.5, 0.5, 0.18, 0.07)
) -> NDArray[np.uint8]:
    """High-contrast multi-scale blob texture, (height, width) uint8, deterministic in ``seed``.

    ``scales`` are blob sizes in metres (``texel`` metres per texel); each scale's noise is drawn on
    a coarse grid and upsampled with bicubic interpolation, the sum goes through a sigmoid.
    """
    rng = np.random.default_rng(seed)
    acc = np.zeros((height, width), dtype=np.float32)
    for k, s in enumerate(scales):
        gw = max(int(np.ceil(width * texel / s)) + 3, 4)
        gh = max(int(np.ceil(height * texel / s)) + 3, 4)
        grid = rng.standard_normal((gh, gw)).astype(np.float32)
        up = cv2.resize(grid, (width, height), interpolation=cv2.INTER_CUBIC)
        acc += up * (0.7 + 0.1 * k)
    acc /= max(float(acc.std()), 1e-6)
    img = 127.5 + 110.0 * np.tanh(2.5 * acc)
    return np.clip(img, 0, 255).astype(np.uint8)


class WorldRenderer:
    """Renders :class:`TexturedPlane` worlds (see the module docstring).

    Args:
        planes: the world.
        texel: texture resolution, metres per texel.
        seed: added to every plane's seed.
        levels: mip levels.
    """

    def __init__(self, planes: list[TexturedPlane], texel: float = 0.02, seed: int = 0, levels: int = 4) -> None:
        if not planes:
            raise ValueError("the world needs at least one plane")
        self.planes = list(planes)
        self.texel = float(texel)
        textures = []
        for p in self.planes:
            w = max(int(np.ceil(p.size[0] / texel)), 2)
            h = max(int(np.ceil(p.size[1] / texel)), 2)
            textures.append(procedural_texture(h, w, texel, seed * 1000 + p.seed))
        width = max(t.shape[1] for t in textures) + 2 * _PAD
        offsets = []
        rows = []
        y = _PAD
        for t in textures:
            offsets.append((_PAD, y))
            block = np.full((t.shape[0] + _PAD, width), int(SKY), dtype=np.uint8)
            block[: t.shape[0], _PAD : _PAD + t.shape[1]] = t
            rows.append(block)
            y += t.shape[0] + _PAD
        atlas = np.vstack([np.full((_PAD, width), int(SKY), dtype=np.uint8), *rows])
        self.offsets = np.array(offsets, dtype=np.float32)
        self.mips = [atlas.astype(np.float32)]
        for _ in range(1, levels):
            self.mips.append(cv2.pyrDown(self.mips[-1]))
        self._rays: dict[CameraModel, tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]] = {}

    def rays(self, camera: CameraModel) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
        """Undistorted normalized coordinates ``x``, ``y`` of every pixel (rays ``[x, y, 1]``, camera
        frame) and the rays' lengths, each (H*W,) float32, cached per camera."""
        if camera not in self._rays:
            w, h = camera.resolution
            u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
            xy = camera.undistort_points(np.stack([u.ravel(), v.ravel()], axis=1))
            x = np.ascontiguousarray(xy[:, 0], dtype=np.float32)
            y = np.ascontiguousarray(xy[:, 1], dtype=np.float32)
            self._rays[camera] = (x, y, np.sqrt(x * x + y * y + 1.0).astype(np.float32))
        return self._rays[camera]

    def raycast(self, T_cW: FloatArray, xy: FloatArray) -> FloatArray:
        """World points (N, 3) where the rays of normalized coordinates ``xy`` (N, 2) of a camera
        at ``T_cW`` first hit a plane; NaN rows for rays that hit nothing (ground truth for tests)."""
        T_cW = np.asarray(T_cW, dtype=float)
        R_Wc = T_cW[:3, :3].T
        c_W = -R_Wc @ T_cW[:3, 3]
        r_W = np.hstack([np.asarray(xy, float).reshape(-1, 2), np.ones((len(xy), 1))]) @ R_Wc.T
        best = np.full(r_W.shape[0], np.inf)
        for p in self.planes:
            o, u_ax, v_ax, n = (np.asarray(x, float) for x in (p.origin, p.u_axis, p.v_axis, p.normal))
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (n @ (o - c_W)) / (r_W @ n)
            q = c_W + t[:, None] * r_W
            a, b = (q - o) @ u_ax, (q - o) @ v_ax
            hit = (t > 1e-3) & (t < best) & (a >= 0) & (a <= p.size[0]) & (b >= 0) & (b <= p.size[1])
            best[hit] = t[hit]
        out = c_W + best[:, None] * r_W
        out[~np.isfinite(best)] = np.nan
        return out

    def render(
        self,
        camera: CameraModel,
        T_cW: FloatArray,
        noise_sigma: float = 2.0,
        rng: np.random.Generator | None = None,
    ) -> NDArray[np.uint8]:
        """The (H, W) uint8 image of the world seen from the camera pose ``T_cW`` (world -> camera)."""
        T_cW = np.asarray(T_cW, dtype=float)
        R_Wc = T_cW[:3, :3].T
        c_W = -R_Wc @ T_cW[:3, 3]
        rx, ry, rlen = self.rays(camera)
        n_pix = rx.shape[0]
        best_t = np.full(n_pix, np.inf, dtype=np.float32)
        map_x = np.full(n_pix, -1.0, dtype=np.float32)
        map_y = np.full(n_pix, -1.0, dtype=np.float32)
        cos_inc = np.ones(n_pix, dtype=np.float32)
        for k, p in enumerate(self.planes):
            o = np.asarray(p.origin, float)
            u_ax, v_ax, n = np.asarray(p.u_axis, float), np.asarray(p.v_axis, float), p.normal
            # ray r_W = R_Wc r_c: a dot with a world axis is a dot of r_c = [x, y, 1] with R_Wc^T axis
            An, Au, Av = (R_Wc.T @ ax for ax in (n, u_ax, v_ax))
            dn = rx * np.float32(An[0]) + ry * np.float32(An[1]) + np.float32(An[2])
            dist = np.float32(n @ (o - c_W))
            with np.errstate(divide="ignore", invalid="ignore"):
                t = dist / dn
            ok = (t > 1e-3) & (t < best_t)
            idx = np.flatnonzero(ok)
            if idx.size == 0:
                continue
            ti = t[idx]
            xi, yi = rx[idx], ry[idx]
            a = np.float32(u_ax @ (c_W - o)) + ti * (
                xi * np.float32(Au[0]) + yi * np.float32(Au[1]) + np.float32(Au[2])
            )
            b = np.float32(v_ax @ (c_W - o)) + ti * (
                xi * np.float32(Av[0]) + yi * np.float32(Av[1]) + np.float32(Av[2])
            )
            inside = (a >= 0) & (a <= p.size[0]) & (b >= 0) & (b <= p.size[1])
            hit = idx[inside]
            best_t[hit] = ti[inside]
            map_x[hit] = self.offsets[k, 0] + a[inside] / self.texel
            map_y[hit] = self.offsets[k, 1] + (p.size[1] - b[inside]) / self.texel
            cos_inc[hit] = np.abs(dn[hit]) / rlen[hit]
        w, h = camera.resolution
        f = float(np.mean(camera.intrinsics[:2]))
        # texels per pixel along the ray (the larger axis of the footprint ellipse, roughly)
        footprint = best_t * rlen / (f * self.texel * np.maximum(cos_inc, 0.2))
        level = np.clip(np.floor(np.log2(np.maximum(footprint, 1e-6))), 0, len(self.mips) - 1).astype(np.int8)
        out = np.full(n_pix, SKY, dtype=np.float32)
        hit_any = np.isfinite(best_t)
        for lv, mip in enumerate(self.mips):
            sel = hit_any & (level == lv)
            if not np.any(sel):
                continue
            s = 0.5**lv
            out[sel] = _sample(mip, (map_x[sel] + 0.5) * s - 0.5, (map_y[sel] + 0.5) * s - 0.5)
        img = out.reshape(h, w)
        if noise_sigma > 0:
            rng = rng if rng is not None else np.random.default_rng()
            img = img + rng.normal(0.0, noise_sigma, img.shape).astype(np.float32)
        return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def _sample(img: NDArray[np.float32], x: NDArray[np.float32], y: NDArray[np.float32]) -> NDArray[np.float32]:
    """Bilinear samples of ``img`` at (x, y) (remap maps must be < 32767 wide: fold into rows)."""
    n = x.shape[0]
    cols = 1024
    rows = -(-n // cols)
    mx = np.zeros(rows * cols, dtype=np.float32)
    my = np.zeros(rows * cols, dtype=np.float32)
    mx[:n], my[:n] = x, y
    res = cv2.remap(
        img, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    return res.ravel()[:n]


def planes_from_world(world: World, seed: int = 0) -> list[TexturedPlane]:
    """The ground and walls of a :class:`~dcc_fg.sim.trajectory.World` as textured planes."""
    return [
        TexturedPlane(
            tuple(float(x) for x in o),  # type: ignore[arg-type]
            tuple(float(x) for x in u),  # type: ignore[arg-type]
            tuple(float(x) for x in v),  # type: ignore[arg-type]
            (float(eu), float(ev)),
            seed + k,
        )
        for k, (_, o, u, v, eu, ev) in enumerate(world.planes())
    ]


def render_flight(
    renderer: WorldRenderer,
    truth: FlightTruth,
    calibration: GimbalCalibration,
    T_sI: FloatArray,
    noise_sigma: float = 2.0,
    seed: int = 0,
    frames: slice | None = None,
) -> Iterator[tuple[int, NDArray[np.uint8], NDArray[np.uint8]]]:
    """Yield ``(t_ns, static image, gimbal image)`` at every camera frame of ``truth`` (or the
    ``frames`` slice of them), one at a time.

    Static camera pose ``T_sW = T_sI inv(T_WI)``; gimbal camera ``T_dW = T_ds(theta(t)) T_sW`` with
    the true joint angles; the cameras are the calibration's (true) models.
    """
    cam_s, cam_d = calibration.static_camera, calibration.dynamic_camera
    if cam_s is None or cam_d is None:
        raise ValueError("the calibration must carry both camera models to render a flight")
    rng = np.random.default_rng(seed)
    sel = frames if frames is not None else slice(None)
    t_frames = truth.frame_t_ns[sel]
    for i, t in zip(truth.index_of(t_frames), t_frames, strict=True):
        T_sW = T_sI @ inv_se3(truth.T_WI[i])
        T_dW = calibration.T_ds(truth.theta[i]) @ T_sW
        yield (
            int(t),
            renderer.render(cam_s, T_sW, noise_sigma, rng),
            renderer.render(cam_d, T_dW, noise_sigma, rng),
        )
