"""Write a calibration's figures (PNG) and its PDF report next to the other outputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from dcc_fg.calibrate import CalibrationResult
from dcc_fg.data import CalibrationDataset
from dcc_fg.model import GimbalCalibration
from dcc_fg.plots.calibration import calibration_figures
from dcc_fg.plots.common import save_figure
from dcc_fg.plots.pdf import write_report_pdf
from dcc_fg.plots.residual_map import residual_grids, residual_map_summary

FIGURE_PREFIX = "calibration_"


def write_calibration_outputs(
    out: Path,
    result: CalibrationResult,
    summary_text: str | None = None,
    truth: GimbalCalibration | None = None,
    thetas_true: NDArray[np.float64] | None = None,
    target_points: NDArray[np.float64] | None = None,
    pdf_name: str | None = "report.pdf",
    data: CalibrationDataset | None = None,
) -> list[Path]:
    """Save every calibration figure as ``out/calibration_<name>.png`` and, if ``summary_text`` and
    ``pdf_name`` are given, ``out/<pdf_name>`` (summary page(s), then the figures). All atomic.

    With ``data`` (the dataset ``result`` was computed from) the figures include the per-camera residual
    heat map over the image (``calibration_residual_map.png``) and the summary text gets its lines (worst
    cell per camera, :func:`dcc_fg.plots.residual_map.residual_map_summary`); ``target_points`` then
    defaults to the dataset's.

    Returns the written paths (PNGs first, then the PDF).
    """
    if data is not None and target_points is None:
        target_points = data.target_points
    figs = calibration_figures(result, truth, thetas_true, target_points=target_points, data=data)
    if data is not None and summary_text is not None:
        summary_text = summary_text.rstrip("\n") + "\n\n" + residual_map_summary(residual_grids(result, data))
    paths = [save_figure(fig, out / f"{FIGURE_PREFIX}{name}.png") for name, fig in figs.items()]
    if summary_text is not None and pdf_name:
        write_report_pdf(out / pdf_name, summary_text, figs.values(), title="dcc-fg calibration report")
        paths.append(out / pdf_name)
    return paths
