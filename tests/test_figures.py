"""Every figure is drawn headless (Agg) and contains the artists it promises; the PDF report has its pages."""

from __future__ import annotations

import re
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from matplotlib.collections import PathCollection  # noqa: E402
from matplotlib.container import ErrorbarContainer  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.patches import Circle  # noqa: E402

from dcc_fg import load_calibration, report  # noqa: E402
from dcc_fg.calibrate import CalibrationOptions, CalibrationResult, calibrate  # noqa: E402
from dcc_fg.cli import main  # noqa: E402
from dcc_fg.io.camchain import CamchainEntry  # noqa: E402
from dcc_fg.model import GimbalCalibration  # noqa: E402
from dcc_fg.plots import chain3d, distance_travelled  # noqa: E402
from dcc_fg.plots.calibration import noise_sigma, snapshot_rms  # noqa: E402
from dcc_fg.sim.calibration_scene import (  # noqa: E402
    SceneConfig,
    SimulatedCalibration,
    simulate_calibration,
    true_kinematics,
)
from dcc_fg.sim.write_dataset import CalibrationSimSpec, write_calibration_dataset  # noqa: E402
from dcc_fg.sources.dataset import load_dataset  # noqa: E402
from factors import chain  # noqa: E402
from factors.camera import CameraModel  # noqa: E402
from tests.conftest import shared_data  # noqa: E402

K = 20  # snapshots of the small L = 2 problem (fast; the figures do not need the demo's 81)


@pytest.fixture(scope="module")
def small() -> tuple[SimulatedCalibration, CalibrationResult]:
    sim = simulate_calibration(1, SceneConfig(n_joints=2, n_calibration=K, n_validation=5))
    return sim, calibrate(sim.calibration_set, sim.initial, CalibrationOptions())


def _scatters(ax) -> list[PathCollection]:  # noqa: ANN001
    return [c for c in ax.collections if isinstance(c, PathCollection)]


def _errorbars(ax) -> list[ErrorbarContainer]:  # noqa: ANN001
    return [c for c in ax.containers if isinstance(c, ErrorbarContainer)]


def _labels(fig: Figure) -> str:
    out = [fig._suptitle.get_text() if fig._suptitle else ""]
    for ax in fig.axes:
        out += [ax.get_title(), ax.get_xlabel(), ax.get_ylabel()]
        if hasattr(ax, "get_zlabel"):
            out.append(ax.get_zlabel())
        leg = ax.get_legend()
        if leg is not None:
            out += [t.get_text() for t in leg.get_texts()]
        out += [t.get_text() for t in ax.texts]
    return "\n".join(out)


def _pdf_pages(path: Path) -> int:
    return len(re.findall(rb"/Type\s*/Page(?![a-zA-Z])", path.read_bytes()))


def test_residual_figure(small) -> None:  # noqa: ANN001
    sim, res = small
    fig = report.residual_figure(res, pixel_sigma=0.4)
    assert isinstance(fig, Figure) and len(fig.axes) == 4
    for c, rs in enumerate((res.residuals_static, res.residuals_dynamic)):
        ax_s, ax_h = fig.axes[c], fig.axes[2 + c]
        (sc,) = _scatters(ax_s)
        r = np.concatenate(rs)
        assert sc.get_offsets().shape == r.shape  # one point per corner
        assert np.allclose(sc.get_offsets(), r)
        circles = [p for p in ax_s.patches if isinstance(p, Circle)]
        assert sorted(round(c.get_radius(), 9) for c in circles) == [0.4, 0.8, 1.2]
        assert len(ax_h.patches) == 2 and len(ax_h.lines) == 1  # du, dv histograms and the Gaussian
        assert ax_s.get_xlabel() == "du (px)" and ax_s.get_ylabel() == "dv (px)"
    text = _labels(fig)
    assert "1σ" in text and "3σ" in text and "static camera" in text and "dynamic camera" in text


