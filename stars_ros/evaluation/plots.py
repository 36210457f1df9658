"""matplotlib helpers the evaluation reports draw with (file-only: no display needed)."""
from __future__ import annotations

from pathlib import Path


def pyplot():
    """matplotlib's pyplot on the file-only Agg backend (no display needed)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt


def mean_band(axis, x, means, sds, label: str, marker: str = 'o', alpha: float = 0.2) -> None:
    """A line of means with a ±sd band in the line's colour."""
    line, = axis.plot(x, means, marker=marker, label=label)
    axis.fill_between(x, means - sds, means + sds, alpha=alpha, color=line.get_color())


def label_axis(axis, xlabel: str, ylabel: str, legend_size: int | None = None) -> None:
    axis.set_xlabel(xlabel)
    axis.set_ylabel(ylabel)
    axis.grid(alpha=0.3)
    if legend_size:
        axis.legend(fontsize=legend_size)


def save_png(figure, path: Path) -> str:
    """Lay out, write and close ``figure``; returns the file's name."""
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    pyplot().close(figure)
    return path.name
