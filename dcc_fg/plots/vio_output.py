"""Figures of a VIO output folder against ground truth, saved next to the outputs (``dcc-fg evaluate``).

Reads what :func:`dcc_fg.vio.backend.write_vio_outputs` writes (``OUT/trajectory.tum``: body/IMU
poses ``T_WI``; ``OUT/joint_angles.csv``: radians; ``OUT/summary.json``: the mode), aligns the
estimate to the ground truth exactly as the evaluation does (:func:`dcc_fg.vio.evaluate.align_trajectory`:
SE(3), or Sim(3) for monocular runs) and draws, in the ground truth's world frame W:

* ``OUT/vio_trajectory.png``: top view (x-y, metres) of the aligned estimate and the ground truth;
* ``OUT/vio_joint_angles.png``: joint angles (degrees) over time (seconds since the first keyframe),
  only when the folder has joint angles (dcc / scc runs), with the ground truth's if it has any;
* ``OUT/vio_error.png``: translation error (m) over the distance travelled along the ground truth (m).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from dcc_fg.io.outputs import read_joint_angles_csv
from dcc_fg.io.tum import read_tum
from dcc_fg.plots.common import save_figure
from dcc_fg.plots.vio import error_over_distance_figure, joint_angles_figure, trajectory_topview_figure
from dcc_fg.vio.evaluate import (
    NS,
    GroundTruth,
    align_trajectory,
    joint_rmse,
    load_ground_truth,
    output_mode_and_alignment,
)

FIGURE_PREFIX = "vio_"
ALIGNMENT_NAMES = {"se3": "SE(3)-aligned", "sim3": "Sim(3)-aligned", "none": "not aligned"}


@dataclass(frozen=True)
class VioFigures:
    """The figures drawn for one output folder (keys ``trajectory``, ``joint_angles``, ``error``; no
    ``joint_angles`` for runs without joints) and the PNG each was saved to."""

    figures: dict[str, Figure]
    paths: dict[str, Path]


def vio_output_figures(
    out_dir: str | Path, ground_truth: str | Path | GroundTruth, align: str = "auto", max_diff: float = 0.01
) -> dict[str, Figure]:
    """Build the figures of a VIO output folder (see module docstring) without saving them.

    ``ground_truth`` is a TUM file, a bag (see :func:`dcc_fg.vio.evaluate.load_ground_truth`) or a
    loaded :class:`GroundTruth`; ``align`` as in :func:`dcc_fg.vio.evaluate.evaluate_output`.
    """
    out_dir = Path(out_dir)
    mode, align = output_mode_and_alignment(out_dir, align)
    gt = ground_truth if isinstance(ground_truth, GroundTruth) else load_ground_truth(ground_truth)
    t_ns, T = read_tum(out_dir / "trajectory.tum")
    aligned = align_trajectory(t_ns, T, gt, align, max_diff)
    ape_rmse = float(np.sqrt(np.mean(np.sum((aligned.p_est - aligned.p_gt) ** 2, axis=1))))
    scale = f" with scale {aligned.scale:.3f}" if align == "sim3" else ""
    name = f"{mode or 'estimate'}, {ALIGNMENT_NAMES[align]}{scale}, APE RMSE {ape_rmse:.3g} m"
    figures = {
        "trajectory": trajectory_topview_figure(
            aligned.p_gt, {name: aligned.p_est}, title=f"Trajectory, top view of the world frame ({mode or 'VIO'})"
        ),
    }
    joints_csv = out_dir / "joint_angles.csv"
    if joints_csv.is_file():
        jt_ns, theta = read_joint_angles_csv(joints_csv)
        if theta.size:
            t0 = int(t_ns[0])
            t_est = (jt_ns - t0) / NS
            if gt.joints is not None and gt.joint_t_ns is not None:
                inside = (gt.joint_t_ns >= jt_ns[0]) & (gt.joint_t_ns <= jt_ns[-1])
                fig = joint_angles_figure(
                    (gt.joint_t_ns[inside] - t0) / NS, gt.joints[inside], {mode or "estimate": (t_est, theta)}
                )
                for ax, rmse in zip(fig.axes, joint_rmse(jt_ns, theta, gt) or [], strict=False):
                    ax.text(
                        0.01,
                        0.04,
                        f"RMSE {rmse:.2g} rad ({np.degrees(rmse):.2g} deg)",
                        transform=ax.transAxes,
                        fontsize=8,
                        bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none"},
                    )
            else:
                fig = joint_angles_figure(t_est, None, {mode or "estimate": theta})
            fig.axes[-1].set_xlabel("time since the first keyframe (s)")
            figures["joint_angles"] = fig
    figures["error"] = error_over_distance_figure(aligned.p_gt, {name: aligned.p_est})
    return figures


def write_vio_figures(
    out_dir: str | Path,
    ground_truth: str | Path | GroundTruth,
    align: str = "auto",
    figure_dir: str | Path | None = None,
) -> VioFigures:
    """Build the figures of :func:`vio_output_figures` and save each atomically as
    ``<figure_dir or out_dir>/vio_<name>.png``."""
    figures = vio_output_figures(out_dir, ground_truth, align)
    folder = Path(figure_dir) if figure_dir is not None else Path(out_dir)
    paths = {key: save_figure(fig, folder / f"{FIGURE_PREFIX}{key}.png") for key, fig in figures.items()}
    return VioFigures(figures, paths)