def test_snapshot_error_figure(small) -> None:  # noqa: ANN001
    sim, res = small
    fig = report.snapshot_error_figure(res, sim.truth, sim.joints_calibration)
    assert len(fig.axes) == 4
    ax_r, ax_rot, ax_tr, ax_j = fig.axes
    pts = [ln for ln in ax_r.lines if len(ln.get_xdata()) == K]
    assert len(pts) == 2
    assert np.allclose(pts[0].get_ydata(), snapshot_rms(res, "static"))
    for ax in (ax_rot, ax_tr):
        assert [len(ln.get_xdata()) for ln in ax.lines] == [K, K]  # errors and reported 1-sigma
    bars = _errorbars(ax_j)
    assert len(bars) == 2 and all(len(b.lines[0].get_xdata()) == K for b in bars)
    # without truth: only the reported 1-sigma
    fig2 = report.snapshot_error_figure(res)
    assert [len(ln.get_xdata()) for ln in fig2.axes[1].lines] == [K]
    assert "ground truth" not in fig2.axes[1].get_title()
    assert "snapshot" in fig.axes[-1].get_xlabel()


def test_coverage_figure_panels(small) -> None:  # noqa: ANN001
    _, res = small
    fig = report.coverage_figure(res)
    scatter_axes = [ax for ax in fig.axes if _scatters(ax)]
    assert len(scatter_axes) == 1 and len(fig.axes) == 2  # the panel and its colour bar
    (sc,) = _scatters(scatter_axes[0])
    assert np.allclose(sc.get_offsets(), np.degrees(res.joint_angles))
    assert scatter_axes[0].get_xlabel() == "θ_1 (deg)" and scatter_axes[0].get_ylabel() == "θ_2 (deg)"
    rng = np.random.default_rng(0)
    fig3 = report.coverage_figure(res, joint_angles=rng.uniform(-1, 1, (K, 3)))
    panels = [ax for ax in fig3.axes if _scatters(ax)]
    assert len(panels) == 3  # theta_1/2, theta_1/3, theta_2/3
    assert all(len(_scatters(ax)[0].get_offsets()) == K for ax in panels)
    fig1 = report.coverage_figure(res, joint_angles=rng.uniform(-1, 1, (K, 1)))
    (ax1,) = [ax for ax in fig1.axes if _scatters(ax)]
    assert len(_scatters(ax1)[0].get_offsets()) == K
    assert len(fig1.axes[0].patches) > 0 and fig1.axes[0].get_ylabel() == "snapshots"  # histogram bars


def test_parameter_figure_marks_status(small) -> None:  # noqa: ANN001
    sim, res = small
    cal = res.calibration
    fig = report.parameter_figure(cal, sim.truth)
    assert len(fig.axes) == 4
    n = len(cal.kin)
    value_axes = fig.axes[0::2]
    counts = {"o": 0, "s": 0, "^": 0}
    for ax in value_axes:
        for b in _errorbars(ax):
            counts[b.lines[0].get_marker()] += len(b.lines[0].get_xdata())
    assert sum(counts.values()) == n
    assert counts["s"] == int(cal.gauge_fixed.sum())
    assert counts["o"] == int((cal.observable & ~cal.gauge_fixed).sum())
    truth_pts = sum(len(ln.get_xdata()) for ax in value_axes for ln in ax.lines if ln.get_marker() == "x")
    assert truth_pts == n
    ticks = [t.get_text() for ax in value_axes for t in ax.get_yticklabels()]
    assert sorted(ticks) == sorted(cal.names)
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    assert "unobservable (gauge-dependent)" in legend and "gauge-fixed (held)" in legend and "truth" in legend


@pytest.mark.parametrize("L", [0, 1, 2, 3])
def test_chain_figure_frames(L: int) -> None:

    truth = true_kinematics(L)
    theta = np.linspace(0.2, 0.5, L)
    fig = report.chain_figure(truth, theta)
    (ax,) = fig.axes
    n_frames = L + 3 if L > 0 else 3  # s, b, 1..L-1, e, d (b and e coincide when L = 0)
    assert len(ax.lines) == 3 * n_frames + 1 + L  # triads, the chain polyline, the joint axes
    labels = {t.get_text() for t in ax.texts}
    assert labels == ({"s", "b", "e", "d", *(str(i) for i in range(1, L))} if L else {"s", "b = e", "d"})
    frames = chain3d.chain_frames(truth, theta)
    assert np.allclose(chain.inv_se3(frames["d"]) @ frames["s"], truth.T_ds(theta))
    # the d triad starts at the dynamic camera's origin in s (plotted as x, z, -y)
    o = frames["d"][:3, 3]
    starts = [(ln.get_data_3d()[0][0], ln.get_data_3d()[1][0], ln.get_data_3d()[2][0]) for ln in ax.lines]
    assert any(np.allclose(s, (o[0], o[2], -o[1])) for s in starts)


