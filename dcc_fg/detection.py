"""Target detection in images: chessboards (OpenCV) and Kalibr AprilGrids (OpenCV ArUco).

Every detector returns an :class:`~dcc_fg.data.Observation`: target point ids (the row index into
:attr:`TargetGeometry.points`, see :mod:`dcc_fg.targets`) and pixel coordinates ``(u, v)`` in the
distorted image, OpenCV's convention (origin at the centre of the top-left pixel, u right, v down).
Nothing found gives an empty observation (``len(obs) == 0``), never ``None``.

Input images may be 8-bit or 16-bit, grey or colour (BGR / BGRA channel order, as ``cv2.imread``
and :mod:`dcc_fg.io.bags` return them); :func:`to_gray8` converts them.

Chessboards
    ``targetCols`` x ``targetRows`` inner corners, id = row * cols + col.  OpenCV's corner order
    may come out rotated by 180 degrees depending on the view, so the order is fixed from the
    square colours (after fixing the handedness: target z axis into the board): corner 0 is the
    corner whose diagonal square outside the corner grid (the board square touching corner 0
    only) is black.  For a board with one odd and one even inner-corner count (e.g. OpenCV's
    9x6) that makes the ids the same physical corners in every camera, however it is rolled.  A
    board whose two counts are both even or both odd is 180-degree symmetric *including its
    colours*; nothing in the image can tell its two orientations apart, so the ids of such a
    board are only defined up to that rotation and a warning is logged.  When the outermost
    corner row or column lies just outside the image, OpenCV's sector-based detector may return a
    full grid shifted by one row onto the L-shaped corners at the board's edge (every id one row
    off); such a grid is dropped: the ring of border squares one square beyond a true inner-corner
    grid continues the colour pattern, the uniform margin beyond a shifted grid does not
    (``_ring_matches``). A corner that lands off its X-junction (inside a square, on a small
    tilted board) is dropped when its grid neighbours put it elsewhere (``_off_grid_corners``).

AprilGrids (Kalibr)
    tag36h11 tags with a 2-bit black border, separated by gaps of ``tagSpacing * tagSize`` with
    black squares at the gap crossings.  Point id = 4 * tag_id + corner, corners 0 bottom-left,
    1 bottom-right, 2 top-right, 3 top-left in the target frame (as Kalibr and yac).  OpenCV
    returns the four corners of an AprilTag in the order (1, 0, 3, 2) of that convention (checked
    against yac's detections of real RealSense images: same ids, median difference 0.09 px).
    Detection runs in four steps:

    1. Candidates: OpenCV's ArUco detector (``DICT_APRILTAG_36h11``, ``markerBorderBits = 2``,
       no corner refinement) on the image and, if tags are still missing, on a copy whose dark
       regions are eroded by one pixel (in blurred images a tag merges with the gap squares that
       touch its corners, and its outline is no longer a quadrilateral).  Decoded tags whose id is
       outside the grid (false detections, another board) are dropped; quads OpenCV could not
       decode are decoded here (at most 2 bit errors) with the bits sampled on refined corners.
    2. Consistency: a tag that sits where none of its grid neighbours expects it is dropped.
    3. Grid completion: a tag still missing is predicted from its found neighbours (local
       homography target plane -> image), snapped to an undecoded quad if one is there, refined,
       and accepted only if its bits read as the expected id within ``max_bit_errors`` errors and
       its black border is intact.
    4. Every corner is refined with ``cv2.cornerSubPix`` (tag corners are X-junctions with the
       gap squares; the window stays inside the tag's border) and kept only if the refined point
       is an X-junction (bright gaps, dark tag and square around it).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray

from dcc_fg.data import Observation
from dcc_fg.targets import TargetGeometry

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
UInt8Array = NDArray[np.uint8]

#: Kalibr corner index for each corner index OpenCV returns for an AprilTag.
OPENCV_TO_KALIBR_CORNER = (1, 0, 3, 2)
#: Black border width of Kalibr's AprilGrid tags, in bit cells.
KALIBR_BORDER_BITS = 2

_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 40, 0.01)


def to_gray8(image: NDArray[np.generic]) -> UInt8Array:
    """Convert an image to 8-bit grey.

    Args:
        image: (H, W), (H, W, 1), (H, W, 3) BGR or (H, W, 4) BGRA; uint8, uint16 or float.
            uint16 and float images are stretched linearly between their 0.5 and 99.5
            percentiles (16-bit cameras rarely use the full range).

    Returns:
        (H, W) uint8 image.
    """
    img = np.asarray(image)
    if img.dtype not in (np.uint8, np.uint16, np.float32):
        img = img.astype(np.float32)
    if img.ndim == 3:
        if img.shape[2] == 1:
            img = img[:, :, 0]
        elif img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        elif img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
        else:
            raise ValueError(f"image with {img.shape[2]} channels is not supported (1, 3 or 4)")
    elif img.ndim != 2:
        raise ValueError(f"expected an (H, W) or (H, W, C) image, got shape {img.shape}")
    if img.dtype == np.uint8:
        return np.ascontiguousarray(img)
    if img.dtype == np.uint16:
        cdf = np.cumsum(np.bincount(img.ravel(), minlength=65536)) / img.size
        lo, hi = int(np.searchsorted(cdf, 0.005)), int(np.searchsorted(cdf, 0.995))
        levels = np.arange(65536, dtype=np.float64)
        lut = np.clip((levels - lo) * (255.0 / max(hi - lo, 1)), 0.0, 255.0).astype(np.uint8)
        return lut[img]
    f = img.astype(np.float64)
    lo_f, hi_f = (float(x) for x in np.percentile(f, [0.5, 99.5]))
    scale = 255.0 / (hi_f - lo_f) if hi_f > lo_f else 1.0
    return np.clip((f - lo_f) * scale, 0.0, 255.0).astype(np.uint8)


# --------------------------------------------------------------------------------------------
# Chessboard
# --------------------------------------------------------------------------------------------


def checkerboard_is_symmetric(cols: int, rows: int) -> bool:
    """True if a board with ``cols`` x ``rows`` inner corners looks the same turned by 180 degrees.

    Square ``(i, j)`` maps to ``(cols - i, rows - j)`` under the rotation; its colour (parity of
    ``i + j``) is kept iff ``cols + rows`` is even.
    """
    return (cols + rows) % 2 == 0


def _square_means(gray: UInt8Array, centres: FloatArray, side: float) -> FloatArray:
    """Mean grey level of a small patch (half width 0.15 of the square ``side``, at least 1 px; clipped
    to the image) around each square centre (..., 2) px; NaN where the patch is empty."""
    half = max(1, int(0.15 * side))
    h, w = gray.shape
    out = np.full(centres.shape[:-1], np.nan)
    for idx in np.ndindex(*centres.shape[:-1]):
        u, v = np.round(centres[idx]).astype(int)
        patch = gray[max(0, v - half) : min(h, v + half + 1), max(0, u - half) : min(w, u + half + 1)]
        if patch.size:
            out[idx] = float(patch.mean())
    return out


def _extend(a: FloatArray, axis: int) -> FloatArray:
    """``a`` with one more entry before and after along ``axis``: quadratic extrapolation from the
    three outermost entries (follows the perspective foreshortening and the lens curvature over one
    square), linear when there are only two."""
    a = np.moveaxis(a, axis, 0)
    if a.shape[0] >= 3:
        lo, hi = 3 * a[0] - 3 * a[1] + a[2], 3 * a[-1] - 3 * a[-2] + a[-3]
    else:
        lo, hi = 2 * a[0] - a[1], 2 * a[-1] - a[-2]
    return np.moveaxis(np.concatenate([lo[None], a, hi[None]]), 0, axis)


def _board_squares(gray: UInt8Array, grid: FloatArray) -> FloatArray:
    """(rows + 1, cols + 1) mean grey levels of the squares of a corner grid (rows, cols, 2) px: square
    (r, c) of the result lies between extended corners (r - 1, c - 1) and (r, c), so ``[1:-1, 1:-1]``
    are the squares inside the grid (sampled at the mean of their four corners) and the border is the
    ring of squares one square beyond it (the grid extended by :func:`_extend`); NaN for a ring square
    whose centre is outside the image. Square (r, c) has parity ``r + c`` as its inner index does."""
    if grid.shape[0] < 2 or grid.shape[1] < 2:  # a single row or column: no square inside the grid
        return np.full((grid.shape[0] + 1, grid.shape[1] + 1), np.nan)
    ext = _extend(_extend(grid, 0), 1)
    centres = 0.25 * (ext[:-1, :-1] + ext[1:, :-1] + ext[:-1, 1:] + ext[1:, 1:])
    side = float(np.median(np.linalg.norm(grid[:, 1:] - grid[:, :-1], axis=2)))
    vals = _square_means(gray, centres, side)
    h, w = gray.shape
    u, v = np.round(centres[..., 0]).astype(int), np.round(centres[..., 1]).astype(int)
    outside = (u < 0) | (u >= w) | (v < 0) | (v >= h)
    outside[1:-1, 1:-1] = False  # the squares inside the grid are sampled as they are
    vals[outside] = np.nan
    return vals


def _parity(shape: tuple[int, ...]) -> NDArray[np.bool_]:
    """True where ``row + col`` is even."""
    rr, cc = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    return (rr + cc) % 2 == 0


def _square_parity_dark(squares: FloatArray) -> bool:
    """True if the squares with even ``col + row`` inside the corner grid are the darker ones
    (``squares``: :func:`_board_squares`)."""
    inner = squares[1:-1, 1:-1]
    even = _parity(inner.shape)
    return bool(np.nanmean(inner[even]) < np.nanmean(inner[~even]))


#: A side of the ring of border squares (one square beyond the corner grid) must match the board's
#: colour pattern on at least this fraction of its squares inside the image (see _ring_matches).
RING_MATCH_MIN = 0.75


def _ring_matches(squares: FloatArray) -> bool:
    """Whether the corner grid is the board's inner-corner grid and not one shifted by a row or column
    onto the board's edge (which OpenCV returns when the outermost corner row lies outside the image:
    the L-shaped corners between the last squares and the white margin then stand in for it, and
    every id is off by one row). ``squares``: :func:`_board_squares` of the grid.

    A chessboard with C x R inner corners has (C + 1) x (R + 1) squares, so one square beyond the grid
    on every side there is a ring of squares that continue the colour pattern. Every ring square
    inside the image is classified dark (below 30 % of the way from the dark to the light mean of the
    squares inside the grid) or light (above 70 %; a sample in between straddles a square's edge and
    is not used), and each side with at least two classified squares must match the pattern on at
    least ``RING_MATCH_MIN`` of them; beyond a shifted grid's edge lies the uniform margin, which
    matches on about half."""
    even = _parity(squares.shape)
    inner, inner_even = squares[1:-1, 1:-1], even[1:-1, 1:-1]
    if inner.size == 0 or not np.isfinite(inner).any():
        return True  # no square inside the grid to compare with (a single row or column)
    m_even, m_odd = np.nanmean(inner[inner_even]), np.nanmean(inner[~inner_even])
    if not (np.isfinite(m_even) and np.isfinite(m_odd)):
        return True  # a single square inside the grid: no contrast to compare with
    frac = (squares - m_even) / (m_odd - m_even)  # 0: the even squares' shade, 1: the odd squares'
    classified = (frac < 0.3) | (frac > 0.7)
    matches = (frac < 0.5) == even
    for ring in (np.s_[0, :], np.s_[-1, :], np.s_[:, 0], np.s_[:, -1]):
        seen = classified[ring]
        if seen.sum() >= 2 and matches[ring][seen].mean() < RING_MATCH_MIN:
            return False
    return True


def _refine_checkerboard(gray: UInt8Array, corners: NDArray[np.float32], target: TargetGeometry) -> NDArray[np.float32]:
    """``cv2.cornerSubPix`` on checkerboard corners (N, 1, 2), half window 0.2 of the median square
    side in pixels (2 to 11)."""
    c = corners.reshape(target.rows, target.cols, 2)
    side = float(np.median(np.linalg.norm(np.diff(c, axis=1), axis=2)))
    win = int(min(11, max(2, round(0.2 * side))))
    return cv2.cornerSubPix(gray, corners, (win, win), (-1, -1), _SUBPIX_CRITERIA)


#: A checkerboard corner farther than this fraction of the local square side from where its grid
#: neighbours put it is not on its X-junction (see :func:`_off_grid_corners`).
OFF_GRID_LIMIT = 0.15
#: Neighbours within this many squares (Chebyshev distance) predict a corner.
OFF_GRID_REACH = 2


def _grid_error(grid: FloatArray, bad: NDArray[np.bool_], r: int, c: int) -> float:
    """Distance (px) of corner (r, c) of ``grid`` (rows, cols, 2) from where a homography board ->
    image fitted to its neighbours within ``OFF_GRID_REACH`` squares (corners in ``bad`` and itself
    left out) puts it; 0 when fewer than 6 neighbours are left."""
    R, C = grid.shape[:2]
    r0, r1 = max(0, r - OFF_GRID_REACH), min(R, r + OFF_GRID_REACH + 1)
    c0, c1 = max(0, c - OFF_GRID_REACH), min(C, c + OFF_GRID_REACH + 1)
    use = ~bad[r0:r1, c0:c1]
    use[r - r0, c - c0] = False
    if use.sum() < 6:
        return 0.0
    rr, cc = np.meshgrid(np.arange(r0, r1), np.arange(c0, c1), indexing="ij")
    board = np.stack([cc, rr], axis=-1).astype(np.float64)
    H, _ = cv2.findHomography(board[use], grid[r0:r1, c0:c1][use], 0)
    if H is None:
        return 0.0
    q = H @ np.array([c, r, 1.0])
    return float(np.linalg.norm(q[:2] / q[2] - grid[r, c]))


def _off_grid_corners(grid: FloatArray) -> NDArray[np.bool_]:
    """(rows, cols) mask of refined checkerboard corners (``grid`` (rows, cols, 2) pixels) that sit
    off their X-junction: their neighbours put them (:func:`_grid_error`) farther than
    ``OFF_GRID_LIMIT`` times the median square side. The worst such corner is flagged and the test
    repeated, so two neighbouring bad corners do not hide each other; then a flagged corner that
    its unflagged neighbours put within the limit is taken back (a good corner next to bad ones can
    be the worst while they are still in the fit). Over four squares a lens's distortion bends the
    grid by a few hundredths of a square; a corner OpenCV placed inside a square (7 px off on 12 px
    squares of a small board tilted 36 deg, rendered: the planning study's member 2) is far beyond
    the limit."""
    R, C = grid.shape[:2]
    steps = np.concatenate(
        [np.linalg.norm(np.diff(grid, axis=1), axis=2).ravel(), np.linalg.norm(np.diff(grid, axis=0), axis=2).ravel()]
    )
    bad = np.zeros((R, C), dtype=bool)
    if steps.size == 0 or float(np.median(steps)) <= 0.0:
        return bad
    limit = OFF_GRID_LIMIT * float(np.median(steps))
    # Fast path: a corner moved by d changes a second difference through it by at least d, and smooth
    # grids (perspective, distortion) have small ones; when all are below half the limit, none is off.
    d2 = [np.linalg.norm(np.diff(grid, n=2, axis=ax), axis=2) for ax in (0, 1) if grid.shape[ax] >= 3]
    if d2 and max(float(x.max()) for x in d2) < 0.5 * limit:
        return bad
    for _ in range(R * C):
        err = np.array([[0.0 if bad[r, c] else _grid_error(grid, bad, r, c) for c in range(C)] for r in range(R)])
        if err.max() <= limit:
            break
        bad[np.unravel_index(int(np.argmax(err)), err.shape)] = True
    changed = True
    while changed:
        changed = False
        for r, c in zip(*np.nonzero(bad), strict=True):
            if _grid_error(grid, bad, int(r), int(c)) <= limit:
                bad[r, c] = False
                changed = True
    return bad


def detect_checkerboard(image: NDArray[np.generic], target: TargetGeometry) -> Observation:
    """Detect all inner corners of a chessboard.

    Args:
        image: the image (any type :func:`to_gray8` accepts).
        target: a ``checkerboard`` target; ``target.cols`` x ``target.rows`` inner corners.

    Returns:
        The ``cols * rows`` corners (id = row * cols + col, pixels in the distorted image) with
        corner 0 next to the black board square (see the module docstring), less any corner that
        sits off its X-junction (:func:`_off_grid_corners`), or an empty observation if the board is
        not found completely.
    """
    if target.target_type != "checkerboard":
        raise ValueError(f"detect_checkerboard needs a checkerboard target, got '{target.target_type}'")
    gray = to_gray8(image)
    size = (target.cols, target.rows)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
    ok, corners = cv2.findChessboardCorners(gray, size, flags=flags)
    if ok:
        corners = _refine_checkerboard(gray, corners, target)
    else:  # slower, more robust to blur and strong perspective
        ok, corners = cv2.findChessboardCornersSB(gray, size, flags=cv2.CALIB_CB_ACCURACY)
        if not ok:
            return Observation(np.zeros(0, dtype=np.int64), np.zeros((0, 2)))
        # refined like the first detector's: its own corners carry a per-image bias of up to a few
        # hundredths of a pixel (0.045 px RMS of the per-image mean error on 10-13 px squares of a
        # rendered fisheye image, 0.008 px after cornerSubPix), which a calibration absorbs
        corners = _refine_checkerboard(gray, corners.astype(np.float32), target)
    grid = corners.reshape(target.rows, target.cols, 2).astype(np.float64)
    # Handedness: seen from the front, the column direction turns clockwise (image v down) into
    # the row direction, i.e. the target z axis points into the board.  (OpenCV's detectors
    # already order corners this way; enforcing it rules out a mirrored order before the colour
    # check, which only distinguishes the two rotations.)
    d_col = grid[:-1, 1:] - grid[:-1, :-1]
    d_row = grid[1:, :-1] - grid[:-1, :-1]
    if np.mean(d_col[..., 0] * d_row[..., 1] - d_col[..., 1] * d_row[..., 0]) < 0:
        grid = grid[::-1]
    squares = _board_squares(gray, grid)
    if not _ring_matches(squares):
        log.debug("checkerboard corners shifted onto the board's edge (outermost corners outside the image): dropped")
        return Observation(np.zeros(0, dtype=np.int64), np.zeros((0, 2)))
    if checkerboard_is_symmetric(target.cols, target.rows):
        log.warning(
            "checkerboard %dx%d is 180-degree symmetric (colours included): its corner ids are only "
            "defined up to that rotation; use a board with one odd and one even inner-corner count",
            target.cols,
            target.rows,
        )
    elif not _square_parity_dark(squares):
        # Even-parity squares are white: corner 0's outer diagonal square (parity of (-1, -1),
        # i.e. even) is white, so the opposite corner is the canonical corner 0.
        grid = grid[::-1, ::-1]
    off = _off_grid_corners(grid).ravel()
    if off.any():
        log.debug("checkerboard: %d corner(s) off their X-junction dropped", int(off.sum()))
    ids = np.arange(target.rows * target.cols, dtype=np.int64)
    return Observation(ids[~off], grid.reshape(-1, 2)[~off])


# --------------------------------------------------------------------------------------------
# AprilGrid
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class AprilTag:
    """One detected tag.

    Attributes:
        tag_id: tag36h11 id.
        corners: (4, 2) pixels of the tag's outer black-border corners in Kalibr's order
            (0 bottom-left, 1 bottom-right, 2 top-right, 3 top-left, in the target frame).
    """

    tag_id: int
    corners: FloatArray


@lru_cache(maxsize=4)
def _aruco_detector(border_bits: int) -> cv2.aruco.ArucoDetector:
    params = cv2.aruco.DetectorParameters()
    params.markerBorderBits = border_bits
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
    # A few more threshold windows than the default: small, blurred tags in fisheye images.
    params.adaptiveThreshWinSizeMin = 3
    params.adaptiveThreshWinSizeMax = 33
    params.adaptiveThreshWinSizeStep = 10
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    return cv2.aruco.ArucoDetector(dictionary, params)


def _run_aruco(gray: UInt8Array, border_bits: int) -> tuple[list[AprilTag], list[FloatArray]]:
    """OpenCV's detector: decoded tags (Kalibr corner order) and undecoded quads (4, 2), any order."""
    corners, ids, rejected = _aruco_detector(border_bits).detectMarkers(gray)
    quads = [np.asarray(q, dtype=np.float64).reshape(4, 2) for q in rejected]
    if ids is None:
        return [], quads
    out = []
    for quad, tag_id in zip(corners, ids.ravel(), strict=True):
        q = quad.reshape(4, 2).astype(np.float64)
        kalibr = np.empty((4, 2))
        for k_cv, k_kalibr in enumerate(OPENCV_TO_KALIBR_CORNER):
            kalibr[k_kalibr] = q[k_cv]
        out.append(AprilTag(int(tag_id), kalibr))
    return out, quads


def detect_apriltags(image: NDArray[np.generic], border_bits: int = KALIBR_BORDER_BITS) -> list[AprilTag]:
    """All tag36h11 tags OpenCV's ArUco detector decodes (no grid logic, no sub-pixel refinement).

    Args:
        image: the image (any type :func:`to_gray8` accepts).
        border_bits: black border width in bit cells (2 for Kalibr's AprilGrid).

    Returns:
        Tags in detection order, corners in Kalibr's order at OpenCV's contour corners (integer
        pixels, up to ~0.1 tag side inside the true corner); an id may appear more than once
        (e.g. two identical boards).
    """
    return _run_aruco(to_gray8(image), border_bits)[0]


@lru_cache(maxsize=1)
def _tag_codes() -> NDArray[np.bool_]:
    """(587, 6, 6) tag36h11 code bits (True = white) in the dictionary's canonical orientation."""
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    n = d.bytesList.shape[0]
    return np.stack([d.getBitsFromByteList(d.bytesList[i : i + 1], d.markerSize) for i in range(n)]).astype(bool)


def _canonical_corners(cells: int) -> NDArray[np.float32]:
    """Where Kalibr corners 0..3 sit in the dictionary's canonical marker image (x right, y down).

    Kalibr corner 0 is the canonical top-right, 1 the top-left, 2 the bottom-left and 3 the
    bottom-right corner: on real detections every decoded tag matches its code with zero bit
    errors in this arrangement and in no other.
    """
    return np.array([[cells, 0.0], [0.0, 0.0], [0.0, cells], [cells, cells]], dtype=np.float32)


@lru_cache(maxsize=4)
def _sample_pattern(cells: int) -> FloatArray:
    """(cells * cells * 9, 2) canonical sample points: 3x3 per cell over its central half."""
    offs = np.array([-0.25, 0.0, 0.25])
    cy, cx = np.meshgrid(np.arange(cells) + 0.5, np.arange(cells) + 0.5, indexing="ij")
    oy, ox = np.meshgrid(offs, offs, indexing="ij")
    xs = (cx[:, :, None] + ox.ravel()[None, None, :]).ravel()
    ys = (cy[:, :, None] + oy.ravel()[None, None, :]).ravel()
    return np.stack([xs, ys], axis=1)


def _cell_means(gray: UInt8Array, corners: FloatArray, cells: int) -> FloatArray | None:
    """Mean intensity of the ``cells`` x ``cells`` bit cells of a tag, canonical orientation.

    ``corners`` (4, 2) are the outer corners in Kalibr order.  None if the tag leaves the image.
    """
    H = cv2.getPerspectiveTransform(_canonical_corners(cells), corners.astype(np.float32))
    pts = cv2.perspectiveTransform(_sample_pattern(cells)[None], H)[0]
    h, w = gray.shape
    if pts[:, 0].min() < 0 or pts[:, 1].min() < 0 or pts[:, 0].max() > w - 1 or pts[:, 1].max() > h - 1:
        return None
    mapx = pts[:, 0].astype(np.float32).reshape(1, -1)
    mapy = pts[:, 1].astype(np.float32).reshape(1, -1)
    vals = cv2.remap(gray, mapx, mapy, cv2.INTER_LINEAR).astype(np.float64)
    return vals.reshape(cells, cells, 9).mean(axis=2)


def _threshold_cells(vals: FloatArray, border_bits: int) -> NDArray[np.bool_] | None:
    """Binarize (cells, cells) cell means (True = white); None if it does not look like a tag.

    The threshold is halfway between the black border level (median of the border cells) and
    the bright code cells (90th percentile of the code cells).  None if the contrast is below 15
    grey levels or more than 10 % of the border cells read white.  The border is symmetric, so
    the result does not depend on the orientation the cells were sampled in.
    """
    cells = vals.shape[0]
    inner = np.sort(vals[border_bits : cells - border_bits, border_bits : cells - border_bits], axis=None)
    border_mask = np.ones((cells, cells), dtype=bool)
    border_mask[border_bits : cells - border_bits, border_bits : cells - border_bits] = False
    border = np.sort(vals[border_mask])
    black = float(border[border.size // 2])
    white = float(inner[int(0.9 * (inner.size - 1))])
    if white - black < 15.0:
        return None
    thr = 0.5 * (black + white)
    if np.count_nonzero(border > thr) > 0.1 * border.size:
        return None
    return vals > thr


def _read_bits(gray: UInt8Array, corners: FloatArray, border_bits: int) -> NDArray[np.bool_] | None:
    """The 6x6 code bits (True = white) of the tag with ``corners`` (Kalibr order), or None.

    None if the tag leaves the image or does not look like a tag (:func:`_threshold_cells`).
    """
    n = _tag_codes().shape[1]
    vals = _cell_means(gray, corners, n + 2 * border_bits)
    cells = None if vals is None else _threshold_cells(vals, border_bits)
    return None if cells is None else cells[border_bits : border_bits + n, border_bits : border_bits + n]


@lru_cache(maxsize=4)
def _orderings(cells: int) -> tuple[tuple[NDArray[np.intp], NDArray[np.intp]], ...]:
    """The 8 corner orders of a quad (4 rotations x 2 windings) and what they do to its cells.

    For each order ``idx`` (a permutation of 0..3) returns ``(idx, cell_map)``: sampling a tag
    with corners ``quad[idx]`` gives the flat (row-major) cell array ``v[cell_map]`` where ``v``
    was sampled with ``quad`` itself.  (The sampling homography changes by the map of the
    canonical square sending canonical corner ``j`` to canonical corner ``idx[j]``.)
    """
    canon = _canonical_corners(cells)
    cy, cx = np.meshgrid(np.arange(cells) + 0.5, np.arange(cells) + 0.5, indexing="ij")
    centres = np.stack([cx.ravel(), cy.ravel()], axis=1)[None].astype(np.float64)
    out = []
    for base in (np.arange(4), np.arange(4)[::-1]):
        for shift in range(4):
            idx = np.roll(base, shift)
            M = cv2.getPerspectiveTransform(canon, canon[idx])
            mapped = cv2.perspectiveTransform(centres, M)[0]
            col = np.clip(np.floor(mapped[:, 0]), 0, cells - 1).astype(np.intp)
            row = np.clip(np.floor(mapped[:, 1]), 0, cells - 1).astype(np.intp)
            out.append((idx, row * cells + col))
    return tuple(out)


def _decode_quad(
    gray: UInt8Array, quad: FloatArray, border_bits: int, n_ids: int
) -> tuple[int, NDArray[np.intp], int] | None:
    """Identify a quad whose corner order is unknown among tag ids ``0 .. n_ids - 1``.

    Tries the 8 corner orders (4 rotations, 2 windings).  Returns (tag id, corner order ``idx``
    such that ``quad[idx]`` is in Kalibr order, bit errors) of the best match, or None if the
    quad does not read as a tag.
    """
    codes = _tag_codes()[:n_ids]
    n = codes.shape[1]
    cells = n + 2 * border_bits
    vals = _cell_means(gray, quad, cells)
    binary = None if vals is None else _threshold_cells(vals, border_bits)
    if binary is None:
        return None
    flat = binary.ravel()
    codes_flat = codes.reshape(n_ids, -1)
    best: tuple[int, NDArray[np.intp], int] | None = None
    for idx, cell_map in _orderings(cells):
        bits = flat[cell_map].reshape(cells, cells)[border_bits : border_bits + n, border_bits : border_bits + n]
        errors = np.count_nonzero(codes_flat != bits.reshape(1, -1), axis=1)
        k = int(np.argmin(errors))
        if best is None or errors[k] < best[2]:
            best = (k, idx, int(errors[k]))
    return best


def _tag_side(corners: FloatArray) -> float:
    """Mean edge length of a quad, pixels."""
    return float(np.mean(np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1)))


def _tag_width(corners: FloatArray) -> float:
    """Narrowest extent of a quad (area / longest edge), pixels: the side of a square tag seen
    head-on, much less than :func:`_tag_side` for a tag seen at a grazing angle."""
    x, y = corners[:, 0], corners[:, 1]
    area = 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))
    longest = float(np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1).max())
    return area / longest if longest > 0 else 0.0


