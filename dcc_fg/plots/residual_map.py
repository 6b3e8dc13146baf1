"""Where over the image the reprojection residuals are large: per-camera heat maps of binned residuals.

Each camera's image area (``resolution = (width, height)`` in pixels, ``u`` to the right, ``v`` down,
the top-left image corner at ``(0, 0)``) is cut into a grid of equal cells. Every corner of every
snapshot falls into the cell of its *detected* pixel position ``z`` and contributes its residual
``e = h(x) - z`` (pixels, as in :class:`dcc_fg.calibrate.CalibrationResult`). Per cell:

* ``count``: corners in the cell;
* ``rms``: RMS residual magnitude ``sqrt(mean(|e|^2))`` in pixels (``sqrt(2)`` times the RMS per axis
  of :func:`dcc_fg.calibrate.residual_stats` for isotropic noise);
* ``mean``: the mean residual vector ``(du, dv)`` in pixels (a systematic pattern, e.g. radially
  outward at the periphery, points at a distortion model that does not fit).

Cells with fewer than ``min_count`` corners are masked: an RMS of two corners is noise, not a finding.
The corner positions are not part of a calibration result; they come from the
:class:`dcc_fg.data.CalibrationDataset` the result was computed from (same snapshots, same corner order).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from matplotlib.axes import Axes
from matplotlib.collections import QuadMesh
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Patch, Rectangle
from numpy.typing import NDArray

from dcc_fg.calibrate import CalibrationResult
from dcc_fg.data import CalibrationDataset
from dcc_fg.plots.common import new_figure

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
CAMERAS = ("static", "dynamic")
CELLS_ACROSS = 8  # cells along the image width; rows follow the aspect ratio (752 x 480 -> 8 x 5)
MIN_COUNT = 5  # fewer corners than this in a cell: masked
EDGE_TOLERANCE_PX = 0.5  # corners this far outside the image area (pixel-centre conventions) go into the edge cells
ARROW_CELL_FRACTION = 0.45  # the largest mean residual vector is drawn this long, as a fraction of a cell width


@dataclass(frozen=True)
class ResidualGrid:
    """Residuals of one camera binned over its image (see the module docstring).

    Attributes:
        resolution: ``(width, height)`` of the image in pixels.
        u_edges: (nu + 1,) cell boundaries along u (pixels, left to right).
        v_edges: (nv + 1,) cell boundaries along v (pixels, top to bottom).
        count: (nv, nu) corners per cell (row = v, column = u).
        rms: (nv, nu) RMS residual magnitude per cell in pixels, NaN where masked.
        mean: (nv, nu, 2) mean residual vector ``(du, dv)`` per cell in pixels, NaN where masked.
        min_count: cells with fewer corners are masked.
        n_outside: corners beyond the image area (not binned).
        overall_rms: RMS residual magnitude over all binned corners (pixels, NaN without any).
    """

    resolution: tuple[int, int]
    u_edges: FloatArray
    v_edges: FloatArray
    count: IntArray
    rms: FloatArray
    mean: FloatArray
    min_count: int
    n_outside: int
    overall_rms: float

    @property
    def masked(self) -> NDArray[np.bool_]:
        """(nv, nu) True where a cell has fewer than ``min_count`` corners."""
        return self.count < self.min_count

    @property
    def cell_size(self) -> tuple[float, float]:
        """Cell width and height in pixels."""
        return float(self.u_edges[1] - self.u_edges[0]), float(self.v_edges[1] - self.v_edges[0])

    def worst_cell(self) -> tuple[int, int] | None:
        """``(row, column)`` of the unmasked cell with the largest RMS, or None when every cell is masked."""
        if np.all(self.masked):
            return None
        row, col = np.unravel_index(int(np.nanargmax(np.where(self.masked, -np.inf, self.rms))), self.rms.shape)
        return int(row), int(col)


def grid_shape(resolution: tuple[int, int], cells_across: int = CELLS_ACROSS) -> tuple[int, int]:
    """``(rows, columns)`` of near-square cells: ``cells_across`` columns, rows by the aspect ratio (>= 1)."""
    w, h = resolution
    if cells_across < 1 or w <= 0 or h <= 0:
        raise ValueError(
            f"grid_shape: need cells_across >= 1 and a positive resolution, got {cells_across}, {resolution}"
        )
    return max(1, int(round(cells_across * h / w))), int(cells_across)


def bin_residuals(
    pixels: FloatArray,
    residuals: FloatArray,
    resolution: tuple[int, int],
    cells_across: int = CELLS_ACROSS,
    min_count: int = MIN_COUNT,
) -> ResidualGrid:
    """Bin the residuals ``(N, 2)`` (pixels) of corners detected at ``pixels`` ``(N, 2)`` (``u, v`` in
    pixels) over an image of ``resolution = (width, height)``: see :class:`ResidualGrid`."""
    z = np.asarray(pixels, dtype=float).reshape(-1, 2)
    e = np.asarray(residuals, dtype=float).reshape(-1, 2)
    if z.shape != e.shape:
        raise ValueError(f"bin_residuals: {z.shape[0]} corner positions but {e.shape[0]} residuals")
    if not (np.all(np.isfinite(z)) and np.all(np.isfinite(e))):
        raise ValueError("bin_residuals: corner positions or residuals contain NaN or inf")
    if min_count < 1:
        raise ValueError(f"bin_residuals: min_count must be >= 1, got {min_count}")
    w, h = int(resolution[0]), int(resolution[1])
    nv, nu = grid_shape((w, h), cells_across)
    u_edges, v_edges = np.linspace(0.0, w, nu + 1), np.linspace(0.0, h, nv + 1)
    tol = EDGE_TOLERANCE_PX
    inside = (z[:, 0] >= -tol) & (z[:, 0] < w + tol) & (z[:, 1] >= -tol) & (z[:, 1] < h + tol)
    col = np.clip(np.floor(z[inside, 0] * nu / w).astype(np.int64), 0, nu - 1)
    row = np.clip(np.floor(z[inside, 1] * nv / h).astype(np.int64), 0, nv - 1)
    cell = row * nu + col
    ein = e[inside]
    count = np.bincount(cell, minlength=nv * nu).astype(np.int64)
    sq = np.bincount(cell, weights=np.sum(ein * ein, axis=1), minlength=nv * nu)
    su = np.bincount(cell, weights=ein[:, 0], minlength=nv * nu)
    sv = np.bincount(cell, weights=ein[:, 1], minlength=nv * nu)
    keep = count >= min_count
    n = np.where(keep, count, 1)
    rms = np.where(keep, np.sqrt(sq / n), np.nan)
    mean = np.stack([np.where(keep, su / n, np.nan), np.where(keep, sv / n, np.nan)], axis=-1)
    overall = float(np.sqrt(np.mean(np.sum(ein * ein, axis=1)))) if ein.shape[0] else float("nan")
    return ResidualGrid(
        resolution=(w, h),
        u_edges=u_edges,
        v_edges=v_edges,
        count=count.reshape(nv, nu),
        rms=rms.reshape(nv, nu),
        mean=mean.reshape(nv, nu, 2),
        min_count=int(min_count),
        n_outside=int(np.count_nonzero(~inside)),
        overall_rms=overall,
    )


def corner_residuals(result: CalibrationResult, data: CalibrationDataset, camera: str) -> tuple[FloatArray, FloatArray]:
    """All corners of ``camera`` (``static`` or ``dynamic``) over the snapshots: detected pixel positions
    ``z`` (N, 2) and residuals ``h(x) - z`` (N, 2), both in pixels.

    Raises ValueError when ``data`` is not the dataset of ``result`` (other snapshot or corner counts).
    """
    if camera not in CAMERAS:
        raise ValueError(f"camera must be one of {', '.join(CAMERAS)}, got '{camera}'")
    res = result.residuals_static if camera == "static" else result.residuals_dynamic
    if len(res) != len(data.snapshots):
        raise ValueError(
            f"residual map: the result has {len(res)} snapshots but the dataset {len(data.snapshots)} "
            "(pass the dataset the calibration was computed from)"
        )
    pixels = []
    for i, (snap, r) in enumerate(zip(data.snapshots, res, strict=True)):
        z = (snap.static if camera == "static" else snap.dynamic).pixels
        if z.shape[0] != r.shape[0]:
            raise ValueError(
                f"residual map: snapshot {i} has {z.shape[0]} {camera} corners in the dataset but {r.shape[0]} "
                "residuals in the result (pass the dataset the calibration was computed from)"
            )
        pixels.append(np.asarray(z, float).reshape(-1, 2))
    if not pixels:
        return np.zeros((0, 2)), np.zeros((0, 2))
    return np.concatenate(pixels), np.concatenate([np.asarray(r, float).reshape(-1, 2) for r in res])


def residual_grids(
    result: CalibrationResult,
    data: CalibrationDataset,
    cells_across: int = CELLS_ACROSS,
    min_count: int = MIN_COUNT,
) -> dict[str, ResidualGrid]:
    """:class:`ResidualGrid` of the static and of the dynamic camera (keys ``static``, ``dynamic``),
    over each camera's resolution from ``data``."""
    cams = {"static": data.static_camera, "dynamic": data.dynamic_camera}
    return {
        cam: bin_residuals(*corner_residuals(result, data, cam), cams[cam].resolution, cells_across, min_count)
        for cam in CAMERAS
    }


