"""Pieces the offline programs share: logging set-up and the SocNav1 default path."""
import logging
import os
import platform
import sys
from pathlib import Path

import torch

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
