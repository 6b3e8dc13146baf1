"""Figures of a VIO output folder against ground truth, saved next to the outputs (``dcc-fg evaluate``).

Reads what :func:`dcc_fg.vio.backend.write_vio_outputs` writes (``OUT/trajectory.tum``: body/IMU
poses ``T_WI``; ``OUT/joint_angles.csv``: radians; ``OUT/summary.json``: the mode), aligns the
estimate to the ground truth exactly as the evaluation does (:func:`dcc_fg.vio.evaluate.align_trajectory`:
SE(3), or Sim(3) for monocular runs) and draws, in the ground truth's world frame W:

* ``OUT/vio_trajectory.png``: top view (x-y, metres) of the aligned estimate and the ground truth;
* ``OUT/vio_joint_angles.png``: joint angles (degrees) over time (seconds since the first keyframe),
  only when the folder has joint angles (dcc / scc runs), with the ground truth's if it has any, and a
  shaded ±1-sigma band per joint where ``OUT/joint_angles_sigma.csv`` (:mod:`dcc_fg.plots.joint_band`)
  gives the keyframe's sigma;
* ``OUT/vio_joint_errors.png``: with joint sigmas *and* ground-truth joint angles, the error against the
  interpolated truth (degrees) with the ±1-sigma band around zero and the fraction inside it;
* ``OUT/vio_error.png``: translation error (m) over the distance travelled along the ground truth (m).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from numpy.typing import NDArray

from dcc_fg.io.outputs import read_joint_angles_csv
from dcc_fg.io.tum import read_tum
from dcc_fg.plots.common import save_figure
from dcc_fg.plots.joint_band import SIGMA_FILE, joint_error_band_figure, read_joint_sigmas_csv, sigmas_at
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
    ``joint_angles`` for runs without joints; ``joint_errors`` for runs with joint sigmas and
    ground-truth joint angles) and the PNG each was saved to."""

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
    joint_error_fig: Figure | None = None
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
            est_name = mode or "estimate"
            sigma = joint_sigmas(out_dir, jt_ns, theta.shape[1])
            sigmas = {est_name: sigma} if sigma is not None else None
            if gt.joints is not None and gt.joint_t_ns is not None:
                inside = (gt.joint_t_ns >= jt_ns[0]) & (gt.joint_t_ns <= jt_ns[-1])
                fig = joint_angles_figure(
                    (gt.joint_t_ns[inside] - t0) / NS, gt.joints[inside], {est_name: (t_est, theta)}, sigmas
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
                if sigma is not None:
                    err = theta - truth_at(jt_ns, gt.joint_t_ns, gt.joints)
                    err_fig = joint_error_band_figure(t_est, err, sigma, est_name)
                    err_fig.axes[-1].set_xlabel("time since the first keyframe (s)")
                    joint_error_fig = err_fig
            else:
                fig = joint_angles_figure(t_est, None, {est_name: theta}, sigmas)
            fig.axes[-1].set_xlabel("time since the first keyframe (s)")
            figures["joint_angles"] = fig
    figures["error"] = error_over_distance_figure(aligned.p_gt, {name: aligned.p_est})
    if joint_error_fig is not None:
        figures["joint_errors"] = joint_error_fig
    return figures


def joint_sigmas(out_dir: Path, stamps_ns: NDArray[np.int64], n_joints: int) -> NDArray[np.float64] | None:
    """(N, L) per-keyframe joint-angle 1-sigma (rad, NaN where not reported) of the keyframes
    ``stamps_ns`` from ``OUT/joint_angles_sigma.csv``, or None when the run wrote no such file (today's
    ``dcc-fg vio`` does not: its result carries no joint-angle marginals)."""
    path = out_dir / SIGMA_FILE
    if not path.is_file():
        return None
    s_ns, sigma = read_joint_sigmas_csv(path)
    return sigmas_at(stamps_ns, s_ns, sigma, n_joints)


def truth_at(
    stamps_ns: NDArray[np.int64], gt_t_ns: NDArray[np.int64], gt_joints: NDArray[np.float64]
) -> NDArray[np.float64]:
    """(N, L) ground-truth joint angles (rad) linearly interpolated at ``stamps_ns``; NaN outside the
    ground truth's time span (no extrapolation)."""
    t = np.asarray(stamps_ns, np.int64)
    ref = np.asarray(gt_t_ns, np.int64)
    dt = (t - ref[0]).astype(float)
    dref = (ref - ref[0]).astype(float)  # relative to the first stamp: exact in float64 for epoch stamps
    out = np.column_stack([np.interp(dt, dref, gt_joints[:, j]) for j in range(gt_joints.shape[1])])
    out[(t < ref[0]) | (t > ref[-1])] = np.nan
    return out


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