def image_region(grid: ResidualGrid, row: int, col: int) -> str:
    """Plain words for where the cell lies in the image: ``top-left`` ... ``centre`` ... ``bottom-right``
    (image thirds of the cell's centre)."""
    w, h = grid.resolution
    uc = 0.5 * (grid.u_edges[col] + grid.u_edges[col + 1])
    vc = 0.5 * (grid.v_edges[row] + grid.v_edges[row + 1])
    vert = ("top", "middle", "bottom")[min(2, int(3 * vc / h))]
    horiz = ("left", "centre", "right")[min(2, int(3 * uc / w))]
    if vert == "middle" and horiz == "centre":
        return "centre"
    if vert == "middle":
        return f"{horiz} edge"
    if horiz == "centre":
        return f"{vert} edge"
    return f"{vert}-{horiz} corner"


def residual_map_summary(grids: Mapping[str, ResidualGrid]) -> str:
    """One line per camera: the worst cell's RMS (px), its pixel range and image region, its corners,
    the ratio to the camera's overall RMS, the median cell and the masked cells."""
    lines = []
    for cam, g in grids.items():
        nv, nu = g.count.shape
        cw, ch = g.cell_size
        head = f"residual map, {cam} camera ({nu} x {nv} cells of {cw:.0f} x {ch:.0f} px, >= {g.min_count} corners):"
        worst = g.worst_cell()
        if worst is None:
            lines.append(f"{head} no cell has enough corners")
            continue
        r, c = worst
        ratio = g.rms[r, c] / g.overall_rms if g.overall_rms > 0 else float("nan")
        lines.append(
            f"{head} worst cell RMS |e| {g.rms[r, c]:.3g} px at u {g.u_edges[c]:.0f}-{g.u_edges[c + 1]:.0f}, "
            f"v {g.v_edges[r]:.0f}-{g.v_edges[r + 1]:.0f} px ({image_region(g, r, c)}, {g.count[r, c]} corners), "
            f"{ratio:.2g}x the camera's RMS |e| {g.overall_rms:.3g} px; median cell {np.nanmedian(g.rms):.3g} px; "
            f"{int(np.count_nonzero(g.masked))} of {nu * nv} cells masked"
            + (f"; {g.n_outside} corners outside the image" if g.n_outside else "")
        )
    return "\n".join(lines)


