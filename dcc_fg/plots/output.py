"""Write a calibration's figures (PNG) and its PDF report next to the other outputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from dcc_fg.calibrate import CalibrationResult
from dcc_fg.model import GimbalCalibration
from dcc_fg.plots.calibration import calibration_figures
from dcc_fg.plots.common import save_figure
from dcc_fg.plots.pdf import write_report_pdf

FIGURE_PREFIX = "calibration_"


def write_calibration_outputs(
    out: Path,
    result: CalibrationResult,
    summary_text: str | None = None,
    truth: GimbalCalibration | None = None,
    thetas_true: NDArray[np.float64] | None = None,
    target_points: NDArray[np.float64] | None = None,
    pdf_name: str | None = "report.pdf",
) -> list[Path]:
    """Save every calibration figure as ``out/calibration_<name>.png`` and, if ``summary_text`` and
    ``pdf_name`` are given, ``out/<pdf_name>`` (summary page(s), then the figures). All atomic.

    Returns the written paths (PNGs first, then the PDF).
    """
    figs = calibration_figures(result, truth, thetas_true, target_points=target_points)
    paths = [save_figure(fig, out / f"{FIGURE_PREFIX}{name}.png") for name, fig in figs.items()]
    if summary_text is not None and pdf_name:
        write_report_pdf(out / pdf_name, summary_text, figs.values(), title="dcc-fg calibration report")
        paths.append(out / pdf_name)
    return paths
