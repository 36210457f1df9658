"""Base vs StARS (and mf) on one fixed, seeded 80/20 row split, with seconds per epoch.

    python -m offline_training.holdout --data-root ../shared/datasets/socnav1 \
        --backbones gat gcn --variants base stars --out results/holdout_socnav1

Each backbone's config is ``config/socnav1_<backbone>.yaml`` (``--config-pattern``);
runs go to ``--jobs`` worker processes with one torch thread each. Writes
``results.json`` (every figure, the command, the machine, wall time) and ``results.md``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from stars_ros import StarsRecommender
from stars_ros.data.ratings import load_dataset
from stars_ros.evaluation.provenance import program_argv, run_record
from stars_ros.model.config import ExperimentConfig
from stars_ros.model.training import split_rows

from .common import DEFAULT_SOCNAV1

_data = {}


def _run(job):
    data_root, config_dict = job
    if data_root not in _data:
        _data[data_root] = load_dataset(data_root)
    data = _data[data_root]
    config = ExperimentConfig.from_dict(config_dict)
    train, test = split_rows(data, config.split.test_fraction, config.split.seed)
    started = time.perf_counter()
    recommender = StarsRecommender(config).fit(data, train)
    seconds = time.perf_counter() - started
    epochs = config.training.pretrain_epochs + config.training.joint_epochs
    return {'backbone': config.encoder.name, 'variant': config.model.variant,
            'metrics': recommender.test(data, test), 'train_seconds': seconds,
            'seconds_per_epoch': seconds / max(epochs, 1), 'epochs': epochs,
            'final_train_loss': recommender.history['joint'][-1], 'config': config.to_dict()}


def markdown(rows) -> str:
    lines = ['| model | MSE | RMSE | Pearson r | CCC | s/epoch |', '| --- | --- | --- | --- | --- | --- |']
    for row in rows:
        m = row['metrics']
        lines.append(f"| {row['backbone']}-{row['variant']} | {m['mse']:.4f} | {m['rmse']:.4f} | "
                      f"{m['pearson_r']:.4f} | {m['ccc']:.4f} | {row['seconds_per_epoch']:.2f} |")
    return '\n'.join(lines) + '\n'


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--data-root', default=str(DEFAULT_SOCNAV1))
    parser.add_argument('--backbones', nargs='+', default=['gcn', 'gin', 'graphsage', 'ggnn', 'rgcn', 'gat'])
    parser.add_argument('--variants', nargs='+', default=['base', 'stars'], choices=['base', 'stars', 'mf'])
    parser.add_argument('--config-pattern', default='config/socnav1_{backbone}.yaml')
    parser.add_argument('--epochs', type=int, nargs=2, metavar=('T1', 'T2'), help='override the configs')
    parser.add_argument('--jobs', type=int, default=2)
    parser.add_argument('--out', required=True, help='results folder')
    args = parser.parse_args(argv)

    jobs = []
    for backbone in args.backbones:
        config = ExperimentConfig.from_yaml(args.config_pattern.format(backbone=backbone))
        training = {'threads': 1}
        if args.epochs:
            training.update(pretrain_epochs=args.epochs[0], joint_epochs=args.epochs[1])
        for variant in args.variants:
            jobs.append((args.data_root, config.replace(model={'variant': variant}, training=training).to_dict()))
    started = time.perf_counter()
    with ProcessPoolExecutor(args.jobs) as pool:
        rows = []
        for row in pool.map(_run, jobs):
            rows.append(row)
            print(f"{row['backbone']}-{row['variant']}: MSE {row['metrics']['mse']:.4f} "
                  f"r {row['metrics']['pearson_r']:.4f} CCC {row['metrics']['ccc']:.4f} "
                  f"({row['seconds_per_epoch']:.2f} s/epoch)", flush=True)
    wall = time.perf_counter() - started
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    record = run_record(program_argv('offline_training.holdout', argv))
    (out / 'results.json').write_text(json.dumps(
        {**record, 'wall_seconds': wall, 'jobs': args.jobs, 'runs': rows}, indent=2) + '\n')
    table = markdown(rows)
    (out / 'results.md').write_text(
        f'# Fixed 80/20 row split\n\nCommand: `{record["command"]}`\n\nWall time {wall / 60:.1f} min with {args.jobs} '
        f'worker processes (1 torch thread each; s/epoch measured with both workers busy).\n\n{table}')
    print(table)
    return 0


if __name__ == '__main__':
    sys.exit(main())