def draw_residual_map(ax: Axes, grid: ResidualGrid, norm: Normalize, arrow_px_per_px: float | None) -> QuadMesh:
    """Draw one camera's grid on ``ax`` in image coordinates (u right, v down, pixels): the cells coloured
    by RMS (masked cells left grey and hatched), each unmasked cell's RMS as text, the mean residual
    vectors as arrows from the cell centres (``arrow_px_per_px`` image pixels per pixel of residual;
    None: no arrows) and the worst cell outlined. Returns the colour mesh (for a colour bar)."""
    w, h = grid.resolution
    ax.set_facecolor("0.88")
    mesh = ax.pcolormesh(
        grid.u_edges, grid.v_edges, np.ma.masked_invalid(grid.rms), cmap="viridis", norm=norm, edgecolors="face"
    )
    masked = grid.masked
    for r, c in zip(*np.nonzero(masked), strict=True):
        ax.add_patch(
            Rectangle(
                (grid.u_edges[c], grid.v_edges[r]),
                grid.u_edges[c + 1] - grid.u_edges[c],
                grid.v_edges[r + 1] - grid.v_edges[r],
                fill=False,
                hatch="//",
                edgecolor="0.65",
                lw=0.0,
            )
        )
    uc = 0.5 * (grid.u_edges[:-1] + grid.u_edges[1:])
    vc = 0.5 * (grid.v_edges[:-1] + grid.v_edges[1:])
    cw, ch = grid.cell_size
    for r, c in zip(*np.nonzero(~masked), strict=True):
        light = norm(grid.rms[r, c]) < 0.55
        ax.text(
            uc[c],
            vc[r] - 0.3 * ch,
            f"{grid.rms[r, c]:.2g}",
            ha="center",
            va="center",
            fontsize=6,
            color="white" if light else "black",
        )
    if arrow_px_per_px is not None and np.any(~masked):
        U, V = np.meshgrid(uc, vc)
        ax.quiver(
            U[~masked],
            V[~masked],
            grid.mean[..., 0][~masked] * arrow_px_per_px,
            grid.mean[..., 1][~masked] * arrow_px_per_px,
            angles="xy",
            scale_units="xy",
            scale=1.0,
            color="white",
            edgecolor="black",
            linewidth=0.4,
            width=0.006,
        )
    worst = grid.worst_cell()
    if worst is not None:
        r, c = worst
        ax.add_patch(Rectangle((grid.u_edges[c], grid.v_edges[r]), cw, ch, fill=False, edgecolor="red", lw=2.0))
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)  # image convention: v grows downwards
    ax.set_aspect("equal")
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")
    return mesh


