"""Rendered images of a planar calibration target seen through a camera model (distortion included).

Rendering is per-pixel inverse mapping, so the lens model is applied exactly, not approximated:

1. every output pixel is split into ``supersample`` x ``supersample`` sub-pixel samples; the
   sample positions (pixels, OpenCV convention: the centre of pixel (col j, row i) is at
   ``u = j, v = i``) are undistorted once per camera into normalized image coordinates
   ``(x_n, y_n)`` (a ray ``(x_n, y_n, 1)`` in the camera frame), and cached;
2. per image, each ray is intersected with the target plane ``z_t = 0``: with
   ``T_ct = [R | t]`` (target -> camera) the plane point ``(x, y)`` (metres, target frame) is
   ``q = [R_1 R_2 t]^-1 (x_n, y_n, 1)``, ``(x, y) = q_12 / q_3``; rays with ``q_3 <= 0`` (target
   behind the camera) see the background;
3. the board texture (a raster of the printed board, see :func:`make_texture`, blurred as in
   step 4) is sampled there bilinearly (``cv2.remap``) and the sub-pixel samples are averaged back to one
   pixel (``cv2.resize`` with ``INTER_AREA``, an exact box filter for integer factors);
4. optics blur is applied to the board texture before it is sampled (a Gaussian of
   ``blur_sigma_px`` image pixels at the board centre's depth, converted to texels), which
   band-limits the texture so that the sub-pixel samples do not alias (blurring after sampling
   leaves aliasing that moves detected corners by ~0.05 px in a pattern correlated between
   neighbouring corners); Gaussian sensor noise is added and the image quantized to 8 bits.

Printed boards (target frame t: x along the columns, y along the rows, z = 0 on the board,
metres; the same corner geometry as :class:`~dcc_fg.targets.TargetGeometry`):

* ``checkerboard``: ``(cols + 1) x (rows + 1)`` squares around the inner corners, the square
  touching only corner 0 (outside the corner grid) black, as :mod:`dcc_fg.detection` expects,
  plus a white margin of one square; seen from the side the target z axis points away from
  (the detector's handedness, and the simulator's board poses).
* ``aprilgrid`` (Kalibr): tag36h11 tags (OpenCV's ``DICT_APRILTAG_36h11`` bit patterns) with a
  2-cell black border, black squares of side ``tagSpacing * tagSize`` at every tag corner, a
  white margin.  The tag images are placed so that a camera on the side the target z axis
  points to (Kalibr's convention) sees them unmirrored; :func:`aprilgrid_view_flip` turns a
  pose whose z axis points away from the camera into such a pose with the same corner pixels.

Intensities are grey levels on the 0-255 scale.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray

from dcc_fg.targets import TargetGeometry
from factors.camera import CameraModel

FloatArray = NDArray[np.float64]

#: Black border of Kalibr's AprilGrid tags, in bit cells, and the tag36h11 data bits per side.
APRILGRID_BORDER_BITS = 2
TAG36H11_BITS = 6


@dataclass(frozen=True)
class RenderConfig:
    """Image formation parameters.

    Attributes:
        supersample: sub-pixel samples per pixel and axis (anti-aliasing), >= 1.
        blur_sigma_px: Gaussian blur of the optics, image pixels at the board centre's depth
            (applied on the board, see the module docstring; 0 disables).
        noise_sigma: Gaussian sensor noise, grey levels (0-255 scale).
        black, white: grey levels of the printed black and white.
        background: grey level of the scene around the board.
        texel_m: largest texture pixel of the board raster, metres.
    """

    supersample: int = 2
    blur_sigma_px: float = 0.6
    noise_sigma: float = 2.0
    black: float = 30.0
    white: float = 220.0
    background: float = 120.0
    texel_m: float = 0.5e-3

    def __post_init__(self) -> None:
        if self.supersample < 1:
            raise ValueError(f"supersample must be >= 1, got {self.supersample}")
        if self.blur_sigma_px < 0 or self.noise_sigma < 0 or self.texel_m <= 0:
            raise ValueError("blur_sigma_px and noise_sigma must be >= 0, texel_m > 0")


@dataclass(frozen=True)
class BoardTexture:
    """An area-averaged raster of a printed board.

    Attributes:
        image: (H, W) float32 reflectance in [0, 1] (0 black, 1 white); texel (col i, row j)
            covers target x in ``[x0 + i * texel, x0 + (i + 1) * texel]`` and y likewise.
        x0, y0: target-frame coordinates of the raster's outer corner, metres.
        texel: texel side, metres.
    """

    image: NDArray[np.float32]
    x0: float
    y0: float
    texel: float


def _checkerboard_reflectance(target: TargetGeometry, x: FloatArray, y: FloatArray) -> FloatArray:
    """1 white / 0 black at target points (x, y) metres; white margin of one square around."""
    sx, sy = target.col_spacing, target.row_spacing
    i = np.floor(x / sx).astype(np.int64) + 1  # square column 0 .. cols (square i spans corners i-1 .. i)
    j = np.floor(y / sy).astype(np.int64) + 1
    inside = (i >= 0) & (i <= target.cols) & (j >= 0) & (j <= target.rows)
    black = inside & ((i + j) % 2 == 0)  # the square touching only corner 0 (i = j = 0) is black
    return np.where(black, 0.0, 1.0)


@lru_cache(maxsize=8)
def _tag_cells(n_tags: int) -> NDArray[np.uint8]:
    """(n_tags, 10, 10) canonical tag36h11 images (1 = white), one cell per bit, 2-cell border."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    cells = TAG36H11_BITS + 2 * APRILGRID_BORDER_BITS
    if n_tags > dictionary.bytesList.shape[0]:
        raise ValueError(
            f"an AprilGrid of {n_tags} tags needs more than the {dictionary.bytesList.shape[0]} tag36h11 ids"
        )
    out = np.empty((n_tags, cells, cells), dtype=np.uint8)
    for k in range(n_tags):
        img = cv2.aruco.generateImageMarker(dictionary, k, cells, borderBits=APRILGRID_BORDER_BITS)
        out[k] = (img > 127).astype(np.uint8)
    return out