def test_chain_figure_with_target(small) -> None:  # noqa: ANN001
    sim, res = small
    figs = report.calibration_figures(
        res, sim.truth, sim.joints_calibration, target_points=sim.calibration_set.target_points
    )
    assert set(figs) == {"residuals", "snapshot_errors", "coverage", "parameters", "chain"}
    fig = figs["chain"]
    assert len(fig.axes) == 2
    (sc,) = _scatters(fig.axes[1])
    assert len(sc._offsets3d[0]) == len(sim.calibration_set.target_points)


def _vio_data() -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    t = np.linspace(0.0, 20.0, 201)
    gt = np.stack([np.cos(t / 5), np.sin(t / 5), 0.01 * t], axis=1)
    est = {"dcc": gt + 0.01, "scc": gt + np.array([0.0, 0.02 * t[-1], 0.0]) * (t / t[-1])[:, None], "mono": gt * 1.05}
    return t, gt, est


def test_vio_figures() -> None:
    t, gt, est = _vio_data()
    fig = report.trajectory_topview_figure(gt, est)
    (ax,) = fig.axes
    curves = [ln for ln in ax.lines if len(ln.get_xdata()) == len(t)]
    assert [ln.get_label() for ln in curves] == ["ground truth", "dcc", "scc", "mono"]
    assert np.allclose(curves[0].get_xdata(), gt[:, 0]) and np.allclose(curves[0].get_ydata(), gt[:, 1])
    assert "start" in _labels(fig) and "end" in _labels(fig)

    th = np.stack([0.3 * np.sin(t), 0.1 * np.cos(t), 0.2 * t / t[-1]], axis=1)
    fig = report.joint_angles_figure(t, th, {"dcc": th + 0.01, "dcc (t_est)": (t[::2], th[::2])})
    assert len(fig.axes) == 3
    for j, ax in enumerate(fig.axes):
        assert len(ax.lines) == 3 and ax.get_ylabel() == f"θ_{j + 1} (deg)"
        assert np.allclose(ax.lines[0].get_ydata(), np.degrees(th[:, j]))

    fig = report.error_over_distance_figure(gt, est)
    (ax,) = fig.axes
    assert len(ax.lines) == 3

    d = distance_travelled(gt)
    assert np.allclose(ax.lines[0].get_xdata(), d)
    assert np.allclose(ax.lines[2].get_ydata(), np.linalg.norm(gt * 0.05, axis=1))
    assert ax.get_xlabel() == "distance travelled (m)"


def test_vio_figures_reject_bad_input() -> None:

    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 0]], float)
    assert distance_travelled(square)[-1] == pytest.approx(4.0)
    t, gt, est = _vio_data()
    with pytest.raises(ValueError, match="dcc"):
        report.error_over_distance_figure(gt, {"dcc": gt[:-1]})
    with pytest.raises(ValueError, match="NaN"):
        report.trajectory_topview_figure(gt, {"mono": np.full_like(gt, np.nan)})
    with pytest.raises(ValueError, match="same number of joints"):
        report.joint_angles_figure(t, np.zeros((len(t), 2)), {"dcc": np.zeros((len(t), 3))})


def test_report_pdf_pages_and_pngs(small, tmp_path: Path) -> None:  # noqa: ANN001
    sim, res = small
    paths = report.write_calibration_outputs(
        tmp_path, res, "summary\n" * 200, sim.truth, sim.joints_calibration, sim.calibration_set.target_points
    )
    names = sorted(p.name for p in paths)
    stems = ("residuals", "snapshot_errors", "coverage", "parameters", "chain")
    assert names == sorted([f"calibration_{n}.png" for n in stems] + ["report.pdf"])
    for p in paths[:-1]:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # 200 summary lines -> 3 text pages (80 per page), then 5 figures
    assert _pdf_pages(tmp_path / "report.pdf") == 3 + 5
    assert not list(tmp_path.glob(".*"))  # no temporary files left behind