def _subpix_window(side: float, tag_spacing: float) -> int:
    """Half window for cornerSubPix, pixels.

    The tag's black border is 0.2 side wide and the gap square ``tag_spacing`` side: a window of
    3/4 of the narrower one sees only the four quadrants of the X-junction.
    """
    return min(12, max(2, round(0.75 * min(0.2, tag_spacing) * side)))


def _subpix(gray: UInt8Array, corners: FloatArray, win: int) -> FloatArray | None:
    """cv2.cornerSubPix with half window ``win``; None if a window would leave the image.

    cornerSubPix returns the start point unchanged when the corner lies farther than the window
    from it; such corners are retried with growing windows up to ``2 win`` until one moves, then
    with ``win`` again from there (a large window is biased by the tag's code bits next to the
    junction), so a start up to ~2 ``win`` off still converges.
    """
    h, w = gray.shape

    def margin(pts: FloatArray) -> float:
        return float(min(pts[:, 0].min(), pts[:, 1].min(), w - 1 - pts[:, 0].max(), h - 1 - pts[:, 1].max()))

    if margin(corners) < win:
        return None

    def run(pts: FloatArray, half: int) -> FloatArray:
        p = pts.astype(np.float32).reshape(-1, 1, 2)
        return cv2.cornerSubPix(gray, p, (half, half), (-1, -1), _SUBPIX_CRITERIA).reshape(-1, 2).astype(np.float64)

    out = run(corners, win)
    for i in np.flatnonzero(np.linalg.norm(out - corners, axis=1) < 1e-3):
        for half in range(win + 1, min(2 * win, int(margin(corners[i : i + 1]))) + 1):
            moved = run(corners[i : i + 1], half)
            if np.linalg.norm(moved - corners[i]) >= 1e-3:
                out[i] = run(moved, win)[0]
                break
    if margin(out) < win:
        return None
    return out