def residual_map_figure(grids: Mapping[str, ResidualGrid], arrows: bool = True) -> Figure:
    """One panel per camera (see :func:`draw_residual_map`), one colour scale (RMS |e|, px) for both.

    Arrows are on one scale for both cameras: the largest mean residual vector is drawn
    ``ARROW_CELL_FRACTION`` of a cell long; the legend states the scale.
    """
    if not grids:
        raise ValueError("residual_map_figure: no camera to draw")
    finite = [g.rms[np.isfinite(g.rms)] for g in grids.values()]
    vmax = max((float(f.max()) for f in finite if f.size), default=1.0)
    norm = Normalize(vmin=0.0, vmax=vmax if vmax > 0 else 1.0)
    longest = max(
        (float(np.nanmax(np.linalg.norm(g.mean, axis=-1))) for g in grids.values() if np.any(~g.masked)), default=0.0
    )
    scale = None
    if arrows and longest > 0:
        scale = ARROW_CELL_FRACTION * min(min(g.cell_size) for g in grids.values()) / longest
    fig = new_figure(5.6 * len(grids) + 1.2, 4.8)
    axes = np.atleast_1d(fig.subplots(1, len(grids), squeeze=False)).ravel()
    mesh = None
    for ax, (cam, g) in zip(axes, grids.items(), strict=True):
        mesh = draw_residual_map(ax, g, norm, scale)
        n = int(g.count.sum())
        worst = g.worst_cell()
        title = f"{cam} camera: {n} corners"
        if worst is not None:
            r, c = worst
            title += f"\nworst cell {g.rms[worst]:.3g} px ({image_region(g, r, c)}), overall {g.overall_rms:.3g} px"
        ax.set_title(title, fontsize=10)
    fig.colorbar(mesh, ax=list(axes), label="RMS |h(x) - z| per cell (px)", shrink=0.85)
    handles = [
        Patch(
            facecolor="0.88",
            edgecolor="0.65",
            hatch="//",
            label=f"fewer than {next(iter(grids.values())).min_count} corners",
        ),
        Patch(fill=False, edgecolor="red", lw=2.0, label="worst cell"),
    ]
    if scale is not None:
        handles.append(
            Patch(facecolor="white", edgecolor="black", label=f"arrow: mean residual, 1 px = {scale:.3g} px long")
        )
    fig.legend(handles=handles, loc="outside lower center", ncol=len(handles), fontsize=8)
    fig.suptitle("Reprojection residual over the image (cell colour: RMS residual magnitude)")
    return fig
