"""Figures of calibration and VIO results (matplotlib, headless-safe).

Every function builds a :class:`matplotlib.figure.Figure` without pyplot (no global state, no GUI,
works under the Agg backend) and returns it; callers save it (:func:`save_figure`) or display it.
"""

from dcc_fg.plots.calibration import (
    calibration_figures,
    coverage_figure,
    parameter_figure,
    residual_figure,
    snapshot_error_figure,
)
from dcc_fg.plots.chain3d import chain_figure, chain_frames
from dcc_fg.plots.common import save_figure
from dcc_fg.plots.joint_band import draw_sigma_band, joint_error_band_figure, read_joint_sigmas_csv
from dcc_fg.plots.output import write_calibration_outputs
from dcc_fg.plots.pdf import text_page, write_report_pdf
from dcc_fg.plots.residual_map import (
    ResidualGrid,
    bin_residuals,
    residual_grids,
    residual_map_figure,
    residual_map_summary,
)
from dcc_fg.plots.vio import (
    distance_travelled,
    error_over_distance_figure,
    joint_angles_figure,
    trajectory_topview_figure,
)
from dcc_fg.plots.vio_output import VioFigures, vio_output_figures, write_vio_figures

__all__ = [
    "calibration_figures",
    "chain_figure",
    "chain_frames",
    "coverage_figure",
    "bin_residuals",
    "distance_travelled",
    "draw_sigma_band",
    "error_over_distance_figure",
    "joint_angles_figure",
    "joint_error_band_figure",
    "parameter_figure",
    "read_joint_sigmas_csv",
    "residual_figure",
    "residual_grids",
    "residual_map_figure",
    "residual_map_summary",
    "ResidualGrid",
    "save_figure",
    "snapshot_error_figure",
    "text_page",
    "trajectory_topview_figure",
    "VioFigures",
    "vio_output_figures",
    "write_calibration_outputs",
    "write_report_pdf",
    "write_vio_figures",
]