def _sample(gray: UInt8Array, pts: FloatArray) -> FloatArray:
    """Bilinear grey values at (N, 2) pixel positions."""
    mapx = pts[:, 0].astype(np.float32).reshape(1, -1)
    mapy = pts[:, 1].astype(np.float32).reshape(1, -1)
    return cv2.remap(gray, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)[0]


def _x_junctions(gray: UInt8Array, corners: FloatArray, radius: float) -> NDArray[np.bool_]:
    """Which corners of a tag (4, 2) sit on an X-junction of the AprilGrid.

    At a true tag corner the tag (inwards) and the gap square (outwards) are dark and the two
    gaps between them, along the extensions of the tag's edges, are bright.  Sampled at
    ``radius`` pixels from the corner; a corner passes if both bright samples exceed both dark
    ones by 10 grey levels.  Catches corners refined onto a tag edge or a square's far corner.
    """
    inward = np.roll(corners, -1, axis=0) + np.roll(corners, 1, axis=0) - 2.0 * corners
    across = np.roll(corners, -1, axis=0) - np.roll(corners, 1, axis=0)
    n_in = np.linalg.norm(inward, axis=1, keepdims=True)
    n_across = np.linalg.norm(across, axis=1, keepdims=True)
    if (n_in < 1e-9).any() or (n_across < 1e-9).any():
        return np.zeros(4, dtype=bool)
    inward, across = radius * inward / n_in, radius * across / n_across
    v = _sample(gray, np.concatenate([corners + inward, corners - inward, corners + across, corners - across]))
    v = v.reshape(4, 4)  # rows: +in, -in, +across, -across; columns: corners
    return np.minimum(v[2], v[3]) > np.maximum(v[0], v[1]) + 10.0