def _aprilgrid_reflectance(target: TargetGeometry, x: FloatArray, y: FloatArray) -> FloatArray:
    """1 white / 0 black at target points (x, y) metres for a Kalibr AprilGrid.

    Tag k spans ``[c * pitch, c * pitch + tagSize]`` in x (c = k % cols) and likewise in y
    (row k // cols).  Its canonical image (x right, y down, as OpenCV draws it) maps to the target
    with Kalibr corner 0 (target offset (0, 0)) at the canonical top-right, corner 1 at the
    top-left, corner 2 at the bottom-left (the arrangement :mod:`dcc_fg.detection` reads), i.e.
    canonical column = cells - 1 - (tag-local x in cells), canonical row = tag-local y in cells.
    """
    ts = target.tag_size
    gap = target.tag_spacing * ts
    pitch = ts + gap
    cells = TAG36H11_BITS + 2 * APRILGRID_BORDER_BITS
    tags = _tag_cells(target.cols * target.rows)
    out = np.ones_like(x)
    c = np.floor(x / pitch).astype(np.int64)
    r = np.floor(y / pitch).astype(np.int64)
    lx, ly = x - c * pitch, y - r * pitch
    on_tag = (c >= 0) & (c < target.cols) & (r >= 0) & (r < target.rows) & (lx < ts) & (ly < ts)
    k = np.where(on_tag, r * target.cols + c, 0)
    col = np.clip(cells - 1 - np.floor(lx / ts * cells).astype(np.int64), 0, cells - 1)
    row = np.clip(np.floor(ly / ts * cells).astype(np.int64), 0, cells - 1)
    out = np.where(on_tag, tags[k, row, col].astype(float), out)
    # black squares (side gap) at every tag corner: crossing (cc, rr) spans [cc*pitch - gap, cc*pitch]
    cx = np.floor((x + gap) / pitch).astype(np.int64)
    cy = np.floor((y + gap) / pitch).astype(np.int64)
    in_sq_x = (x + gap - cx * pitch) < gap
    in_sq_y = (y + gap - cy * pitch) < gap
    square = in_sq_x & in_sq_y & (cx >= 0) & (cx <= target.cols) & (cy >= 0) & (cy <= target.rows)
    return np.where(square, 0.0, out)


