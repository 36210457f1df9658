"""Pieces the offline programs share: logging, inputs, progress lines, plots, the SocNav1 default path."""
import logging
import os
import platform
import sys
import time
from pathlib import Path

import torch

from stars_ros.data import load_dataset
from stars_ros.errors import StarsError

DEFAULT_SOCNAV1 = Path(os.environ.get('STARS_SOCNAV1_ROOT',
                                      Path(__file__).resolve().parents[1].parent / 'shared' / 'datasets' / 'socnav1'))


def setup_logging(verbose: bool) -> None:
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING,
                        format='%(asctime)s %(name)s %(levelname)s: %(message)s', stream=sys.stderr)


def machine() -> dict:
    """What the figures were measured on."""
    return {'platform': platform.platform(), 'python': platform.python_version(),
            'torch': str(torch.__version__), 'cpus': os.cpu_count(),
            'processor': platform.processor() or platform.machine()}


def cuda_info(device: str) -> dict:
    """The GPU behind a training ``device`` ({} for the CPU). It initialises CUDA in this
    process, so the evaluation asks only once its worker processes are done."""
    if not device.startswith('cuda') or not torch.cuda.is_available():
        return {}
    return {'cuda_device': torch.cuda.get_device_name(device), 'cuda_version': torch.version.cuda}


def format_metrics(metrics: dict) -> str:
    return (f"MSE {metrics['mse']:.4f}  RMSE {metrics['rmse']:.4f}  "
            f"Pearson r {metrics['pearson_r']:.4f}  CCC {metrics['ccc']:.4f}  (n={metrics['n']})")


class Progress:
    """``on_epoch`` callback of ``StarsRecommender.fit`` that prints one line per epoch to
    ``stream``: stage, epoch, training loss, seconds per epoch and the time left."""

    def __init__(self, recommender, pretrain_epochs: int, joint_epochs: int, stream=None):
        self.recommender, self.stream = recommender, stream or sys.stderr
        self.total = {'pretrain': pretrain_epochs, 'joint': joint_epochs}
        self.left = pretrain_epochs + joint_epochs
        self.started = self.last = time.perf_counter()

    def __call__(self, stage: str, epoch: int) -> None:
        now = time.perf_counter()
        self.left -= 1
        per_epoch = (now - self.started) / (sum(self.total.values()) - self.left)
        loss = self.recommender.history[stage][-1]
        print(f'{stage} epoch {epoch}/{self.total[stage]}: loss {loss:.4f}, {now - self.last:.2f} s, '
              f'about {per_epoch * self.left:.0f} s left', file=self.stream, flush=True)
        self.last = now


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


def read_inputs(read_config, data_root):
    """(config, data): the config first, so a bad one is refused before the data loads; None
    after printing the error (the caller exits with status 2)."""
    try:
        config = read_config()
        return config, load_dataset(data_root)
    except (StarsError, OSError) as error:
        print(f'error: {error}', file=sys.stderr)
        return None