def _refine_tag(
    gray: UInt8Array, corners: FloatArray, tag_spacing: float, coarse: bool = False
) -> tuple[FloatArray, NDArray[np.bool_]] | None:
    """Sub-pixel tag corners (X-junctions of the grid) and which of them are trustworthy.

    ``coarse`` (for predicted corners, a few pixels off) first runs a pass with a window of a
    quarter tag width, then the fine pass.  A refined corner that is not an X-junction (e.g.
    OpenCV's quad of a tag merged with a gap square ends at the square's far corner) is searched
    for again from starts moved along the diagonal towards the tag centre; if that fails too the
    corner is marked untrustworthy (False) but keeps its position, good enough to read the tag's
    bits.  None if fewer than 3 corners are found, a corner runs away or the tag is too small.
    """
    side = _tag_width(corners)
    if side < 8.0:
        return None
    win = _subpix_window(side, tag_spacing)
    start = corners
    if coarse:
        first = _subpix(gray, corners, min(16, max(3, round(0.25 * side))))
        if first is None:
            return None
        start = first
    refined = _subpix(gray, start, win)
    if refined is None:
        return None
    radius = max(1.5, 0.5 * min(0.2, tag_spacing) * side)
    good = _x_junctions(gray, refined, radius)
    if not good.all():
        centre = corners.mean(axis=0)
        for t in (0.05, 0.1, 0.15, 0.2, 0.25):
            moved = _subpix(gray, start + t * (centre - start), win)
            if moved is None:
                break
            fixed = ~good & _x_junctions(gray, moved, radius)
            refined[fixed] = moved[fixed]
            good |= fixed
            if good.all():
                break
    if np.count_nonzero(good) < 3:
        return None
    # OpenCV's contour corners sit up to ~0.1 side inside the tag; much farther means lost.
    if np.linalg.norm(refined - corners, axis=1).max() > max(0.3 * side, win + 1.0):
        return None
    return refined, good


