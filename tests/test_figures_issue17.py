"""Issue 17, item 3: the per-camera residual heat map over the image and the VIO joint-angle 1-sigma band.

* The binned statistics of :mod:`dcc_fg.plots.residual_map` against an independent per-cell computation
  on a known residual field (large residuals in one corner cell only), masking of sparse cells, the
  corners at the image border, the figure's artists and the report text.
* The heat map of a real calibration result with its dataset: written as ``calibration_residual_map.png``
  and a PDF page by :func:`dcc_fg.plots.write_calibration_outputs`, and by a ``dcc-fg calibrate`` /
  ``validate --report`` run.
* The band of :mod:`dcc_fg.plots.joint_band`: the shaded polygon's limits are ``theta +- sigma`` (deg),
  nothing where no sigma exists, the sigma file, and the VIO output figures with a sigma file.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from matplotlib.collections import PolyCollection, QuadMesh  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402
from matplotlib.quiver import Quiver  # noqa: E402

from dcc_fg.calibrate import CalibrationOptions, CalibrationResult, calibrate  # noqa: E402
from dcc_fg.cli import main  # noqa: E402
from dcc_fg.commands import calibrate as calibrate_cmd  # noqa: E402
from dcc_fg.data import CalibrationDataset, Observation, Snapshot  # noqa: E402
from dcc_fg.io.outputs import write_joint_angles_csv  # noqa: E402
from dcc_fg.io.tum import write_tum  # noqa: E402
from dcc_fg.plots import output as plots_output  # noqa: E402
from dcc_fg.plots import write_calibration_outputs  # noqa: E402
from dcc_fg.plots.joint_band import (  # noqa: E402
    SIGMA_FILE,
    draw_sigma_band,
    joint_error_band_figure,
    read_joint_sigmas_csv,
    sigmas_at,
)
from dcc_fg.plots.residual_map import (  # noqa: E402
    bin_residuals,
    corner_residuals,
    grid_shape,
    image_region,
    residual_grids,
    residual_map_figure,
    residual_map_summary,
)
from dcc_fg.plots.vio import joint_angles_figure  # noqa: E402
from dcc_fg.plots.vio_output import truth_at, write_vio_figures  # noqa: E402
from dcc_fg.sim.calibration_scene import SceneConfig, SimulatedCalibration, simulate_calibration  # noqa: E402
from dcc_fg.util.health import HealthReport  # noqa: E402
from dcc_fg.vio.evaluate import GroundTruth  # noqa: E402

W, H = 640, 480  # 8 x 6 cells of 80 x 80 px with the default 8 cells across
CELL = 80.0
NS = 1_000_000_000


def _pdf_pages(path: Path) -> int:
    return len(re.findall(rb"/Type\s*/Page(?![a-zA-Z])", path.read_bytes()))


# ------------------------------------------------------------------ binned statistics


def _field(seed: int = 0, n: int = 6000) -> tuple[np.ndarray, np.ndarray]:
    """Corners uniform over the image, residuals N(0, 0.3 px) per axis, except 3 px + a (1, -0.5) px
    bias in the bottom-right cell (u >= 560, v >= 400); the cell (row 2, col 3) keeps only 3 corners."""
    rng = np.random.default_rng(seed)
    z = rng.uniform([0.0, 0.0], [W, H], (n, 2))
    sparse = (z[:, 0] >= 3 * CELL) & (z[:, 0] < 4 * CELL) & (z[:, 1] >= 2 * CELL) & (z[:, 1] < 3 * CELL)
    keep = ~sparse
    keep[np.flatnonzero(sparse)[:3]] = True
    z = z[keep]
    e = rng.normal(0.0, 0.3, z.shape)
    bad = (z[:, 0] >= 7 * CELL) & (z[:, 1] >= 5 * CELL)
    e[bad] = rng.normal(0.0, 3.0, (int(bad.sum()), 2)) + [1.0, -0.5]
    return z, e


def _cell_stats_by_hand(z: np.ndarray, e: np.ndarray, row: int, col: int) -> tuple[int, float, np.ndarray]:
    """Count, RMS |e| and mean e of the corners in one 80 x 80 px cell, by boolean masks (no binning code)."""
    m = (z[:, 0] >= col * CELL) & (z[:, 0] < (col + 1) * CELL) & (z[:, 1] >= row * CELL) & (z[:, 1] < (row + 1) * CELL)
    sel = e[m]
    return int(m.sum()), float(np.sqrt(np.mean(np.sum(sel**2, axis=1)))), sel.mean(axis=0)


def test_binned_statistics_equal_an_independent_computation() -> None:
    z, e = _field()
    g = bin_residuals(z, e, (W, H), cells_across=8, min_count=5)
    assert g.count.shape == (6, 8) and grid_shape((W, H), 8) == (6, 8) and g.cell_size == (80.0, 80.0)
    assert np.allclose(g.u_edges, np.arange(9) * CELL) and np.allclose(g.v_edges, np.arange(7) * CELL)
    assert g.count.sum() == len(z) and g.n_outside == 0
    for row in range(6):
        for col in range(8):
            n, rms, mean = _cell_stats_by_hand(z, e, row, col)
            assert g.count[row, col] == n
            if (row, col) == (2, 3):
                assert n == 3 and g.masked[row, col] and np.isnan(g.rms[row, col])
                assert np.all(np.isnan(g.mean[row, col]))
                continue
            assert not g.masked[row, col]
            assert g.rms[row, col] == pytest.approx(rms, rel=1e-12)
            assert np.allclose(g.mean[row, col], mean, rtol=1e-12, atol=1e-15)
    # the large residuals are only in the bottom-right cell: it is the worst, at about 3 * sqrt(2) px
    assert g.worst_cell() == (5, 7)
    assert 3.5 < g.rms[5, 7] < 5.5 and np.nanmax(np.delete(g.rms.ravel(), 5 * 8 + 7)) < 0.6
    assert np.allclose(g.mean[5, 7], [1.0, -0.5], atol=0.8)
    assert g.overall_rms == pytest.approx(np.sqrt(np.mean(np.sum(e**2, axis=1))))
    assert image_region(g, 5, 7) == "bottom-right corner" and image_region(g, 2, 3) == "centre"
    assert image_region(g, 0, 4) == "top edge" and image_region(g, 3, 0) == "left edge"


def test_sparse_cells_are_masked_and_border_corners_binned() -> None:
    # 4 corners in the top-left cell (< min_count 5), 5 in the top-right one, none elsewhere
    z = np.array([[10, 10], [20, 20], [30, 30], [40, 40], *[[600 + k, 10 + k] for k in range(5)]], float)
    e = np.tile([0.5, 0.0], (len(z), 1))
    g = bin_residuals(z, e, (W, H), 8, min_count=5)
    assert g.masked.sum() == 47 and not g.masked[0, 7] and g.count[0, 0] == 4
    assert g.worst_cell() == (0, 7) and g.rms[0, 7] == pytest.approx(0.5)
    everything_masked = bin_residuals(z[:4], e[:4], (W, H), 8, min_count=5)
    assert everything_masked.worst_cell() is None
    assert "no cell has enough corners" in residual_map_summary({"static": everything_masked})
    # pixel-centre conventions: a corner half a pixel outside lands in the border cell; further out is not binned
    edge = bin_residuals(np.array([[-0.4, 479.9], [640.3, 0.0], [-3.0, 10.0]]), np.zeros((3, 2)), (W, H), 8, 1)
    assert edge.count[5, 0] == 1 and edge.count[0, 7] == 1 and edge.n_outside == 1
    with pytest.raises(ValueError, match="3 corner positions but 2 residuals"):
        bin_residuals(np.zeros((3, 2)), np.zeros((2, 2)), (W, H))
    with pytest.raises(ValueError, match="NaN"):
        bin_residuals(np.full((1, 2), np.nan), np.zeros((1, 2)), (W, H))


def test_summary_names_the_worst_cell() -> None:
    z, e = _field()
    g = bin_residuals(z, e, (W, H))
    text = residual_map_summary({"static": g, "dynamic": g})
    lines = text.splitlines()
    assert len(lines) == 2 and lines[0].startswith("residual map, static camera (8 x 6 cells of 80 x 80 px, >= 5")
    assert f"worst cell RMS |e| {g.rms[5, 7]:.3g} px at u 560-640, v 400-480 px (bottom-right corner" in lines[0]
    assert "1 of 48 cells masked" in lines[0]


def test_heat_map_figure_artists() -> None:
    z, e = _field()
    g = bin_residuals(z, e, (W, H))
    g2 = bin_residuals(z[::2], e[::2] * 0.5, (W, H))
    fig = residual_map_figure({"static": g, "dynamic": g2})
    assert isinstance(fig, Figure)
    panels = [ax for ax in fig.axes if any(isinstance(c, QuadMesh) for c in ax.collections) and ax.get_title()]
    assert len(panels) == 2
    for ax, grid in zip(panels, (g, g2), strict=True):
        (mesh,) = [c for c in ax.collections if isinstance(c, QuadMesh)]
        arr = mesh.get_array()
        assert np.array_equal(np.ma.getmaskarray(arr).reshape(grid.rms.shape), grid.masked)
        assert np.allclose(np.ma.filled(arr, 0.0).reshape(grid.rms.shape), np.nan_to_num(grid.rms))
        assert mesh.norm.vmin == 0.0 and mesh.norm.vmax == pytest.approx(np.nanmax(g.rms))  # one scale for both
        red = [p for p in ax.patches if isinstance(p, Rectangle) and p.get_edgecolor()[:3] == (1.0, 0.0, 0.0)]
        (worst,) = red
        r, c = grid.worst_cell()
        assert worst.get_xy() == (grid.u_edges[c], grid.v_edges[r])
        (quiver,) = [c for c in ax.collections if isinstance(c, Quiver)]
        assert len(quiver.U) == int((~grid.masked).sum())
        assert ax.get_ylim() == (H, 0) and ax.get_xlim() == (0, W)  # image convention, v down
        assert "worst cell" in ax.get_title()
    # the longest mean vector of both cameras is drawn 0.45 cell long
    longest = max(np.nanmax(np.linalg.norm(gr.mean, axis=-1)) for gr in (g, g2))
    q = [c for c in panels[0].collections if isinstance(c, Quiver)][0]
    assert np.max(np.hypot(q.U, q.V)) == pytest.approx(
        0.45 * CELL * np.nanmax(np.linalg.norm(g.mean, axis=-1)) / longest
    )


# ------------------------------------------------------------------ with a calibration


@pytest.fixture(scope="module")
def small() -> tuple[SimulatedCalibration, CalibrationResult]:
    sim = simulate_calibration(2, SceneConfig(n_joints=2, n_calibration=12, n_validation=1))
    return sim, calibrate(sim.calibration_set, sim.initial, CalibrationOptions())


def test_corner_residuals_follow_the_dataset(small) -> None:  # noqa: ANN001
    sim, res = small
    data = sim.calibration_set
    for cam, rs in (("static", res.residuals_static), ("dynamic", res.residuals_dynamic)):
        z, e = corner_residuals(res, data, cam)
        snaps = [s.static if cam == "static" else s.dynamic for s in data.snapshots]
        assert np.array_equal(z, np.concatenate([o.pixels for o in snaps])) and np.array_equal(e, np.concatenate(rs))
    grids = residual_grids(res, data)
    assert grids["static"].count.sum() + grids["static"].n_outside == sum(len(r) for r in res.residuals_static)
    assert grids["dynamic"].resolution == tuple(data.dynamic_camera.resolution)
    # a dataset that is not the result's is refused, naming the snapshot
    s0 = data.snapshots[0]
    fewer = Snapshot(s0.timestamp_ns, Observation(s0.static.ids[:-1], s0.static.pixels[:-1]), s0.dynamic, s0.joints)
    other = CalibrationDataset(
        data.static_camera, data.dynamic_camera, data.target_points, [fewer, *data.snapshots[1:]], data.source
    )
    with pytest.raises(ValueError, match="snapshot 0 has"):
        corner_residuals(res, other, "static")
    with pytest.raises(ValueError, match="2 snapshots but the dataset"):
        corner_residuals(res, CalibrationDataset(data.static_camera, data.dynamic_camera, data.target_points,
                                                 data.snapshots[:2]), "dynamic")  # fmt: skip


def test_calibration_outputs_with_the_heat_map(
    small,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,  # noqa: ANN001
) -> None:
    sim, res = small
    texts: list[str] = []
    real_pdf = plots_output.write_report_pdf

    def capture(path: Path, summary: str, figures, title: str = "") -> int:  # noqa: ANN001
        texts.append(summary)
        return real_pdf(path, summary, figures, title)

    monkeypatch.setattr(plots_output, "write_report_pdf", capture)
    paths = write_calibration_outputs(tmp_path, res, "summary", data=sim.calibration_set)
    names = [p.name for p in paths]
    assert names[1] == "calibration_residual_map.png" and names[-1] == "report.pdf" and len(names) == 7
    assert (tmp_path / "calibration_residual_map.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert _pdf_pages(tmp_path / "report.pdf") == 1 + 6
    (text,) = texts
    assert text.startswith("summary\n\n") and text.endswith(
        residual_map_summary(residual_grids(res, sim.calibration_set))
    )
    # without the dataset: the five figures as before, no heat map
    other = tmp_path / "no_data"
    paths = write_calibration_outputs(other, res, "summary", target_points=sim.calibration_set.target_points)
    assert len(paths) == 6 and not (other / "calibration_residual_map.png").exists()


def test_calibrate_and_validate_cli_write_the_heat_map(
    small,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,  # noqa: ANN001
) -> None:
    """``dcc-fg calibrate / validate --report`` with the loading, the estimator and the health check
    replaced (the real figures and report are written)."""
    sim, res = small
    mp = monkeypatch
    mp.setattr(calibrate_cmd, "load_calibration_data", lambda *a, **k: sim.calibration_set)
    mp.setattr(calibrate_cmd, "initial_values", lambda inputs, init, mode, data: (sim.initial, data))
    mp.setattr(calibrate_cmd, "load_calibration", lambda path: sim.initial)
    mp.setattr(calibrate_cmd, "calibrate", lambda *a, **k: res)
    mp.setattr(calibrate_cmd, "calibrate_global", lambda *a, **k: res)
    mp.setattr(calibrate_cmd, "calibration_health", lambda **kw: HealthReport("calibration"))
    data = tmp_path / "data"
    (data / "cam0").mkdir(parents=True)
    (data / "cam1").mkdir()
    files = {}
    for name in ("camchain", "target", "gimbal", "calibration"):
        files[name] = tmp_path / "in" / f"{name}.yaml"
        files[name].parent.mkdir(exist_ok=True)
        files[name].write_text(f"{name}: input\n")
    common = ["--camchain", str(files["camchain"]), "--target", str(files["target"]), "-q", "--report"]
    cal, val = tmp_path / "cal", tmp_path / "val"
    assert main(["calibrate", str(data), *common, "--gimbal", str(files["gimbal"]), "--out", str(cal)]) == 0
    assert main(["validate", str(data), *common, "--calibration", str(files["calibration"]), "--out", str(val)]) == 0
    for out in (cal, val):
        assert (out / "report.pdf").is_file() and (out / "calibration_residuals.png").is_file()
    for out in (cal, val):
        assert (out / "calibration_residual_map.png").is_file() and _pdf_pages(out / "report.pdf") >= 1 + 6


# ------------------------------------------------------------------ the VIO joint-angle band


def _band_vertices(band: PolyCollection) -> np.ndarray:
    return np.concatenate([p.vertices for p in band.get_paths()])


def test_band_limits_are_estimate_plus_minus_sigma() -> None:
    t = np.linspace(0.0, 10.0, 41)
    theta = 0.3 * np.sin(t)
    sigma = 0.01 + 0.002 * t
    sigma[15:20] = np.nan  # no sigma reported for these keyframes: no band there
    fig = Figure()
    ax = fig.add_subplot()
    band = draw_sigma_band(ax, t, theta, sigma, color="tab:blue", label="±1σ")
    assert isinstance(band, PolyCollection) and band in ax.collections and len(band.get_paths()) == 2
    v = _band_vertices(band)
    for k in range(len(t)):
        at = v[np.isclose(v[:, 0], t[k], rtol=0, atol=1e-12)]
        if np.isnan(sigma[k]):
            assert at.size == 0, f"band drawn at keyframe {k} without a sigma"
            continue
        assert np.isclose(at[:, 1].min(), np.degrees(theta[k] - sigma[k]), rtol=0, atol=1e-9)
        assert np.isclose(at[:, 1].max(), np.degrees(theta[k] + sigma[k]), rtol=0, atol=1e-9)
    assert draw_sigma_band(ax, t, theta, np.full_like(t, np.nan)) is None  # nothing to draw
    with pytest.raises(ValueError, match="alike"):
        draw_sigma_band(ax, t, theta, sigma[:-1])


def test_joint_angles_figure_with_sigmas() -> None:
    t = np.linspace(0.0, 20.0, 81)
    truth = np.stack([0.3 * np.sin(0.3 * t), 0.2 * np.cos(0.2 * t)], axis=1)
    est = truth + 0.004
    sigma = np.full_like(est, 0.005)
    sigma[:10, 1] = np.nan
    fig = joint_angles_figure(t, truth, {"dcc": est}, {"dcc": sigma})
    assert len(fig.axes) == 2
    for j, ax in enumerate(fig.axes):
        assert len(ax.lines) == 2  # truth and estimate, as without sigmas
        (band,) = [c for c in ax.collections if isinstance(c, PolyCollection)]
        assert band.get_label() == "dcc ±1σ"
        assert np.allclose(band.get_facecolor()[0][:3], matplotlib.colors.to_rgb(ax.lines[1].get_color()))
        v = _band_vertices(band)
        ok = np.isfinite(sigma[:, j])
        for k in np.flatnonzero(ok):
            at = v[np.isclose(v[:, 0], t[k], rtol=0, atol=1e-12), 1]
            assert np.isclose(at.min(), np.degrees(est[k, j] - sigma[k, j]))
            assert np.isclose(at.max(), np.degrees(est[k, j] + sigma[k, j]))
        assert v[:, 0].min() == pytest.approx(t[np.flatnonzero(ok)[0]])
    # a locked joint: the y range still shows the whole band
    flat = np.zeros((len(t), 1))
    fig = joint_angles_figure(t, None, {"scc": flat}, {"scc": np.full((len(t), 1), np.radians(3.0))})
    lo, hi = fig.axes[0].get_ylim()
    assert lo <= -3.0 and hi >= 3.0
    with pytest.raises(ValueError, match="not one of the estimates"):
        joint_angles_figure(t, truth, {"dcc": est}, {"mono": sigma})
    with pytest.raises(ValueError, match="shape"):
        joint_angles_figure(t, truth, {"dcc": est}, {"dcc": sigma[:, :1]})


def test_sigma_file_and_error_band_figure(tmp_path: Path) -> None:
    path = tmp_path / SIGMA_FILE
    path.write_text("timestamp_ns,sigma_theta_1,sigma_theta_2\n30,0.01,0.02\n10,nan,0.03\n")
    s_ns, sig = read_joint_sigmas_csv(path)
    assert s_ns.tolist() == [30, 10] and np.isnan(sig[1, 0]) and sig[0, 1] == 0.02
    at = sigmas_at(np.array([10, 20, 30], np.int64), s_ns, sig, 2)
    assert np.isnan(at[0, 0]) and at[0, 1] == 0.03 and np.all(np.isnan(at[1])) and at[2].tolist() == [0.01, 0.02]
    with pytest.raises(ValueError, match="have 2 joints, the joint angles 3"):
        sigmas_at(np.array([10]), s_ns, sig, 3)
    for bad, match in (
        ("timestamp_ns,theta_1\n1,0.1\n", ":1: columns"),
        ("timestamp_ns,sigma_theta_1\n1,-0.1\n", ":2:"),
    ):
        path.write_text(bad)
        with pytest.raises(ValueError, match=match):
            read_joint_sigmas_csv(path)
    t = np.arange(10.0)
    err = np.column_stack([np.linspace(-0.02, 0.02, 10)])
    fig = joint_error_band_figure(t, err, np.full((10, 1), 0.01))
    (ax,) = fig.axes
    (band,) = [c for c in ax.collections if isinstance(c, PolyCollection)]
    v = _band_vertices(band)
    assert np.isclose(v[:, 1].min(), np.degrees(-0.01)) and np.isclose(v[:, 1].max(), np.degrees(0.01))
    inside = int(np.sum(np.abs(err) <= 0.01))
    assert f"{100 * inside / 10:.0f}% of 10 keyframes inside" in band.get_label()


def test_vio_output_figures_with_a_sigma_file(tmp_path: Path) -> None:
    """A dcc output folder with ``joint_angles_sigma.csv`` (sigmas for all keyframes but the first 5)."""
    t0 = 1_600_000_000 * NS
    t = np.arange(0, 1001) * 0.01
    t_ns = t0 + np.round(t * NS).astype(np.int64)
    T = np.tile(np.eye(4), (t.size, 1, 1))
    T[:, :3, 3] = np.stack([np.cos(t), np.sin(t), 0.1 * t], axis=1)
    theta = np.stack([0.3 * np.sin(0.5 * t), 0.2 * np.cos(0.3 * t)], axis=1)
    k = np.arange(0, t.size, 10)
    out = tmp_path / "run"
    out.mkdir()
    write_tum(out / "trajectory.tum", t_ns[k], T[k])
    est = theta[k] + [0.004, -0.002]
    write_joint_angles_csv(out / "joint_angles.csv", t_ns[k], est)
    (out / "summary.json").write_text(json.dumps({"mode": "dcc", "keyframes": int(k.size)}))
    sigma = np.full((k.size, 2), 0.005)
    rows = [f"{t_ns[i]},{s[0]},{s[1]}" for i, s in zip(k[5:], sigma[5:], strict=True)]
    (out / SIGMA_FILE).write_text("timestamp_ns,sigma_theta_1,sigma_theta_2\n" + "\n".join(rows) + "\n")
    saved = write_vio_figures(out, GroundTruth(t_ns, T, t_ns, theta))
    assert set(saved.figures) == {"trajectory", "joint_angles", "error", "joint_errors"}
    assert saved.paths["joint_errors"].name == "vio_joint_errors.png" and saved.paths["joint_errors"].is_file()
    t_est = (t_ns[k] - t_ns[k][0]) / NS
    for j, ax in enumerate(saved.figures["joint_angles"].axes):
        (band,) = [c for c in ax.collections if isinstance(c, PolyCollection)]
        v = _band_vertices(band)
        assert v[:, 0].min() == pytest.approx(t_est[5])  # no band before the first sigma
        assert np.isclose(v[:, 1].max(), np.degrees(np.max(est[5:, j] + 0.005)))
        assert np.isclose(v[:, 1].min(), np.degrees(np.min(est[5:, j] - 0.005)))
    assert np.allclose(truth_at(t_ns[k], t_ns, theta), theta[k])
    for j, ax in enumerate(saved.figures["joint_errors"].axes):
        (line,) = ax.lines[:1]
        assert np.allclose(line.get_ydata(), np.degrees(est[:, j] - theta[k, j]))
    # without the file: the figures as before
    (out / SIGMA_FILE).unlink()
    plain = write_vio_figures(out, GroundTruth(t_ns, T, t_ns, theta), figure_dir=tmp_path / "plain")
    assert set(plain.figures) == {"trajectory", "joint_angles", "error"}
    assert not any(isinstance(c, PolyCollection) for ax in plain.figures["joint_angles"].axes for c in ax.collections)
