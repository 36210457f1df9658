"""Train a StARS (or base / mf) model and write a checkpoint.

    python -m offline_training.train --config config/socnav1_gat.yaml \
        --data-root ../shared/datasets/socnav1 --out model.pt [--variant base]

Trains on the config's seeded train split, prints held-out MSE, RMSE, Pearson r and CCC
(on the rating scale, macro-averaged over actions) next to the training-mean baseline,
and stores them in the checkpoint. ``--all-rows`` trains on every rating instead (for a
deployed model; no held-out figures then).
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from stars_ros import StarsRecommender
from stars_ros.errors import StarsError
from stars_ros.evaluation.provenance import program_argv, run_record
from stars_ros.model.config import ExperimentConfig
from stars_ros.model.metrics import regression_report
from stars_ros.model.training import split_rows

from .common import DEFAULT_SOCNAV1, Progress, cuda_info, format_metrics, read_inputs, setup_logging


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--config', required=True, help='experiment YAML (see config/)')
    parser.add_argument('--data-root', default=str(DEFAULT_SOCNAV1),
                        help='SocNav1 root or generic-format root (default: %(default)s)')
    parser.add_argument('--out', required=True, help='checkpoint file to write')
    parser.add_argument('--variant', choices=['base', 'stars', 'mf'], help='override model.variant')
    parser.add_argument('--epochs', type=int, nargs=2, metavar=('T1', 'T2'),
                        help='override pretrain and joint epochs')
    parser.add_argument('--seed', type=int, help='override training seed')
    parser.add_argument('--device', help="override training.device: 'cpu', 'cuda' or 'cuda:N'")
    parser.add_argument('--all-rows', action='store_true', help='train on every rating (no held-out test)')
    parser.add_argument('--quiet', action='store_true', help='no progress line per epoch (on stderr)')
    parser.add_argument('--verbose', action='store_true', help='log every epoch')
    return parser.parse_args(argv)


def configure(args) -> ExperimentConfig:
    config = ExperimentConfig.from_yaml(args.config)
    training = {}
    if args.epochs:
        training.update(pretrain_epochs=args.epochs[0], joint_epochs=args.epochs[1])
    if args.seed is not None:
        training['seed'] = args.seed
    if args.device:
        training['device'] = args.device
    return config.replace(training=training, **({'model': {'variant': args.variant}} if args.variant else {}))


def main(argv=None) -> int:
    args = parse_args(argv)
    setup_logging(args.verbose)
    inputs = read_inputs(lambda: configure(args), args.data_root)
    if inputs is None:
        return 2
    config, data = inputs
    for note in data.notes:
        print(f'note: {note}')
    if args.all_rows:
        train, test = np.arange(len(data)), np.zeros(0, dtype=np.int64)
    else:
        train, test = split_rows(data, config.split.test_fraction, config.split.seed)
    print(f'data: {data.source}: {len(data)} ratings, {len(set(data.users.tolist()))} users, '
          f'{len(data.scene_keys)} scenes, actions {list(data.action_names)}; train {len(train)}, test {len(test)}')
    label = f'{config.encoder.name}-{config.model.variant}'
    record = run_record(program_argv('offline_training.train', argv), config.training.device)
    started = time.perf_counter()
    recommender = StarsRecommender(config)
    pretrain = config.training.pretrain_epochs if 'content' in config.model.parts else 0
    try:  # the one recipe: every training rating, the prior's noise from a fit on less (personalisation.recipe)
        recommender.fit(data, train, on_epoch=None if args.quiet else
                        Progress(recommender, pretrain, config.training.joint_epochs))
    except StarsError as error:
        print(f'error: {error}', file=sys.stderr)
        return 1
    seconds = time.perf_counter() - started
    prior = recommender.fitted.user_prior
    if prior is not None:
        print(f"personalisation prior: {prior['details']}; noise variance (z-scale) per action "
              f"{[round(float(v), 4) for v in prior['noise']]}")
    epochs = config.training.pretrain_epochs + config.training.joint_epochs
    print(f'{label}: trained {epochs} epochs in {seconds:.1f} s ({seconds / max(epochs, 1):.2f} s/epoch)')
    metrics = {}
    if len(test):
        metrics = recommender.test(data, test)
        mean_baseline = regression_report(data.scores[test], np.full(len(test), data.scores[train].mean()),
                                          data.actions[test])
        print(f'{label} held-out: {format_metrics(metrics)}')
        print(f'training-mean baseline: MSE {mean_baseline["mse"]:.4f}')
    digest = recommender.save(
        args.out, data={'n_test': len(test), 'split': 'all rows' if args.all_rows else config.split.model_dump()},
        metrics=metrics,
        provenance={**record, 'train_seconds': round(seconds, 1),
                    'machine': {**record['machine'], **cuda_info(config.training.device)}})
    print(f'wrote {args.out} (digest {digest[:12]})')
    return 0


if __name__ == '__main__':
    sys.exit(main())