@pytest.mark.slow  # renders a 12-snapshot image set, calibrates and validates twice (~30-90 s)
def test_calibrate_cli_report(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``dcc-fg calibrate IMAGES ... --report`` on a small rendered image folder, then ``validate --report``."""
    spec = CalibrationSimSpec("checkerboard", "folder", seed=5, n_snapshots=12)
    r = write_calibration_dataset(tmp_path / "set", spec)
    files = ["--camchain", str(r.camchain), "--target", str(r.target)]
    out = tmp_path / "out"
    assert main(["calibrate", str(r.data), *files, "--gimbal", str(r.gimbal), "--out", str(out), "--report"]) == 0
    assert "report.pdf" in capsys.readouterr().out
    assert (out / "calibration.yaml").exists() and _pdf_pages(out / "report.pdf") == 1 + 6
    assert sorted(p.name for p in out.glob("calibration_*.png")) == sorted(
        f"calibration_{n}.png"
        for n in ("residuals", "snapshot_errors", "coverage", "parameters", "chain", "residual_map", "accuracy")
    )
    table = report.parameter_table(load_calibration(out / "calibration.yaml"))
    assert table.count("gauge-fixed") == 5 and "dh2.alpha" in table  # L = 2 encoderless: 5 entries held
    # validate without --report: no figures; with --report: figures of the validation run
    val = tmp_path / "val"
    argv = ["validate", str(r.data), "--calibration", str(out / "calibration.yaml"), *files, "--quiet"]
    assert main([*argv, "--out", str(val)]) == 0
    assert not list(val.glob("*.png")) and not (val / "report.pdf").exists()
    assert main([*argv, "--out", str(val), "--report"]) == 0
    assert _pdf_pages(val / "report.pdf") == 1 + 6 and capsys.readouterr().out == ""


def test_figures_on_real_euroc_stereo_pair() -> None:
    """The EuRoC VI-sensor stereo pair (real AprilGrid detections) as an L = 0 cluster."""
    root = shared_data("euroc_aprilgrid/calib/cam_april")
    # intrinsics from EuRoC's sensor.yaml (cam0, cam1)
    c0 = CameraModel(
        (458.654, 457.296, 367.215, 248.375), "radtan", (-0.28340811, 0.07395907, 1.9359e-4, 1.76e-5), (752, 480)
    )
    c1 = CameraModel(
        (457.587, 456.134, 379.999, 255.238), "radtan", (-0.28368365, 0.07451284, -1.0473e-4, -3.56e-5), (752, 480)
    )
    data = load_dataset(root, {"cam0": CamchainEntry(c0), "cam1": CamchainEntry(c1)}, progress=False)
    init = GimbalCalibration.from_parts(
        np.zeros(6), [0, 0, 0, -0.1, 0, 0], np.zeros((0, 3)), static_camera=c0, dynamic_camera=c1
    )
    res = calibrate(data, init, CalibrationOptions())
    figs = report.calibration_figures(res, target_points=data.target_points)
    fig = figs["residuals"]
    n_corners = [sum(len(r) for r in rs) for rs in (res.residuals_static, res.residuals_dynamic)]
    assert [len(_scatters(fig.axes[c])[0].get_offsets()) for c in (0, 1)] == n_corners
    # robust noise estimate: sub-pixel corners on real images, below the RMS that the outlier corners inflate
    sigma, source = noise_sigma(res)
    allr = np.concatenate(res.residuals_static + res.residuals_dynamic)
    assert "MAD" in source and 0.05 < sigma < 0.5 and sigma < np.sqrt(np.mean(allr**2))
    assert "rigid pair" in _labels(figs["coverage"])
    assert {t.get_text() for t in figs["chain"].axes[0].texts} == {"s = b = e", "d"}
    ax_r = figs["snapshot_errors"].axes[0]
    assert sum(len(ln.get_xdata()) == len(data.snapshots) for ln in ax_r.lines) == 2