def _grid_cell(target: TargetGeometry, tag_id: int) -> tuple[int, int]:
    return tag_id // target.cols, tag_id % target.cols


def _neighbours(target: TargetGeometry, tags: dict[int, FloatArray], tag_id: int, dist: int) -> list[int]:
    """Tags in ``tags`` at Chebyshev grid distance exactly ``dist`` from ``tag_id``."""
    r0, c0 = _grid_cell(target, tag_id)
    out = []
    for t in tags:
        r, c = _grid_cell(target, t)
        if max(abs(r - r0), abs(c - c0)) == dist:
            out.append(t)
    return out


@lru_cache(maxsize=16)
def _target_xy(target: TargetGeometry) -> FloatArray:
    """(M, 2) target-plane corner coordinates, metres (cached: ``points`` is recomputed on access)."""
    return target.points[:, :2].copy()


def _tag_homography(target: TargetGeometry, tags: dict[int, FloatArray], use: list[int]) -> FloatArray | None:
    """Homography target plane (x, y metres) -> image pixels from the corners of tags ``use``."""
    pts = _target_xy(target)
    src = np.concatenate([pts[4 * t : 4 * t + 4] for t in use])
    dst = np.concatenate([tags[t] for t in use])
    H, _ = cv2.findHomography(src, dst, 0)
    return H