def board_extent(target: TargetGeometry) -> tuple[float, float, float, float]:
    """(x_min, y_min, x_max, y_max) of the printed board including its white margin, metres."""
    if target.target_type == "checkerboard":
        mx, my = 2.0 * target.col_spacing, 2.0 * target.row_spacing
        return -mx, -my, target.cols * target.col_spacing + mx, target.rows * target.row_spacing + my
    if target.target_type != "aprilgrid":
        raise ValueError(f"target_type '{target.target_type}' cannot be rendered (checkerboard, aprilgrid)")
    gap = target.tag_spacing * target.tag_size
    pitch = target.tag_size + gap
    m = gap + 0.5 * target.tag_size
    return -m, -m, target.cols * pitch - gap + m, target.rows * pitch - gap + m


def _feature_unit(target: TargetGeometry) -> tuple[float, float] | None:
    """Grid (x, y) in metres on which every edge of the printed board lies, or None if there is none
    (an AprilGrid whose gap is not a whole number of bit cells)."""
    if target.target_type == "checkerboard":
        return target.col_spacing, target.row_spacing
    cells = TAG36H11_BITS + 2 * APRILGRID_BORDER_BITS
    gap_cells = target.tag_spacing * cells
    if abs(gap_cells - round(gap_cells)) > 1e-9 or round(gap_cells) == 0:
        return None
    unit = target.tag_size / cells
    if abs(round(gap_cells) % 2) == 1:  # the margin (gap + tagSize / 2) must lie on the grid too
        unit /= 2.0
    return unit, unit


