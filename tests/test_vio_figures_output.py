"""VIO figures of an output folder (``dcc_fg.plots.vio_output``) and through ``dcc-fg evaluate``.

A synthetic output folder: the ground truth is a 20 s circle (radius 5 m, 100 Hz, world frame W),
the estimate is the ground truth at 10 Hz keyframes seen through a rigid (or, for mono, similarity)
transform plus 2 mm noise, so the alignment must undo the transform before the figures are drawn.
"""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from dcc_fg.cli import main  # noqa: E402
from dcc_fg.io.outputs import write_joint_angles_csv  # noqa: E402
from dcc_fg.io.tum import write_tum  # noqa: E402
from dcc_fg.plots.vio import distance_travelled, joint_angles_figure  # noqa: E402
from dcc_fg.plots.vio_output import vio_output_figures, write_vio_figures  # noqa: E402
from dcc_fg.vio.evaluate import GroundTruth, evaluate_output  # noqa: E402

NS = 1_000_000_000
T0_NS = 1_600_000_000 * NS  # epoch-like stamps: the figures must use times relative to the first keyframe
NOISE = 0.002  # m
THETA_BIAS = np.array([0.01, -0.02])  # rad


def _truth() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground truth at 100 Hz: times (ns), body poses T_WI (N, 4, 4) on a 5 m circle, joint angles (N, 2) rad."""
    t = np.arange(0, 2001) * 0.01
    phi = 2 * np.pi * t / 20.0
    T = np.tile(np.eye(4), (t.size, 1, 1))
    T[:, :3, :3] = Rotation.from_euler("z", (phi + np.pi / 2)[:, None]).as_matrix()
    T[:, :3, 3] = np.stack([5 * np.cos(phi), 5 * np.sin(phi), 2.0 + 0.2 * np.sin(3 * phi)], axis=1)
    theta = np.stack([0.3 * np.sin(0.5 * t), 0.2 * np.cos(0.3 * t)], axis=1)
    return T0_NS + np.round(t * NS).astype(np.int64), T, theta


def _write_output(
    folder: Path, mode: str, scale: float = 1.0, joints: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A VIO output folder whose estimate is every 10th truth pose, moved by a fixed rigid transform
    (positions scaled by ``scale``) plus noise; returns the truth (times, poses, joints)."""
    t_ns, T, theta = _truth()
    rng = np.random.default_rng(3)
    k = np.arange(0, t_ns.size, 10)
    offset = np.eye(4)
    offset[:3, :3] = Rotation.from_euler("xyz", [0.02, -0.03, 0.7]).as_matrix()
    offset[:3, 3] = [1.0, -2.0, 0.5]
    est = offset @ T[k]
    est[:, :3, 3] = scale * (est[:, :3, 3] + rng.normal(0.0, NOISE, (k.size, 3)))
    folder.mkdir(parents=True)
    write_tum(folder / "trajectory.tum", t_ns[k], est)
    if joints:
        write_joint_angles_csv(folder / "joint_angles.csv", t_ns[k], theta[k] + THETA_BIAS)
    (folder / "summary.json").write_text(json.dumps({"mode": mode, "keyframes": int(k.size)}))
    return t_ns, T, theta


def _curves(ax, n: int) -> list:  # noqa: ANN001
    return [ln for ln in ax.lines if len(ln.get_xdata()) == n]


def test_dcc_figures_with_joint_truth(tmp_path: Path) -> None:
    out = tmp_path / "dcc"
    t_ns, T, theta = _write_output(out, "dcc")
    gt = GroundTruth(t_ns, T, t_ns, theta)
    saved = write_vio_figures(out, gt)
    assert set(saved.figures) == {"trajectory", "joint_angles", "error"}
    assert {p.name for p in saved.paths.values()} == {"vio_trajectory.png", "vio_joint_angles.png", "vio_error.png"}
    for p in saved.paths.values():
        assert p.parent == out and p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(out.glob(".*"))  # atomic writes leave no temporary files

    n = 201  # keyframes, all inside the ground truth
    (ax,) = saved.figures["trajectory"].axes
    gt_line, est_line = _curves(ax, n)
    assert gt_line.get_label() == "ground truth"
    assert est_line.get_label().startswith("dcc, SE(3)-aligned")
    # the alignment undid the 0.7 rad / 2 m offset: the estimate lies on the truth to the noise level
    gt_xy = np.column_stack([gt_line.get_xdata(), gt_line.get_ydata()])
    est_xy = np.column_stack([est_line.get_xdata(), est_line.get_ydata()])
    assert np.allclose(gt_xy, T[::10, :2, 3])
    assert np.abs(est_xy - gt_xy).max() < 6 * NOISE
    assert len([ln for ln in ax.lines if len(ln.get_xdata()) == 1]) == 3  # start + the two end markers
    assert ax.get_aspect() == 1.0 and ax.get_xlabel() == "x (m)" and ax.get_ylabel() == "y (m)"

    fig = saved.figures["joint_angles"]
    assert len(fig.axes) == 2
    for j, ax in enumerate(fig.axes):
        truth_line, est_line = ax.lines
        assert len(truth_line.get_xdata()) == 2001 and len(est_line.get_xdata()) == n
        assert truth_line.get_xdata()[0] == pytest.approx(0.0)  # seconds since the first keyframe
        assert np.allclose(est_line.get_ydata(), np.degrees(theta[::10, j] + THETA_BIAS[j]))
        (text,) = ax.texts
        assert text.get_text().startswith(f"RMSE {abs(THETA_BIAS[j]):.2g} rad")
    assert fig.axes[-1].get_xlabel() == "time since the first keyframe (s)"

    (ax,) = saved.figures["error"].axes
    (line,) = ax.lines
    assert np.allclose(line.get_xdata(), distance_travelled(T[::10, :3, 3]))
    assert line.get_ydata().max() < 6 * NOISE
    assert ax.get_xlabel() == "distance travelled (m)" and ax.get_ylabel() == "translation error (m)"


