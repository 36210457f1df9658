"""k-shot personalisation of new people: unpersonalised vs Bayesian fold-in (four ways of
choosing the questions) vs full retraining, with the calibration of the predictive intervals.

    python -m offline_training.kshot --config config/socnav1_gat.yaml \
        --data-root ../shared/datasets/socnav1 --out results/kshot-socnav1-bayes [--quick] [--allow-dirty]

A run starts from a commit: with uncommitted changes to tracked files outside ``--out`` it is
refused (``--allow-dirty`` runs anyway, ``--quick`` always may); results.json records the
commit, whether the tree was dirty and the device every fit ran on.

Leave-people-out folds (people shuffled with each of ``--seeds`` and dealt into ``--folds``
groups). Per fold a model is trained by the one recipe (``stars_ros.personalisation.recipe``) on the
other people's examples, less half of a seeded ``--known-test`` share of them, which checks
the known people's calibration. With ``--select SETTING=V1,V2`` (repeatable) the fold's training settings are
chosen first, inside its training people: each combination is fitted on their examples less a
seeded 20 % and scored on those, and the lowest MSE is the fold's (recorded per fold). For every held-out
person ``stars_ros.evaluation.kshot`` sets aside a seeded pool of ``--pool`` examples (one
person's ratings of one scene, every action; fewer for a person with fewer examples, who then
covers only the k it allows, and a person with one example is left out and counted); their
other examples are the test rows, the same for every k and strategy. Per k each fold's
covered people are scored:

- ``unpersonalised``: the scene-only model (p_u = 0, b_u = 0);
- ``fold-in (<strategy>)``: the node's default, the posterior (``FoldIn.posterior``) from the first k
  answers the strategy asked for (``random``: the mean over every set of k pool examples, the
  exact expectation over a random draw, or over ``--random-sets`` seeded sets where there are
  more than ``evaluation.kshot.EXACT_SETS``; ``uncertainty``: largest predictive variance; ``active``:
  the A-optimal expected variance reduction over the pool; ``decision``: the largest expected
  gain in the choices made on the pool, ``Uncertainty.log_decision_value``).
  k = 0 is the population prior's mean, what the node serves a stranger;
- ``ridge λ=<--ridge-lambda> (random)``: the ridge solve the node did before the posterior;
- ``retrained``: the whole model trained again on the fold's rows plus the first k random
  answers of each held-out person (k = 0 is the fold's model), at every k or those of
  ``--retrain-ks``.

Metrics (MSE, r, CCC on the rating scale, scores clipped as served) are pooled over a fold's
covered test rows, then given as mean ± sd over folds. Calibration: the share of test ratings
inside the central 50/80/90/95 % predictive intervals (Student-t with each fold's ν), for new
people at each k (random order) and for known people (their held-out examples, each scored
from their trained row and its covariance), pooled over folds. Goals: each strategy at or below
unpersonalised in every fold at every k ≥ 1, the node's strategy against random, coverage
within ±3 points. Writes results.json, results.md and kshot.png. Fits run
in worker processes with ``--jobs`` (one torch thread each) or as Ray tasks (``--executor
ray``); a fold any of whose fits fails is left out and named, and the run ends with status 1.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
from threadpoolctl import threadpool_limits

from stars_ros.errors import StarsError
from stars_ros.evaluation.kshot import STRATEGIES
from stars_ros.evaluation.provenance import program_argv, refuse_uncommitted, run_record
from stars_ros.evaluation.kshot_report import write_results
from stars_ros.evaluation.kshot_run import SELECTABLE, KShotSettings, retrained_ks, run
from stars_ros.model.config import ExperimentConfig

from .common import DEFAULT_SOCNAV1, add_executor_options, build_executor, read_inputs, setup_logging

QUICK = {'folds': 2, 'ks': [0, 1, 2, 5], 'epochs': [1, 2], 'max_train_rows': 1500,
         'experiment': {'encoder': {'hidden': 16, 'layers': 1}, 'model': {'dim': 16},
                        'training': {'lr': 3e-3}}}


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--config', required=True, help='experiment YAML (see config/)')
    parser.add_argument('--data-root', default=str(DEFAULT_SOCNAV1), help='SocNav1 root (default: %(default)s)')
    parser.add_argument('--out', required=True, help='results folder')
    parser.add_argument('--folds', type=int, default=4, help='annotator folds (default: %(default)s)')
    parser.add_argument('--seeds', type=int, nargs='+', default=[0],
                        help='seeds of folds and revealed pools, one partition of the annotators each (default: 0)')
    parser.add_argument('--pool', type=int, default=20,
                        help='revealable examples per held-out person (default: %(default)s)')
    parser.add_argument('--ks', type=int, nargs='+', default=[0, 1, 2, 3, 5, 10, 20],
                        help='answered questions (examples) (default: %(default)s)')
    parser.add_argument('--strategies', nargs='+', choices=STRATEGIES, default=['random'],
                        help='how questions are chosen (default: random; the first one listed is the one retrained)')
    parser.add_argument('--retrain-ks', type=int, nargs='+',
                        help='the ks at which the model is also retrained (default: every k; 0 is always fitted)')
    parser.add_argument('--known-test', type=float, default=0.2,
                        help="share of the training people's examples held out for their calibration "
                             '(default: %(default)s)')
    parser.add_argument('--random-sets', type=int, default=64,
                        help='seeded sets of k pool examples that random answers are averaged over where there are '
                             'too many to take every one (default: %(default)s)')
    parser.add_argument('--select', action='append', default=[], metavar='SETTING=V1,V2',
                        help='choose a training setting per fold among these values, inside the fold\'s training '
                             f'people (repeatable; settings: {", ".join(SELECTABLE)}); default: the config\'s')
    parser.add_argument('--ridge-lambda', type=float, default=1.0,
                        help='λ of the ridge fold-in shown beside the posterior (default: %(default)s, the node\'s '
                             'former default)')
    parser.add_argument('--epochs', type=int, nargs=2, metavar=('T1', 'T2'), help='override the config epochs')
    parser.add_argument('--max-train-rows', type=int, help='subsample each fold\'s training rows (seeded)')
    parser.add_argument('--device', help="train on this device ('cpu', 'cuda'; default: the config's)")
    parser.add_argument('--quick', action='store_true',
                        help='pipeline check: 2 folds, k in {0,2,5}, tiny model and epochs, 1,500 training rows')
    parser.add_argument('--allow-dirty', action='store_true',
                        help='run although tracked files outside --out have uncommitted changes (results.json says '
                             'dirty; without this such a run is refused; --quick always may)')
    parser.add_argument('--verbose', action='store_true')
    add_executor_options(parser)
    return parser.parse_args(argv)


def configure(args) -> ExperimentConfig:
    config = ExperimentConfig.from_yaml(args.config)
    if args.quick:
        config = config.replace(**QUICK['experiment'])
        args.folds, args.ks = QUICK['folds'], QUICK['ks']
        args.epochs = args.epochs or QUICK['epochs']
        args.max_train_rows = args.max_train_rows or QUICK['max_train_rows']
    training = {'threads': 1, **({'device': args.device} if args.device else {})}
    if args.epochs:
        training.update(pretrain_epochs=args.epochs[0], joint_epochs=args.epochs[1])
    if min(args.ks) < 0 or max(args.ks) > args.pool or args.folds < 2 or not 0 <= args.known_test < 1 \
            or args.random_sets < 1:
        raise StarsError(f'ks must lie in 0..{args.pool}, folds must be at least 2, --known-test in [0, 1) and '
                         '--random-sets at least 1')
    parse_select(args.select)  # refused here, before the data loads
    refuse_uncommitted(Path(args.out), args.quick or args.allow_dirty)
    return config.replace(training=training)


def parse_select(options: list) -> tuple:
    """``--select`` options as KShotSettings.select: ((setting, (values...)), ...)."""
    chosen = []
    for option in options:
        name, _, values = option.partition('=')
        if name not in SELECTABLE or not values:
            raise StarsError(f"--select takes SETTING=V1,V2 with a setting of {list(SELECTABLE)}, got '{option}'")
        kind = int if name.endswith('epochs') else float
        try:
            chosen.append((name, tuple(kind(v) for v in values.split(','))))
        except ValueError:
            raise StarsError(f"--select {name}: the values must be {kind.__name__}s, got '{values}'") from None
    return tuple(chosen)


def main(argv=None) -> int:
    args = parse_args(argv)
    setup_logging(args.verbose)
    torch.set_num_threads(1)
    threadpool_limits(1, user_api='blas')  # the fold-ins' small solves: extra BLAS threads only wait for each other
    inputs = read_inputs(lambda: configure(args), args.data_root)
    if inputs is None:
        return 2
    config, data = inputs
    try:
        fits = build_executor(args, data, devices=[config.training.device])
    except StarsError as error:
        print(f'error: {error}', file=sys.stderr)
        return 2
    folder = Path(args.out)
    folder.mkdir(parents=True, exist_ok=True)
    settings = KShotSettings(args.folds, tuple(args.seeds), args.pool, tuple(args.ks), tuple(args.strategies),
                             None if args.retrain_ks is None else tuple(args.retrain_ks), args.known_test,
                             args.ridge_lambda, args.max_train_rows, args.random_sets, parse_select(args.select))
    started = time.perf_counter()
    header = {**run_record(program_argv('offline_training.kshot', argv), config.training.device),
              'config': config.to_dict(), 'data': {'source': data.source, 'fingerprint': data.fingerprint},
              'pool': args.pool, 'ks': sorted(args.ks), 'seeds': args.seeds, 'jobs': fits.jobs,
              'strategies': args.strategies, 'known_test': args.known_test, 'ridge_lambda': args.ridge_lambda,
              'random_sets': args.random_sets, 'select': args.select,
              'retrain_ks': retrained_ks(settings),
              'executor': fits.settings, 'quick': args.quick,
              'max_train_rows': args.max_train_rows,
              'epochs': [config.training.pretrain_epochs, config.training.joint_epochs]}

    def on_fold(records, timings, folds, failed, left_out, calibration):  # partial results survive a stop
        write_results(folder, {'records': records, 'fits': timings, 'folds': folds, 'failed': failed,
                               'left_out': left_out, 'calibration': calibration},
                      {**header, 'seconds': time.perf_counter() - started, 'complete': False})
    try:
        result = run(settings, config, data, fits, log=lambda line: print(line, flush=True), on_fold=on_fold)
    except StarsError as error:
        print(f'error: {error}', file=sys.stderr)
        return 1
    write_results(folder, result, {**header, 'seconds': time.perf_counter() - started,
                                             'complete': not result['failed']})
    print((folder / 'results.md').read_text())
    if result['failed']:
        print('\n'.join([f"error: {len(result['failed'])} fit(s) failed, their folds are left out:",
                         *(f"  seed {f['seed']} fold {f['fold']} k={f['k']}: {f['error']}" for f in result['failed'])]),
              file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
