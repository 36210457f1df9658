"""k-shot personalisation on held-out annotators: unpersonalised vs fold-in vs retraining.

    python -m offline_training.kshot --config config/socnav1_gat.yaml \
        --data-root ../shared/datasets/socnav1 --out results/kshot_socnav1 [--quick]

Leave-annotators-out folds (annotators shuffled with each of ``--seeds`` and dealt into
``--folds`` groups; several seeds give several such partitions). Per fold a model is trained
on the other annotators. For every held-out annotator a
seeded pool of ``--pool`` ratings is set aside as "revealable", revealed in a fixed order;
the remaining ratings are the test rows, the same for every k, so the curves compare across
k. For each k the held-out annotators are scored three ways:

- ``unpersonalised``: p_u = 0, b_u = 0 (what the node does for a stranger);
- ``fold-in``: (p_u, b_u) solved in closed form (stars_ros.personalisation.foldin) from the first k revealed
  ratings, towards the population prior (the mean trained user row, as the node does);
- ``fold-in (zero prior)``: the same towards p_u = 0, b_u = 0, i.e. towards the
  unpersonalised model (equal to it at k = 0);
- ``retrained``: the whole model trained again from scratch on the fold's training rows plus
  the first k revealed ratings of each held-out annotator (k = 0 is the fold's model).

λ: one value per prior and seed, chosen on the seed's first fold's held-out annotators
using their revealable pools only (fold in from the first k of the pool, score the rest of
the pool; mean MSE over the k of ``--ks`` with 0 < k < pool); no test row takes part. (The
training annotators are no use for this: the model fitted their ratings, which favours a
tiny λ.) As a check, not used for any choice, the fold-in MSE of every λ of the grid on the
test rows is reported too.

Metrics (MSE, r, CCC on the rating scale) are pooled over the fold's held-out test rows,
then given as mean ± sd over folds (of all seeds). Writes results.json, results.md and
kshot.png. The fits are independent of each other: ``--jobs`` runs them in worker
processes (one torch thread each, sharing the GPU with ``--device cuda``), ``--executor ray``
as Ray tasks. A fold any of whose fits fails (raises, or its worker dies) is left out and
named with the error; the run then ends with status 1.
"""
from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch

from stars_ros.model.config import ExperimentConfig
from stars_ros.errors import StarsError
from stars_ros.evaluation.protocol import FitFailure, fit_outcome, worker_data
from stars_ros.evaluation.kshot import LAMBDA_GRID, PRIORS, Design, annotator_folds, choose_regularisation, reveal_pools
from stars_ros.model.metrics import regression_report
from stars_ros.evaluation.stats import mean_sd
from stars_ros.model.training import StarsTrainer

from .common import (DEFAULT_SOCNAV1, add_executor_options, build_executor, label_axis, machine, pyplot, read_inputs,
                     save_png, setup_logging)

