"""k-shot personalisation of new people: unpersonalised vs Bayesian fold-in (three ways of
choosing the questions) vs full retraining, with the calibration of the predictive intervals.

    python -m offline_training.kshot --config config/socnav1_gat.yaml \
        --data-root ../shared/datasets/socnav1 --out results/kshot-socnav1-bayes [--quick]

Leave-people-out folds (people shuffled with each of ``--seeds`` and dealt into ``--folds``
groups). Per fold a model is trained on the other people's examples, less a seeded
``--known-test`` share of them: half of it gives the personalisation prior its noise
variance (``estimate_prior``'s held-out rows), the other half checks the known people's
calibration. For every held-out
person ``stars_ros.evaluation.kshot`` sets aside a seeded pool of ``--pool`` examples (one
person's ratings of one scene, every action; fewer for a person with fewer examples, who then
covers only the k it allows, and a person with one example is left out and counted); their
other examples are the test rows, the same for every k and strategy. Per k each fold's
covered people are scored:

- ``unpersonalised``: the scene-only model (p_u = 0, b_u = 0);
- ``fold-in (<strategy>)``: the node's default, the Gaussian posterior from the first k
  answers the strategy asked for (``random``: the pool's seeded order; ``uncertainty``: largest
  predictive variance; ``active``: the A-optimal expected variance reduction over the pool).
  k = 0 is the population prior's mean, what the node serves a stranger;
- ``ridge λ=<--ridge-lambda> (random)``: the ridge solve the node did before the posterior;
- ``retrained``: the whole model trained again on the fold's rows plus the first k random
  answers of each held-out person (k = 0 is the fold's model), at every k or those of
  ``--retrain-ks``.

Metrics (MSE, r, CCC on the rating scale, scores clipped as served) are pooled over a fold's
covered test rows, then given as mean ± sd over folds. Calibration: the share of test ratings
inside the central 50/80/90/95 % predictive intervals, for new people at each k (random
order) and for known people (their held-out examples, each scored from their trained row and
its covariance), pooled over folds. Writes results.json, results.md and kshot.png. Fits run
in worker processes with ``--jobs`` (one torch thread each) or as Ray tasks (``--executor
ray``); a fold any of whose fits fails is left out and named, and the run ends with status 1.
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
from stars_ros.evaluation.executors import FitFailure, fit_outcome, worker_data
from stars_ros.evaluation.kshot import LEVELS, NODE_STRATEGY, STRATEGIES, Design, annotator_folds, coverage, known_split, reveal_pools
from stars_ros.model.metrics import regression_report
from stars_ros.evaluation.stats import mean_sd
from stars_ros.model.training import StarsTrainer
from stars_ros.personalisation.prior import estimate_prior

from .common import (DEFAULT_SOCNAV1, add_executor_options, build_executor, label_axis, machine, pyplot, read_inputs,
                     save_png, setup_logging)

METRICS = ('mse', 'pearson_r', 'ccc')
NAMES = {'mse': 'MSE', 'pearson_r': 'Pearson r', 'ccc': 'CCC'}
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
                        help="share of the training people's examples held out for their calibration (default: %(default)s)")
    parser.add_argument('--ridge-lambda', type=float, default=1.0,
                        help='λ of the ridge fold-in shown beside the posterior (default: %(default)s, the node\'s '
                             'former default)')
    parser.add_argument('--epochs', type=int, nargs=2, metavar=('T1', 'T2'), help='override the config epochs')
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
    if min(args.ks) < 0 or max(args.ks) > args.pool or args.folds < 2 or not 0 <= args.known_test < 1:
        raise StarsError(f'ks must lie in 0..{args.pool}, folds must be at least 2 and --known-test in [0, 1)')
    return config.replace(training=training)


def fit_rows(experiment: dict, train: np.ndarray, test: np.ndarray, keep: bool, noise_rows=None, data=None) -> dict:
    """One fit (in a ``fit_executor`` worker, or inline with ``data``): seconds, predictions
    on ``test``, and with ``keep`` the fitted recommender itself, its model on the CPU, where
    the fold-in designs are computed, with the personalisation prior a checkpoint keeps (its
    noise from ``noise_rows``, held-out ratings of the trained people)."""
    data = worker_data() if data is None else data
    started = time.perf_counter()
    recommender = StarsTrainer(ExperimentConfig.from_dict(experiment)).fit(data, train)
    seconds = time.perf_counter() - started
    predictions = recommender.predict_rows(data, test)
    if keep:
        recommender.model.cpu()
        recommender.user_prior = estimate_prior(recommender, data, train, noise_rows=noise_rows).to_dict()
    return {'seconds': seconds, 'predictions': predictions, 'recommender': recommender if keep else None}


def report(data, rows, predictions) -> dict:
    return regression_report(data.scores[rows], predictions, data.actions[rows])


def plan_folds(args, data) -> list:
    """(seed, fold id, held-out people, training rows, {person: Person}, left out, known
    people's test rows, their rows for the prior's noise) of every fold of every seed."""
    plan = []
    for seed in args.seeds:
        for fold_id, held_out in enumerate(annotator_folds(data.users, args.folds, seed)):
            train = np.flatnonzero(~np.isin(data.users, held_out))
            train, held = known_split(data, train, args.known_test, seed)
            noise, known = known_split(data, held, 0.5, seed + 1)  # half for the prior's noise, half to check it
            if args.max_train_rows and len(train) > args.max_train_rows:
                train = np.sort(np.random.default_rng([seed, fold_id]).choice(train, args.max_train_rows,
                                                                              replace=False))
            people, left_out = reveal_pools(data, held_out, args.pool, seed)
            plan.append((seed, fold_id, held_out, train, people, left_out, known, noise))
    return plan


def fit_rows_of(fold: tuple, k: int) -> np.ndarray:
    """The training rows at ``k``: the fold's, plus each held-out person's first k random answers."""
    _, _, _, train, people, _, _, _ = fold
    if k == 0:
        return train
    return np.sort(np.concatenate([train, *(person.rows(range(min(k, len(person.pool)))) for person in people.values())]))


def test_rows(people: dict, k: int) -> tuple[list, np.ndarray]:
    """(people who cover k, their test rows)."""
    covered = sorted(name for name, person in people.items() if len(person.pool) >= k)
    rows = np.concatenate([people[name].test for name in covered]) if covered else np.zeros(0, dtype=np.int64)
    return covered, np.sort(rows)


def score_fold(args, data, design: Design, fold: tuple, outcomes: dict) -> tuple[list, dict]:
    """(records, calibration samples) of one fold whose fits are ``outcomes`` {k: fit}."""
    seed, fold_id, held, _, people, _, known, _ = fold
    orders = {(name, strategy): design.reveal_order(person, strategy, max(args.ks))
              for name, person in people.items() for strategy in args.strategies}
    methods = [f'fold-in ({s})' for s in args.strategies]
    ridge = f'ridge λ={args.ridge_lambda:g} ({args.strategies[0]})'
    records, calibration = [], {'new': {}, 'known': None}
    for k in sorted(args.ks):
        covered, rows = test_rows(people, k)
        if not len(rows):
            continue
        entry = {'seed': seed, 'fold': fold_id, 'k': k, 'held_out': held, 'covered': covered, 'n_test': len(rows),
                 'unpersonalised': report(data, rows, design.predict(rows, None))}
        predictions = {method: np.zeros(len(data)) for method in [*methods, ridge]}
        samples = {'y': [], 'mean': [], 'sd': []}
        for name in covered:
            person = people[name]
            for strategy, method in zip(args.strategies, methods):
                answered = person.rows(orders[name, strategy][:k])
                theta, covariance = design.posterior(answered)
                predictions[method][person.test] = design.predict(person.test, theta)
                if strategy == args.strategies[0]:
                    mean, sd = design.predictive(person.test, theta, covariance)
                    samples['y'].append(data.scores[person.test])
                    samples['mean'].append(mean)
                    samples['sd'].append(sd)
                    if k:
                        ridge_theta, _ = design.posterior(answered, regularisation=args.ridge_lambda)
                        predictions[ridge][person.test] = design.predict(person.test, ridge_theta)
                    else:
                        predictions[ridge][person.test] = predictions[method][person.test]
        for method, values in predictions.items():
            entry[method] = report(data, rows, values[rows])
        if k in outcomes:
            entry['retrained'] = report(data, rows, outcomes[k]['predictions'][np.searchsorted(fold_test(fold), rows)])
        calibration['new'][k] = {**{key: np.concatenate(v) for key, v in samples.items()},
                                 'nu': design.foldin.user_prior.nu}
        records.append(entry)
    if len(known):
        users = np.asarray(data.users[known])
        means, sds = np.zeros(len(known)), np.zeros(len(known))
        for name in sorted(set(users.tolist())):
            mine = users == name
            theta, covariance = design.posterior(np.zeros(0, dtype=np.int64), user_id=name)
            means[mine], sds[mine] = design.predictive(known[mine], theta, covariance)
        calibration['known'] = {'y': data.scores[known], 'mean': means, 'sd': sds, 'nu': design.foldin.user_prior.nu}
    return records, calibration


def retrained_ks(args) -> list:
    """The ks whose fits run: 0 (the fold's model) and those of ``--retrain-ks`` (default: all)."""
    return sorted({0, *(args.ks if args.retrain_ks is None else [k for k in args.retrain_ks if k in args.ks])})


def fold_test(fold: tuple) -> np.ndarray:
    """Every test row of a fold's held-out people (what each fit predicts), sorted."""
    people = fold[4]
    return np.sort(np.concatenate([person.test for person in people.values()]))


def run(args, config, data, fits, log=print) -> dict:
    """Every fold of the plan, its fits run by ``fits`` (common.FitExecutor)."""
    plan = plan_folds(args, data)
    experiment = config.to_dict()
    executor = fits.executor
    submitted = {}

    def submit(folds):  # the largest fits first, so that the last wave is short
        order = sorted(((fold, k) for fold in folds for k in retrained_ks(args)), key=lambda f: -len(fit_rows_of(*f)))
        for fold, k in order:
            submitted[fold[:2] + (k,)] = executor.submit(fit_rows, experiment, fit_rows_of(fold, k), fold_test(fold),
                                                         k == 0, fold[7])

    if fits.jobs > 1:  # every fit at once; inline, fold by fold, so that partial results come as it goes
        submit(plan)
    records, timings, folds, failed, left_out = [], [], {}, [], {}
    pooled = {'new': {}, 'known': []}
    try:
        for fold in plan:
            seed, fold_id, held, train, people, skipped, known, _ = fold
            if fits.jobs == 1:
                submit([fold])
            outcomes = {k: fit_outcome(submitted.pop((seed, fold_id, k)), f'seed {seed} fold {fold_id} k={k}')
                        for k in retrained_ks(args)}
            lost = [{'seed': seed, 'fold': fold_id, 'k': k, 'error': outcome.error}
                    for k, outcome in outcomes.items() if isinstance(outcome, FitFailure)]
            if lost:
                failed += lost
                log(f'seed {seed} fold {fold_id}: left out, ' + '; '.join(f"the fit at k={f['k']} failed: "
                                                                          f"{f['error']}" for f in lost))
                continue
            folds.setdefault(str(seed), []).append(held)
            left_out.update({f'{seed}:{name}': count for name, count in skipped.items()})
            base = outcomes[0]
            for k, outcome in outcomes.items():
                timings.append({'seed': seed, 'fold': fold_id, 'k': k, 'seconds': round(outcome['seconds'], 1),
                                'n_train': len(fit_rows_of(fold, k))})
            log(f'seed {seed} fold {fold_id} ({len(people)} held out, {len(skipped)} left out): base model on '
                f"{len(train)} ratings in {base['seconds']:.0f} s")
            fold_records, calibration = score_fold(args, data, Design(base['recommender'], data), fold, outcomes)
            records += fold_records
            for k, samples in calibration['new'].items():
                pooled['new'].setdefault(k, []).append(samples)
            if calibration['known'] is not None:
                pooled['known'].append(calibration['known'])
            for entry in fold_records:
                log(f"seed {seed} fold {fold_id} k={entry['k']}: MSE " + '  '.join(
                    f"{m} {entry[m]['mse']:.4f}" for m in methods_of(entry)))
            if args.on_fold:
                args.on_fold(records, timings, folds, failed, left_out, calibration_table(pooled))
    finally:
        executor.shutdown(cancel_futures=True)
    return {'records': records, 'fits': timings, 'folds': folds, 'failed': failed, 'left_out': left_out,
            'calibration': calibration_table(pooled)}


def methods_of(entry: dict) -> list:
    """The scored methods of a record, in table order."""
    return [key for key in entry if isinstance(entry[key], dict) and 'mse' in entry[key]]


def calibration_table(pooled: dict) -> dict:
    """{'new': {k: {level: coverage}}, 'known': {level: coverage}, 'n': ...} pooled over folds
    (each fold's intervals from its own prior's ν)."""
    def cover(parts):
        sizes = np.array([len(p['y']) for p in parts])
        shares = [coverage(p['y'], p['mean'], p['sd'], p['nu']) for p in parts]
        return {**{level: float(np.average([share[level] for share in shares], weights=sizes)) for level in shares[0]},
                'n': int(sizes.sum()), 'mean_sd': float(np.mean(np.concatenate([p['sd'] for p in parts]))),
                'nu': sorted({float(p['nu']) for p in parts})}
    table = {'new': {str(k): cover(parts) for k, parts in sorted(pooled['new'].items())}}
    if pooled['known']:
        table['known'] = cover(pooled['known'])
    return table


def summarise(records: list) -> dict:
    """{method: {k: {metric: [mean, sd, n_folds]}}}"""
    summary = {}
    for method in methods_of(records[0]) if records else []:
        summary[method] = {}
        for k in sorted({r['k'] for r in records if method in r}):
            values = {m: [r[method][m] for r in records if r['k'] == k] for m in METRICS}
            summary[method][k] = {m: [*mean_sd(v), len(v)] for m, v in values.items()}
    return summary


def goals(records: list, summary: dict, strategies: list, ks: list) -> dict:
    """The issue's goals, measured: each fold-in strategy at or below unpersonalised MSE in
    every fold at every k >= 1 (the folds that fail named); for the node's question strategy
    (``NODE_STRATEGY``), the fewest questions reaching random's mean MSE at k = 10 and whether
    it is never behind random on the mean."""
    never_worse = {}
    for method in summary:
        if method.startswith('fold-in'):
            failing = sorted({(r['seed'], r['fold'], r['k']) for r in records
                              if r['k'] >= 1 and method in r and r[method]['mse'] > r['unpersonalised']['mse']})
            never_worse[method] = {'met': not failing, 'failing': [list(f) for f in failing]}
    out = {'never_worse': never_worse}
    node = f'fold-in ({NODE_STRATEGY})'
    if NODE_STRATEGY in strategies and 'random' in strategies and 10 in summary.get('fold-in (random)', {}):
        target = summary['fold-in (random)'][10]['mse'][0]
        reached = [k for k in sorted(summary[node]) if summary[node][k]['mse'][0] <= target]
        out['node_questions_to_match_random_at_10'] = reached[0] if reached else None
        out['node_never_behind_random'] = all(summary[node][k]['mse'][0] <= summary['fold-in (random)'][k]['mse'][0]
                                              for k in ks if k in summary[node])
    return out


def write_results(folder: Path, result: dict, header: dict) -> dict:
    summary = summarise(result['records'])
    ks = sorted(summary.get('unpersonalised', {}))
    checks = goals(result['records'], summary, header['strategies'], ks) if summary else {}
    payload = {**header, 'folds': result['folds'], 'left_out': result['left_out'], 'records': result['records'],
               'fits': result['fits'], 'failed': result['failed'], 'calibration': result['calibration'],
               'summary': {m: {str(k): v for k, v in s.items()} for m, s in summary.items()}, 'goals': checks}
    (folder / 'results.json').write_text(json.dumps(payload, indent=1))
    partitions = '; '.join(f'seed {seed}: {folds}' for seed, folds in result['folds'].items())
    covered = {k: sorted({(r['seed'], name) for r in result['records'] if r['k'] == k for name in r['covered']})
               for k in ks}
    lines = ['# k-shot personalisation of new people', '', f"`{header['command']}`", '',
             f"{len({(r['seed'], r['fold']) for r in result['records']})} folds of held-out people ({partitions}); "
             f"pools of up to {header['pool']} examples per person; {len(result['left_out'])} people left out for "
             f"having a single example; epochs T1={header['epochs'][0]}, T2={header['epochs'][1]}. "
             'Mean ± sd over folds.', '',
             '| k | people covered | method | MSE | Pearson r | CCC |', '| --- | --- | --- | --- | --- | --- |']
    for k in ks:
        for method in summary:
            if k in summary[method]:
                cells = [f'{s[0]:.4f} ± {s[1]:.4f}' for s in (summary[method][k][m] for m in METRICS)]
                lines.append(f'| {k} | {len(covered[k])} | {method} | ' + ' | '.join(cells) + ' |')
    calibration = result['calibration']
    levels = [str(level) for level in LEVELS]
    lines += ['', f"Calibration: share of held-out ratings inside the central predictive intervals "
                  f"(new people: {header['strategies'][0]} questions; pooled over folds).", '',
              '| people | k | ratings | mean score_sd | ν | ' + ' | '.join(f'{float(l):.0%}' for l in levels) + ' |',
              '| --- | --- | --- | --- | --- |' + ' --- |' * len(levels)]
    rows = [('new', k, calibration['new'][k]) for k in calibration.get('new', {})]
    if 'known' in calibration:
        rows.append(('known', '–', calibration['known']))
    for who, k, cells in rows:
        lines.append(f"| {who} | {k} | {cells['n']} | {cells['mean_sd']:.4f} | {', '.join(f'{v:g}' for v in cells['nu'])} | "
                     + ' | '.join(f'{100 * cells[l]:.1f}' for l in levels) + ' |')
    if checks:
        lines += ['', 'Goals:', '']
        for method, held in checks['never_worse'].items():
            lines.append(f"- {method} at or below unpersonalised MSE in every fold at every k ≥ 1: "
                         + ('met' if held['met'] else 'NOT met (seed, fold, k: '
                            + ', '.join(f'{s}/{f}/{k}' for s, f, k in held['failing']) + ')'))
        if 'node_questions_to_match_random_at_10' in checks:
            reached = checks['node_questions_to_match_random_at_10']
            lines.append(f"- {NODE_STRATEGY} questions (the node's) needed to reach random's MSE at k = 10: "
                         f"{reached if reached is not None else 'not reached'} (goal ≤ 5: "
                         f"{'met' if reached is not None and reached <= 5 else 'NOT met'}); never behind random: "
                         f"{'met' if checks['node_never_behind_random'] else 'NOT met'}")
        worst = max((abs(100 * cells[l] - 100 * float(l)) for _, _, cells in rows for l in levels), default=0.0)
        lines.append(f"- interval coverage within ±3 points of nominal: {'met' if worst <= 3 else 'NOT met'} "
                     f'(largest gap {worst:.1f} points)')
    fit_seconds = [f['seconds'] for f in result['fits']]
    lines += ['', f"{len(fit_seconds)} fits, {np.mean(fit_seconds) if fit_seconds else 0:.0f} s each on average, "
                  f"{header.get('seconds', 0):.0f} s in all (one torch thread each, {header['jobs']} at a time, "
                  f"on {header['config']['training']['device']})."]
    (folder / 'results.md').write_text('\n'.join(lines) + '\n')
    if summary:
        plot(folder / 'kshot.png', summary)
    return payload


def plot(path: Path, summary: dict) -> None:
    plt = pyplot()

    figure, axes = plt.subplots(1, len(METRICS), figsize=(13, 3.6))
    for axis, metric in zip(axes, METRICS):
        for method in summary:
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
              'strategies': args.strategies, 'known_test': args.known_test, 'ridge_lambda': args.ridge_lambda,
              'retrain_ks': retrained_ks(args),
              'executor': fits.settings, 'quick': args.quick,
              'max_train_rows': args.max_train_rows, 'machine': machine(),
              'epochs': [config.training.pretrain_epochs, config.training.joint_epochs]}

    def on_fold(records, timings, folds, failed, left_out, calibration):  # partial results survive a stop
        write_results(folder, {'records': records, 'fits': timings, 'folds': folds, 'failed': failed,
                               'left_out': left_out, 'calibration': calibration},
                      {**header, 'seconds': time.perf_counter() - started, 'complete': False})
    args.on_fold = on_fold
    try:
        result = run(args, config, data, fits, log=lambda line: print(line, flush=True))
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
