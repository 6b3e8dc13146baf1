"""Multi-page PDF report (matplotlib PdfPages): text summary pages, then figures, written atomically."""

from __future__ import annotations

import os
import tempfile
import textwrap
from collections.abc import Iterable
from pathlib import Path

from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure

from dcc_fg.plots.common import new_figure

LINES_PER_PAGE = 80
CHARS_PER_LINE = 112  # 7.5 pt monospace across an A4 page with 5% margins


def text_page(text: str, title: str = "") -> list[Figure]:
    """Portrait A4 pages of monospaced ``text``: long lines wrapped, split every LINES_PER_PAGE lines."""
    lines = [
        wrapped
        for line in (text.splitlines() or [""])
        for wrapped in (textwrap.wrap(line, CHARS_PER_LINE, subsequent_indent="    ") or [""])
    ]
    pages = []
    for start in range(0, len(lines), LINES_PER_PAGE):
        fig = new_figure(8.27, 11.69)
        fig.set_layout_engine("none")
        if title:
            fig.text(0.05, 0.97, title, fontsize=13, fontweight="bold", va="top")
        fig.text(
            0.05, 0.93, "\n".join(lines[start : start + LINES_PER_PAGE]), family="monospace", fontsize=7.5, va="top"
        )
        pages.append(fig)
    return pages


def write_report_pdf(path: str | Path, summary: str, figures: Iterable[Figure], title: str = "dcc-fg report") -> int:
    """Write ``summary`` (text pages) then every figure to the PDF ``path`` atomically; returns the page count."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".pdf", dir=path.parent)
    os.close(fd)
    try:
        with PdfPages(tmp) as pdf:
            for fig in [*text_page(summary, title), *figures]:
                pdf.savefig(fig)
            n = pdf.get_pagecount()
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return n