METHODS = ('unpersonalised', 'fold-in', 'fold-in (zero prior)', 'retrained')
METRICS = ('mse', 'pearson_r', 'ccc')
NAMES = {'mse': 'MSE', 'pearson_r': 'Pearson r', 'ccc': 'CCC'}
QUICK = {'folds': 2, 'ks': [0, 2, 5], 'epochs': [1, 2], 'max_train_rows': 1500,
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
    parser.add_argument('--pool', type=int, default=20, help='revealable ratings per held-out annotator')
    parser.add_argument('--ks', type=int, nargs='+', default=[0, 1, 2, 5, 10, 20], help='revealed ratings')
    parser.add_argument('--epochs', type=int, nargs=2, metavar=('T1', 'T2'), help='override the config epochs')
    parser.add_argument('--regularisation', type=float, help='fold-in λ (default: chosen on fold 0, see above)')
    parser.add_argument('--max-train-rows', type=int, help='subsample each fold\'s training rows (seeded)')
    parser.add_argument('--device', help="train on this device ('cpu', 'cuda'; default: the config's)")
    parser.add_argument('--quick', action='store_true',
                        help='pipeline check: 2 folds, k in {0,2,5}, tiny model and epochs, 1,500 training rows')
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
    if min(args.ks) < 0 or max(args.ks) > args.pool or args.folds < 2:
        raise StarsError(f'ks must lie in 0..{args.pool} and folds must be at least 2')
    return config.replace(training=training)


def fit_rows(experiment: dict, train: np.ndarray, test: np.ndarray, keep: bool, data=None) -> dict:
    """One fit (in a ``fit_executor`` worker, or inline with ``data``): seconds, predictions
    on ``test``, and with ``keep`` the fitted recommender itself, its model on the CPU, where
    the fold-in designs are computed."""
    data = worker_data() if data is None else data
    started = time.perf_counter()
    recommender = StarsTrainer(ExperimentConfig.from_dict(experiment)).fit(data, train)
    seconds = time.perf_counter() - started
    predictions = recommender.predict_rows(data, test)
    if keep:
        recommender.model.cpu()
    return {'seconds': seconds, 'predictions': predictions, 'recommender': recommender if keep else None}


def report(data, rows, predictions) -> dict:
    return regression_report(data.scores[rows], predictions, data.actions[rows])


def plan_folds(args, data) -> list:
    """(seed, fold id, held-out annotators, training rows, reveal pools, test rows) of every
    fold of every seed."""
    plan = []
    for seed in args.seeds:
        for fold_id, held in enumerate(annotator_folds(data.users, args.folds, seed)):
            train = np.flatnonzero(~np.isin(data.users, held))
            if args.max_train_rows and len(train) > args.max_train_rows:
                train = np.sort(np.random.default_rng([seed, fold_id]).choice(train, args.max_train_rows,
                                                                              replace=False))
            pools = reveal_pools(data, held, args.pool, seed)
            test = np.sort(np.concatenate([pools[name][1] for name in held]))
            plan.append((seed, fold_id, held, train, pools, test))
    return plan


def fit_rows_of(fold: tuple, k: int) -> np.ndarray:
    """The training rows at ``k``: the fold's, plus the first k revealed of each held-out annotator."""
    _, _, held, train, pools, _ = fold
    if k == 0:
        return train
    return np.sort(np.concatenate([train, *(pools[name][0][:k] for name in held)]))


def run(args, config, data, fits, log=print) -> dict:
    """Every fold of the plan, its fits run by ``fits`` (common.FitExecutor)."""
    plan = plan_folds(args, data)
    experiment = config.to_dict()
    executor = fits.executor
    submitted = {}

    def submit(folds):  # the largest fits first, so that the last wave is short
        order = sorted(((fold, k) for fold in folds for k in sorted(args.ks)), key=lambda f: -len(fit_rows_of(*f)))
        for fold, k in order:
            submitted[fold[:2] + (k,)] = executor.submit(fit_rows, experiment, fit_rows_of(fold, k), fold[5], k == 0)

    if fits.jobs > 1:  # every fit at once; inline, fold by fold, so that partial results come as it goes
        submit(plan)
    records, timings, regularisation, selection, folds, failed = [], [], {}, {}, {}, []
    try:
        for fold in plan:
            seed, fold_id, held, train, pools, test = fold
            if fits.jobs == 1:
                submit([fold])
            outcomes = {k: fit_outcome(submitted.pop((seed, fold_id, k)), f'seed {seed} fold {fold_id} k={k}')
                        for k in sorted(args.ks)}
            lost = [{'seed': seed, 'fold': fold_id, 'k': k, 'error': outcome.error}
                    for k, outcome in outcomes.items() if isinstance(outcome, FitFailure)]
            if lost:
                failed += lost
                log(f'seed {seed} fold {fold_id}: left out, ' + '; '.join(f"the fit at k={f['k']} failed: "
                                                                          f"{f['error']}" for f in lost))
                continue
            folds.setdefault(str(seed), []).append(held)
            base = outcomes[0]
            timings.append({'seed': seed, 'fold': fold_id, 'k': 0, 'seconds': round(base['seconds'], 1),
                            'n_train': len(train)})
            log(f'seed {seed} fold {fold_id} (held out {held}): base model on {len(train)} ratings in '
                f"{base['seconds']:.0f} s")
            design = Design(base['recommender'], data)
            if str(seed) not in regularisation:
                if args.regularisation:
                    regularisation[str(seed)] = {method: args.regularisation for method in PRIORS}
                else:
                    chosen = {method: choose_regularisation(design, pools, args.ks, prior)
                              for method, prior in PRIORS.items()}
                    regularisation[str(seed)] = {method: lam for method, (lam, _) in chosen.items()}
                    selection[str(seed)] = {method: scores for method, (_, scores) in chosen.items()}
                    log(f'seed {seed}: fold-in λ {regularisation[str(seed)]} (chosen on the revealable pools of '
                        f'fold {fold_id}: {selection[str(seed)]})')
            lambdas = regularisation[str(seed)]
            unpersonalised = report(data, test, design.predict(test, None))
            for k in sorted(args.ks):
                entry = {'seed': seed, 'fold': fold_id, 'k': k, 'held_out': held, 'n_test': len(test),
                         'unpersonalised': unpersonalised, 'mse_by_lambda': {}}
                for method, prior in PRIORS.items():
                    by_lambda = {}
                    for candidate in sorted({lambdas[method], *LAMBDA_GRID}):
                        predictions = np.zeros(len(data))
                        for name in held:
                            revealed, rows = pools[name]
                            predictions[rows] = design.predict(rows, design.fold_in(revealed[:k], candidate, prior))
                        by_lambda[candidate] = report(data, test, predictions[test])
                    entry[method] = by_lambda[lambdas[method]]
                    entry['mse_by_lambda'][method] = {str(lam): r['mse'] for lam, r in by_lambda.items()}
                retrained = outcomes[k]
                if k:
                    timings.append({'seed': seed, 'fold': fold_id, 'k': k, 'seconds': round(retrained['seconds'], 1),
                                    'n_train': len(fit_rows_of(fold, k))})
                entry['retrained'] = report(data, test, retrained['predictions'])
                records.append(entry)
                log(f'seed {seed} fold {fold_id} k={k}: MSE ' + '  '.join(f"{m} {entry[m]['mse']:.4f}"
                                                                         for m in METHODS))
            if args.on_fold:
                args.on_fold(records, timings, regularisation, selection, folds, failed)
    finally:
        executor.shutdown(cancel_futures=True)
    return {'records': records, 'fits': timings, 'regularisation': regularisation, 'selection': selection,
            'folds': folds, 'failed': failed}


def summarise(records: list) -> dict:
    """{method: {k: {metric: [mean, sd, n_folds]}}}"""
    summary = {}
    for method in METHODS:
        summary[method] = {}
        for k in sorted({r['k'] for r in records}):
            values = {m: [r[method][m] for r in records if r['k'] == k] for m in METRICS}
            summary[method][k] = {m: [*mean_sd(v), len(v)] for m, v in values.items()}
    return summary


def gap_share(summary: dict, k: int, method: str = 'fold-in') -> float | None:
    """Share of the MSE gap between k = 0 unpersonalised and retraining at ``k`` that
    ``method`` at ``k`` recovers (None when k was not run or there is no gap)."""
    if k not in summary[method] or 0 not in summary['unpersonalised']:
        return None
    start = summary['unpersonalised'][0]['mse'][0]
    gap = start - summary['retrained'][k]['mse'][0]
    return None if abs(gap) < 1e-12 else (start - summary[method][k]['mse'][0]) / gap


def write_results(folder: Path, result: dict, header: dict) -> dict:
    summary = summarise(result['records'])
    top = max(summary['fold-in']) if summary['fold-in'] else 0
    shares = {method: gap_share(summary, top, method) for method in PRIORS}
    payload = {**header, 'regularisation': result['regularisation'], 'regularisation_selection': result['selection'],
               'folds': result['folds'], 'records': result['records'], 'fits': result['fits'],
               'failed': result['failed'],
               'summary': {m: {str(k): v for k, v in s.items()} for m, s in summary.items()},
               'gap_share': {'k': top, **shares}}
    (folder / 'results.json').write_text(json.dumps(payload, indent=1))
    partitions = '; '.join(f'seed {seed}: {folds}' for seed, folds in result['folds'].items())
    lines = ["# k-shot personalisation on held-out annotators", '', f"`{header['command']}`", '',
             f"{len(result['records']) // max(1, len(header['ks']))} folds of held-out annotators ({partitions}); "
             f"{header['pool']} revealable ratings per held-out annotator; fold-in λ by seed "
             f"{result['regularisation']}; epochs T1={header['epochs'][0]}, T2={header['epochs'][1]}. "
             'Mean ± sd over folds.', '',
             '| k | method | MSE | Pearson r | CCC |', '| --- | --- | --- | --- | --- |']
    for k in sorted(summary['fold-in']):
        for method in METHODS:
            cells = [f'{s[0]:.4f} ± {s[1]:.4f}' for s in (summary[method][k][m] for m in METRICS)]
            lines.append(f'| {k} | {method} | ' + ' | '.join(cells) + ' |')
    for method, share in shares.items():
        if share is not None:
            lines += ['', f'{method} at k={top} recovers {100 * share:.0f}% of the MSE gap between the '
                          f'unpersonalised model (k=0) and full retraining at k={top}.']
    ks = sorted(summary['fold-in'])
    for method in PRIORS:
        lambdas = sorted({float(lam) for r in result['records'] for lam in r['mse_by_lambda'][method]})
        lines += ['', f'Check, not used for any choice: {method} MSE on the test rows for every λ of the grid '
                      '(mean over folds).', '', '| λ | ' + ' | '.join(f'k={k}' for k in ks) + ' |',
                  '| --- |' + ' --- |' * len(ks)]
        for lam in lambdas:
            cells = [np.mean([r['mse_by_lambda'][method][str(lam)] for r in result['records'] if r['k'] == k])
                     for k in ks]
            lines.append(f'| {lam:g} | ' + ' | '.join(f'{v:.4f}' for v in cells) + ' |')
    fit_seconds = [f['seconds'] for f in result['fits']]
    lines += ['', f"{len(fit_seconds)} fits, {np.mean(fit_seconds):.0f} s each on average, "
                  f"{header.get('seconds', 0):.0f} s in all (one torch thread each, {header['jobs']} at a time, "
                  f"on {header['config']['training']['device']})."]
    (folder / 'results.md').write_text('\n'.join(lines) + '\n')
    plot(folder / 'kshot.png', summary)
    return payload


def plot(path: Path, summary: dict) -> None:
    plt = pyplot()

    figure, axes = plt.subplots(1, len(METRICS), figsize=(13, 3.6))
    for axis, metric in zip(axes, METRICS):
        for method in METHODS:
            ks = sorted(summary[method])
            means = np.array([summary[method][k][metric][0] for k in ks])
            sds = np.array([summary[method][k][metric][1] for k in ks])
            sds = np.nan_to_num(sds)
            axis.errorbar(ks, means, yerr=sds, marker='o', capsize=3, label=method)
        label_axis(axis, 'revealed ratings k', NAMES[metric])
    axes[0].legend(fontsize=8)
    save_png(figure, path)


def main(argv=None) -> int:
    args = parse_args(argv)
    setup_logging(args.verbose)
    torch.set_num_threads(1)
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
    started = time.perf_counter()
    header = {'command': shlex.join(['python', '-m', 'offline_training.kshot', *(sys.argv[1:] if argv is None else argv)]),
              'config': config.to_dict(), 'data': {'source': data.source, 'fingerprint': data.fingerprint},
              'pool': args.pool, 'ks': sorted(args.ks), 'seeds': args.seeds, 'jobs': fits.jobs,
              'executor': fits.settings, 'quick': args.quick,
              'max_train_rows': args.max_train_rows, 'machine': machine(),
              'epochs': [config.training.pretrain_epochs, config.training.joint_epochs]}

    def on_fold(records, timings, regularisation, selection, folds, failed):  # partial results survive a stop
        write_results(folder, {'records': records, 'fits': timings, 'regularisation': regularisation,
                               'selection': selection, 'folds': folds, 'failed': failed},
                      {**header, 'seconds': time.perf_counter() - started, 'complete': False})
    args.on_fold = on_fold
    try:
        result = run(args, config, data, fits, log=lambda line: print(line, flush=True))
    except StarsError as error:
        print(f'error: {error}', file=sys.stderr)
        return 1
    payload = write_results(folder, result, {**header, 'seconds': time.perf_counter() - started,
                                             'complete': not result['failed']})
    print((folder / 'results.md').read_text())
    if result['failed']:
        print('\n'.join([f"error: {len(result['failed'])} fit(s) failed, their folds are left out:",
                         *(f"  seed {f['seed']} fold {f['fold']} k={f['k']}: {f['error']}" for f in result['failed'])]),
              file=sys.stderr)
        return 1
    shares = payload['gap_share']
    for method in PRIORS:
        if shares[method] is not None:
            print(f"{method} at k={shares['k']} recovers {100 * shares[method]:.1f}% of the k=0 -> "
                  'full retraining MSE gap')
    return 0


if __name__ == '__main__':
    sys.exit(main())