def _project(target: TargetGeometry, H: FloatArray, tag_id: int) -> FloatArray:
    pts = _target_xy(target)[4 * tag_id : 4 * tag_id + 4]
    return cv2.perspectiveTransform(pts[None], H)[0]


def _consistent(target: TargetGeometry, tags: dict[int, FloatArray]) -> dict[int, FloatArray]:
    """Drop tags that sit where their grid neighbours say they cannot be.

    Each tag's own homography predicts its neighbours at grid distance 1; a neighbour agrees if
    its centre is within 0.5 tag side of the prediction.  A tag that no neighbour agrees with but
    at least one disagrees with is dropped (a wrong decode or a second board with the same ids).
    """
    agree = {t: 0 for t in tags}
    disagree = {t: 0 for t in tags}
    for t in tags:
        H = _tag_homography(target, tags, [t])
        if H is None:
            continue
        for n in _neighbours(target, tags, t, 1):
            ok = np.linalg.norm(_project(target, H, n).mean(axis=0) - tags[n].mean(axis=0)) < 0.5 * _tag_side(tags[n])
            (agree if ok else disagree)[n] += 1
    bad = [t for t in tags if agree[t] == 0 and disagree[t] > 0]
    for t in bad:
        log.debug("dropping tag id %d: inconsistent with its grid neighbours", t)
    return {t: c for t, c in tags.items() if t not in bad}


