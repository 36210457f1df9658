"""Pieces the offline programs share: logging, inputs, where fits run, progress lines, the
SocNav1 default path. (Plots: ``stars_ros.evaluation.plots``.)"""
import argparse
import concurrent.futures as futures
import logging
import sys
import time
from collections.abc import Iterable
from typing import NamedTuple

import torch

from stars_ros.data.ratings import RatingData, load_dataset
from stars_ros.data.scene_source import socnav1_root
from stars_ros.errors import StarsError
from stars_ros.evaluation.executors import fit_executor

DEFAULT_SOCNAV1 = socnav1_root()


def setup_logging(verbose: bool) -> None:
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING,
                        format='%(asctime)s %(name)s %(levelname)s: %(message)s', stream=sys.stderr)


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
    """``on_epoch`` callback of ``StarsTrainer.fit`` that prints one line per epoch to
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


def read_inputs(read_config, data_root):
    """(config, data): the config first, so a bad one is refused before the data loads; None
    after printing the error (the caller exits with status 2)."""
    try:
        config = read_config()
        return config, load_dataset(data_root)
    except (StarsError, OSError) as error:
        print(f'error: {error}', file=sys.stderr)
        return None


#: Options that only mean something to the Ray executor: argparse dest -> flag.
RAY_OPTIONS = {'ray_address': '--ray-address', 'cpus_per_fit': '--cpus-per-fit', 'gpus_per_fit': '--gpus-per-fit',
               'max_retries': '--max-retries'}
DEFAULT_MAX_RETRIES = 3


def add_executor_options(parser: argparse.ArgumentParser) -> None:
    """The options that say where the fits run: local worker processes, or Ray tasks."""
    group = parser.add_argument_group('where the fits run')
    group.add_argument('--executor', choices=('process', 'ray'), default='process',
                       help='process: worker processes on this machine (default); ray: Ray tasks on a local Ray '
                            'instance or a cluster (pip install -r requirements-ray.txt; docs/distributed.md)')
    group.add_argument('--jobs', type=int, help='fits in flight at once (default: 1 with process, one worker '
                                                'process each; with ray, as many as the cluster runs at once)')
    group.add_argument('--ray-address', help='Ray cluster to use, e.g. 10.0.0.5:6379 (default: RAY_ADDRESS, else '
                                             'a cluster started here with `ray start`, else a new local instance)')
    group.add_argument('--cpus-per-fit', type=float, help='CPUs Ray reserves for each fit (default: 1)')
    group.add_argument('--gpus-per-fit', type=float,
                       help='GPUs Ray reserves for each fit, a fraction to share one: 0.1 runs ten fits on a GPU '
                            '(default: 0; fits on the GPU need it, with --device cuda)')
    group.add_argument('--max-retries', type=int,
                       help=f'times Ray runs a fit again whose worker died (default: {DEFAULT_MAX_RETRIES})')


class FitExecutor(NamedTuple):
    """Where the fits run: the executor, how many fits are in flight at once, and the
    choice as a results folder records it (``kind`` and, for Ray, the cluster and the
    per-fit resources)."""

    executor: futures.Executor
    jobs: int
    settings: dict


def build_executor(args: argparse.Namespace, data: RatingData, threads: int = 1,
                   devices: Iterable[str] = ('cpu',)) -> FitExecutor:
    """The executor that ``add_executor_options``' options ask for, for fits of ``data`` on
    ``devices`` with ``threads`` torch threads each; raises StarsError for a contradiction."""
    given = [flag for name, flag in RAY_OPTIONS.items() if getattr(args, name) is not None]
    if args.jobs is not None and args.jobs < 1:
        raise StarsError('--jobs must be positive')
    if args.executor == 'process':
        if given:
            raise StarsError(f"{', '.join(given)} go with --executor ray")
        jobs = args.jobs or 1
        return FitExecutor(fit_executor(data, jobs, threads), jobs, {'kind': 'process'})
    cpus = 1.0 if args.cpus_per_fit is None else args.cpus_per_fit
    gpus = args.gpus_per_fit or 0.0
    for device in set(devices):
        if device.startswith('cuda') and device != 'cuda':
            raise StarsError(f"--executor ray gives each fit its GPU: train on 'cuda', not '{device}'")
        if device == 'cuda' and not gpus:
            raise StarsError('fits on the GPU need --gpus-per-fit with --executor ray (e.g. 0.1: ten share a GPU)')
    if gpus and 'cuda' not in set(devices):
        raise StarsError('--gpus-per-fit reserves GPUs for fits that train on the CPU: give --device cuda')
    from stars_ros.evaluation.ray_executor import RayExecutor  # imports Ray: only here
    retries = DEFAULT_MAX_RETRIES if args.max_retries is None else args.max_retries
    try:
        executor = RayExecutor(data, args.ray_address, cpus, gpus, threads, retries)
    except ValueError as error:
        raise StarsError(str(error)) from None
    jobs = args.jobs or executor.capacity()
    if jobs < 1:
        executor.shutdown()
        raise StarsError(f'the Ray cluster has no node with {cpus:g} CPUs and {gpus:g} GPUs free for a fit')
    return FitExecutor(executor, jobs, {'kind': 'ray', 'address': executor.address, 'cpus_per_fit': cpus,
                                        'gpus_per_fit': gpus, 'max_retries': retries})
