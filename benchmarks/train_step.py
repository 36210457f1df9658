"""Milliseconds per training batch of one backbone on each device, one torch thread.

    PYTHONPATH=. python benchmarks/train_step.py [--devices cuda,cpu] [--backbone gat] [--batches 20]

Times ``StarsTrainer.fit`` for one joint epoch of ``--batches`` batches with the
published grid's model settings (config/eval_socnav1.yaml), after an untimed warm-up fit
(CUDA start-up, kernel choice). ``fit`` reads each loss back per batch, so the wall time
includes the GPU's work. Tells whether a GPU pays for these small graphs before a long run.
"""
import argparse
import time
from pathlib import Path

import numpy as np

from offline_training.common import DEFAULT_SOCNAV1
from stars_ros.data.ratings import load_dataset
from stars_ros.evaluation.protocol import ProtocolConfig
from stars_ros.model.training import StarsTrainer


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--data-root', default=str(DEFAULT_SOCNAV1))
    parser.add_argument('--config', default=str(Path(__file__).resolve().parents[1] / 'config' / 'eval_socnav1.yaml'))
    parser.add_argument('--backbone', default='gat')
    parser.add_argument('--variant', default='stars', choices=['base', 'stars'])
    parser.add_argument('--devices', default='cuda,cpu', help='comma-separated, timed in this order')
    parser.add_argument('--batches', type=int, default=20)
    args = parser.parse_args()
    protocol = ProtocolConfig.from_yaml(args.config)  # a bad config fails before the data loads
    base = protocol.experiment_config(args.backbone, args.variant)
    data = load_dataset(args.data_root)
    rows = np.random.default_rng(0).permutation(len(data))
    size = base.training.batch_size
    for device in args.devices.split(','):
        config = base.replace(training={'pretrain_epochs': 0, 'joint_epochs': 1, 'threads': 1, 'device': device})
        StarsTrainer(config).fit(data, rows[:2 * size])  # warm-up
        started = time.perf_counter()
        StarsTrainer(config).fit(data, rows[:args.batches * size])
        seconds = time.perf_counter() - started
        print(f'{args.backbone} {args.variant} on {device}: {1000 * seconds / args.batches:.1f} ms per batch '
              f'({args.batches} batches of {size}, 1 thread)', flush=True)


if __name__ == '__main__':
    main()