def _predict_tag(target: TargetGeometry, tags: dict[int, FloatArray], tag_id: int) -> FloatArray | None:
    """Corners (Kalibr order) of ``tag_id`` from a homography fitted to its nearest detected tags.

    Uses the detected tags at grid distance 1 if there are at least two, else those at distance
    <= 2 (at least one at distance 1); lens distortion makes a more distant fit unreliable.
    """
    near = _neighbours(target, tags, tag_id, 1)
    use = near if len(near) >= 2 else near + _neighbours(target, tags, tag_id, 2)
    if not near or len(use) < 2:
        return None
    H = _tag_homography(target, tags, use)
    return None if H is None else _project(target, H, tag_id)


def _match_quad(guess: FloatArray, quads: list[FloatArray]) -> FloatArray | None:
    """The undecoded quad that matches ``guess``, re-ordered like it; None if none is close.

    A quad matches if, in its best cyclic order (either winding), every corner lies within 0.3
    tag side of the guessed one.
    """
    side = _tag_side(guess)
    centre = guess.mean(axis=0)
    best, best_err = None, 0.3 * side
    for q in quads:
        if np.linalg.norm(q.mean(axis=0) - centre) > 0.3 * side:
            continue
        for cand in (q, q[::-1]):
            for shift in range(4):
                r = np.roll(cand, shift, axis=0)
                err = float(np.linalg.norm(r - guess, axis=1).max())
                if err < best_err:
                    best, best_err = r, err
    return best