def make_texture(target: TargetGeometry, texel_max: float = 0.5e-3, oversample: int = 8) -> BoardTexture:
    """Rasterize the printed board.

    When every edge of the board lies on a regular grid (checkerboards; AprilGrids whose gap is a
    whole number of bit cells, e.g. Kalibr's usual ratio 0.3), the texel divides that grid, so every
    texel is purely black or white and bilinear sampling puts each edge exactly where it is printed.
    Otherwise each texel is the mean of ``oversample**2`` point samples (edges then move by up to
    ``texel / (2 * oversample)``).  The texel is square, at most ``texel_max`` metres.
    """
    x_min, y_min, x_max, y_max = board_extent(target)
    unit = _feature_unit(target)
    if unit is not None:
        texel = min(unit) / int(np.ceil(min(unit) / texel_max))
        if any(abs(u / texel - round(u / texel)) > 1e-9 for u in unit):  # unequal spacings: common divisor
            texel = texel_max / 4.0
            unit = None
        else:
            oversample = 1
    else:
        texel = texel_max
    w = int(round((x_max - x_min) / texel)) if unit is not None else int(np.ceil((x_max - x_min) / texel))
    h = int(round((y_max - y_min) / texel)) if unit is not None else int(np.ceil((y_max - y_min) / texel))
    offs = (np.arange(oversample) + 0.5) / oversample
    xs = x_min + (np.arange(w)[:, None] + offs[None, :]).ravel() * texel
    ys = y_min + (np.arange(h)[:, None] + offs[None, :]).ravel() * texel
    func = _checkerboard_reflectance if target.target_type == "checkerboard" else _aprilgrid_reflectance
    img = np.empty((h, w), dtype=np.float32)
    rows_per_chunk = max(1, 4_000_000 // (w * oversample * oversample))
    for j0 in range(0, h, rows_per_chunk):
        j1 = min(h, j0 + rows_per_chunk)
        yy, xx = np.meshgrid(ys[j0 * oversample : j1 * oversample], xs, indexing="ij")
        vals = func(target, xx, yy).reshape(j1 - j0, oversample, w, oversample)
        img[j0:j1] = vals.mean(axis=(1, 3))
    return BoardTexture(img, x_min, y_min, texel)


@lru_cache(maxsize=8)
def _rays(camera: CameraModel, supersample: int) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Normalized coordinates (x_n, y_n) of every sub-pixel sample, each (S*H, S*W) float32."""
    w, h = camera.resolution
    s = supersample
    u = (np.arange(s * w) + 0.5) / s - 0.5
    v = (np.arange(s * h) + 0.5) / s - 0.5
    uu, vv = np.meshgrid(u, v)
    xy = camera.undistort_points(np.stack([uu.ravel(), vv.ravel()], axis=1))
    return xy[:, 0].reshape(s * h, s * w).astype(np.float32), xy[:, 1].reshape(s * h, s * w).astype(np.float32)


def render_view(
    camera: CameraModel,
    T_ct: FloatArray,
    texture: BoardTexture,
    config: RenderConfig,
    rng: np.random.Generator,
) -> NDArray[np.uint8]:
    """Render the board seen by ``camera`` with target pose ``T_ct`` (target -> camera, 4x4, m).

    Returns:
        (H, W) uint8 grey image of the camera's resolution.
    """
    xn, yn = _rays(camera, config.supersample)
    R, t = T_ct[:3, :3], T_ct[:3, 3]
    Hinv = np.linalg.inv(np.column_stack([R[:, 0], R[:, 1], t])).astype(np.float32)
    q3 = Hinv[2, 0] * xn + Hinv[2, 1] * yn + Hinv[2, 2]
    front = q3 > 1e-9
    inv = np.where(front, 1.0 / np.where(front, q3, 1.0), 0.0).astype(np.float32)
    x = (Hinv[0, 0] * xn + Hinv[0, 1] * yn + Hinv[0, 2]) * inv
    y = (Hinv[1, 0] * xn + Hinv[1, 1] * yn + Hinv[1, 2]) * inv
    mapx = np.where(front, (x - texture.x0) / texture.texel - 0.5, -10.0).astype(np.float32)
    mapy = np.where(front, (y - texture.y0) / texture.texel - 0.5, -10.0).astype(np.float32)
    lo, hi = config.black, config.white
    tex = (lo + (hi - lo) * texture.image).astype(np.float32)
    if config.blur_sigma_px > 0:
        # optics blur applied on the board (band-limits the texture before it is sampled, so the
        # sub-pixel samples do not alias): blur_sigma_px at the board centre's depth, in texels
        depth = float((T_ct[:3, :3] @ _board_centre(texture) + T_ct[:3, 3])[2])
        focal = 0.5 * (camera.intrinsics[0] + camera.intrinsics[1])
        sigma_tex = config.blur_sigma_px * max(depth, 1e-6) / focal / texture.texel
        tex = cv2.GaussianBlur(tex, (0, 0), sigma_tex, borderType=cv2.BORDER_REPLICATE)
    fine = cv2.remap(
        tex, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=float(config.background)
    )
    w, h = camera.resolution
    img = cv2.resize(fine, (w, h), interpolation=cv2.INTER_AREA) if config.supersample > 1 else fine
    if config.noise_sigma > 0:
        img = img + rng.normal(scale=config.noise_sigma, size=img.shape).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _board_centre(texture: BoardTexture) -> FloatArray:
    """Centre of the board raster in the target frame (metres, z = 0)."""
    h, w = texture.image.shape
    return np.array([texture.x0 + 0.5 * w * texture.texel, texture.y0 + 0.5 * h * texture.texel, 0.0])


def aprilgrid_view_flip(target: TargetGeometry) -> FloatArray:
    """4x4 T_tt' that turns the board over in place: ``(x, y, z) -> (x, y_max - y, -z)``.

    The AprilGrid's corner set is symmetric under this map (y_max = the corner set's extent in
    y), so ``T_ct @ aprilgrid_view_flip(target)`` puts the same corners on the same pixels (with
    other ids) while the target z axis now points towards the camera, the side from which Kalibr
    AprilGrids read unmirrored.
    """
    y_max = float(np.ptp(target.points[:, 1]))
    F = np.diag([1.0, -1.0, -1.0, 1.0])
    F[1, 3] = y_max
    return F