def test_figures_use_the_evaluation_alignment(tmp_path: Path) -> None:
    """The APE RMSE in the legend is the one evaluate_output reports (same association and alignment)."""
    out = tmp_path / "scc"
    t_ns, T, _ = _write_output(out, "scc")
    write_tum(tmp_path / "gt.tum", t_ns, T)
    ev = evaluate_output(out, tmp_path / "gt.tum")
    figs = vio_output_figures(out, tmp_path / "gt.tum")
    label = _curves(figs["trajectory"].axes[0], 201)[1].get_label()
    assert f"APE RMSE {ev['ape_rmse_m']:.3g} m" in label
    (line,) = figs["error"].axes[0].lines
    assert np.sqrt(np.mean(line.get_ydata() ** 2)) == pytest.approx(ev["ape_rmse_m"], rel=1e-9)
    # no joint truth in a TUM file: the joint panels show the estimate alone, without an RMSE
    fig = figs["joint_angles"]
    assert [len(ax.lines) for ax in fig.axes] == [1, 1] and not any(ax.texts for ax in fig.axes)


def test_mono_sim3_and_no_joints(tmp_path: Path) -> None:
    out = tmp_path / "mono"
    t_ns, T, theta = _write_output(out, "mono", scale=0.5, joints=False)
    figs = vio_output_figures(out, GroundTruth(t_ns, T, t_ns, theta))
    assert set(figs) == {"trajectory", "error"}
    gt_line, est_line = _curves(figs["trajectory"].axes[0], 201)
    assert "Sim(3)-aligned with scale 2.000" in est_line.get_label()
    assert np.abs(np.asarray(est_line.get_xdata()) - np.asarray(gt_line.get_xdata())).max() < 12 * NOISE
    (line,) = figs["error"].axes[0].lines
    assert line.get_ydata().max() < 12 * NOISE  # the noise was scaled too; Sim(3) scales it back by 2
    # forcing SE(3) on the half-scale estimate leaves metres of error
    figs_se3 = vio_output_figures(out, GroundTruth(t_ns, T), align="se3")
    assert figs_se3["error"].axes[0].lines[0].get_ydata().max() > 1.0


def test_locked_joints_are_drawn_on_a_readable_span() -> None:
    """scc holds the joints constant: the panel spans +-1 deg around them, without an offset tick label."""
    t = np.linspace(0.0, 10.0, 101)
    held = np.tile([np.pi / 2, 0.0], (t.size, 1))
    fig = joint_angles_figure(t, held, {"scc": held + 1e-12})
    for ax, value in zip(fig.axes, (90.0, 0.0), strict=True):
        assert ax.get_ylim() == pytest.approx((value - 1.0, value + 1.0))
        fig.canvas.draw()
        assert ax.yaxis.get_offset_text().get_text() == ""


def test_missing_trajectory_and_disjoint_times(tmp_path: Path) -> None:
    t_ns, T, _ = _truth()
    with pytest.raises(FileNotFoundError, match="trajectory.tum"):
        vio_output_figures(tmp_path, GroundTruth(t_ns, T))
    out = tmp_path / "dcc"
    _write_output(out, "dcc")
    with pytest.raises(ValueError, match="overlap"):
        vio_output_figures(out, GroundTruth(t_ns + 1000 * NS, T))


def test_cli_evaluate_writes_and_prints_figures(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    t_ns, T, _ = _write_output(out, "dcc")
    write_tum(tmp_path / "gt.tum", t_ns, T)
    assert main(["evaluate", str(out), "--ground-truth", str(tmp_path / "gt.tum")]) == 0
    printed = capsys.readouterr().out
    assert "APE translation RMSE" in printed
    for name in ("vio_trajectory.png", "vio_joint_angles.png", "vio_error.png"):
        assert f"wrote {out / name}" in printed
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "evaluation.json").is_file()
    # no figures (and exit code 2) when the ground truth does not overlap
    write_tum(tmp_path / "late.tum", t_ns + 1000 * NS, T)
    other = tmp_path / "other"
    _write_output(other, "dcc")
    assert main(["evaluate", str(other), "--ground-truth", str(tmp_path / "late.tum")]) == 2
    assert not list(other.glob("vio_*.png"))