def _complete_grid(
    gray: UInt8Array,
    tags: dict[int, FloatArray],
    good: dict[int, NDArray[np.bool_]],
    quads: list[FloatArray],
    target: TargetGeometry,
    border_bits: int,
    max_bit_errors: int,
) -> None:
    """Add tags not found yet (to ``tags`` and ``good``, in place), verified by their bits.

    A tag is predicted from found neighbours, snapped to a matching undecoded quad if there is
    one (lens distortion makes predictions a few pixels off), refined, and accepted if its bits
    read as the expected id within ``max_bit_errors``.  Runs until no tag is added; each added tag
    improves the predictions of its neighbours.
    """
    code = _tag_codes()
    n_tags = target.cols * target.rows
    failed: set[int] = set()
    while True:
        added = False
        for tag_id in range(n_tags):
            if tag_id in tags or tag_id in failed:
                continue
            guess = _predict_tag(target, tags, tag_id)
            if guess is None:
                continue
            failed.add(tag_id)
            snapped = _match_quad(guess, quads)
            for start, coarse in ((snapped, False), (guess, False), (guess, True)):
                if start is None:
                    continue
                result = _refine_tag(gray, start, target.tag_spacing, coarse)
                bits = None if result is None else _read_bits(gray, result[0], border_bits)
                if result is not None and bits is not None:
                    if np.count_nonzero(bits != code[tag_id]) <= max_bit_errors:
                        tags[tag_id], good[tag_id] = result
                        failed.discard(tag_id)
                        added = True
                        break
        if not added:
            return
        failed.clear()  # new neighbours: retry the failures with better predictions


def detect_aprilgrid(
    image: NDArray[np.generic],
    target: TargetGeometry,
    *,
    border_bits: int = KALIBR_BORDER_BITS,
    complete: bool = True,
    max_bit_errors: int = 5,
    min_tags: int = 1,
) -> Observation:
    """Detect a Kalibr AprilGrid; partial views give the visible corners.

    Args:
        image: the image (any type :func:`to_gray8` accepts).
        target: an ``aprilgrid`` target (tag ids ``0 .. cols * rows - 1``).
        border_bits: black border width of the tags in bit cells (Kalibr: 2).
        complete: look for tags OpenCV could not decode (see the module docstring).
        max_bit_errors: bit errors (of 36) allowed when re-reading a tag OpenCV decoded and for
            a tag at the position its grid neighbours predict; an undecoded quad anywhere else
            needs at most 2.
        min_tags: return an empty observation if fewer tags are found.

    Returns:
        Point ids ``4 * tag_id + corner`` (Kalibr corner order) sorted ascending, and the refined
        pixel coordinates of those corners in the distorted image.  A corner whose refinement
        does not land on an X-junction is left out (its tag's other corners are kept).
    """
    if target.target_type != "aprilgrid":
        raise ValueError(f"detect_aprilgrid needs an aprilgrid target, got '{target.target_type}'")
    gray = to_gray8(image)
    n_tags = target.cols * target.rows
    code = _tag_codes()
    found: dict[int, tuple[int, FloatArray, NDArray[np.bool_]]] = {}  # id -> (bit errors, corners, good)

    def offer(tag_id: int, corners: FloatArray, good: NDArray[np.bool_], errors: int) -> None:
        if tag_id not in found or errors < found[tag_id][0]:
            found[tag_id] = (errors, corners, good)

    # Candidates: OpenCV's decoded tags and undecoded quads, on the image and (if tags are still
    # missing) on a copy whose black regions are eroded by one pixel, which separates tags from
    # the gap squares they touch in blurred images.
    undecoded: list[FloatArray] = []
    variants = [gray, cv2.dilate(gray, np.ones((3, 3), np.uint8))] if complete else [gray]
    for img in variants:
        if len(found) == n_tags:
            break
        decoded, und = _run_aruco(img, border_bits)
        undecoded += und
        for tag in decoded:
            if not 0 <= tag.tag_id < n_tags:
                log.debug("dropping tag id %d: outside the %dx%d grid", tag.tag_id, target.cols, target.rows)
                continue
            result = _refine_tag(gray, tag.corners, target.tag_spacing)
            bits = None if result is None else _read_bits(gray, result[0], border_bits)
            if result is not None and bits is not None:
                errors = int(np.count_nonzero(bits != code[tag.tag_id]))
                if errors <= max_bit_errors:
                    offer(tag.tag_id, result[0], result[1], errors)
        if not complete:
            continue
        # Quads on tags already found need no decoding.
        known = np.array([c.mean(axis=0) for _, c, _ in found.values()]).reshape(-1, 2)
        radius = np.array([0.3 * _tag_side(c) for _, c, _ in found.values()])
        for quad in und:
            if known.size and (np.linalg.norm(known - quad.mean(axis=0), axis=1) < radius).any():
                continue
            result = _refine_tag(gray, quad, target.tag_spacing)
            hit = None if result is None else _decode_quad(gray, result[0], border_bits, n_tags)
            if result is not None and hit is not None and hit[2] <= min(2, max_bit_errors):
                tag_id, idx, errors = hit
                offer(tag_id, result[0][idx], result[1][idx], errors)
    tags = _consistent(target, {t: c for t, (_, c, _) in found.items()})
    good = {t: found[t][2] for t in tags}
    if complete and tags:
        _complete_grid(gray, tags, good, undecoded, target, border_bits, max_bit_errors)
    if len(tags) < min_tags:
        return Observation(np.zeros(0, dtype=np.int64), np.zeros((0, 2)))
    ids = [4 * t + k for t in sorted(tags) for k in range(4) if good[t][k]]
    pixels = [tags[t][k] for t in sorted(tags) for k in range(4) if good[t][k]]
    return Observation(np.array(ids, dtype=np.int64), np.array(pixels).reshape(-1, 2))


def detect_target(image: NDArray[np.generic], target: TargetGeometry) -> Observation:
    """Detect ``target`` (checkerboard or aprilgrid) in ``image`` with default options."""
    if target.target_type == "checkerboard":
        return detect_checkerboard(image, target)
    if target.target_type == "aprilgrid":
        return detect_aprilgrid(image, target)
    raise ValueError(f"target_type '{target.target_type}' is not supported (checkerboard, aprilgrid)")
