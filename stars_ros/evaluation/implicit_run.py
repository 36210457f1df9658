"""The implicit-outcome simulation run (``stars_ros.evaluation.implicit``) over data sets and
leave-people-out folds, its summary and its report; ``offline_training.implicit_feedback`` is
its command line."""
from __future__ import annotations

import json
import logging
import tempfile
from pathlib import Path

import numpy as np

from stars_ros.data.ratings import load_dataset
from stars_ros.evaluation import crowd_data
from stars_ros.evaluation.implicit import (OutcomeModel, exchange_rate, expected_mse_implicit, mse_explicit,
                                          mse_implicit)
from stars_ros.evaluation.kshot import Design, annotator_folds, reveal_pools
from stars_ros.evaluation.plots import pyplot, save_png
from stars_ros.evaluation.stats import mean_sd
from stars_ros.model.config import ExperimentConfig
from stars_ros.recommender import StarsRecommender

LOGGER = logging.getLogger(__name__)
CONFIGS = {'socnav1': 'config/socnav1_gat.yaml', 'crowd': 'config/implicit_crowd.yaml'}


def load(name: str, args):
    """The data set ``name``: SocNav1 at ``args.data_root``, or the crowd data generated now."""
    if name == 'socnav1':
        return load_dataset(args.data_root)
    folder = Path(tempfile.mkdtemp(prefix='implicit-crowd-'))
    return load_dataset(crowd_data.write(folder, seed=args.seed))


def run_dataset(name: str, args, ns, ks) -> dict:
    """Curves, coverage and summary of one data set (the command line's module docstring)."""
    data = load(name, args)
    if data.scale is None:
        raise SystemExit(f'{name}: the simulation needs a bounded rating scale')
    config_path = {**CONFIGS, **args.configs}[name]
    config = ExperimentConfig.from_yaml(config_path)
    per_fold, covered, left_out = [], 0, 0
    for fold, held_out in enumerate(annotator_folds(data.users, args.folds, args.seed)):
        train = np.flatnonzero(~np.isin(data.users, held_out))
        design = Design(StarsRecommender(config).fit(data, train).fitted, data)
        people, _ = reveal_pools(data, held_out, args.pool, args.seed)
        people = {p: person for p, person in people.items() if len(person.rows(range(len(person.pool)))) >= max(ks)}
        covered += len(people)
        left_out += len(held_out) - len(people)
        errors = {'explicit': {k: [] for k in ks}, **{f'implicit ε={f}': {n: [] for n in ns} for f in args.flips}}
        for p_index, person in enumerate(people.values()):
            for k in ks:
                errors['explicit'][k].append(mse_explicit(design, person, k))
            for flip in args.flips:
                model = OutcomeModel(flip)
                for n in ns:
                    if n <= args.exact_up_to:  # the expectation itself: no draws' noise where one outcome moves most
                        errors[f'implicit ε={flip}'][n].append(expected_mse_implicit(design, person, n, model,
                                                                                     data.scale))
                        continue
                    draws = [mse_implicit(design, person, n, model,
                                          np.random.default_rng([args.seed, fold, p_index, n, d]), data.scale)
                             for d in range(args.draws)]
                    errors[f'implicit ε={flip}'][n].append(np.mean(draws, axis=0))
        per_fold.append({curve: {str(x): float(np.mean(np.concatenate(v))) for x, v in points.items() if v}
                         for curve, points in errors.items()})  # keyed as results.json keeps them
        LOGGER.info(f'{name}: fold {fold + 1}/{args.folds} done ({len(people)} people)')
    curves = {}
    for curve, points in per_fold[0].items():
        curves[curve] = {x: dict(zip(('mean', 'sd'), mean_sd([f[curve][x] for f in per_fold]))) for x in points}
    return {'data': data.source, 'fingerprint': data.fingerprint, 'scale': list(data.scale), 'config': config_path,
            'people_covered': covered, 'people_left_out': left_out, 'folds': per_fold, 'curves': curves,
            'unpersonalised_mse': curves['explicit']['0']['mean'],
            'summary': summarise(curves, ns, ks, args.flips, per_fold)}


def summarise(curves: dict, ns, ks, flips, per_fold: list) -> dict:
    """Per ε: is every n no worse than unpersonalised on the mean over folds, and in every fold
    (``failing_folds``: (fold, n, excess) where one is worse; the mean can hide a fold that
    loses), and per k > 0 how many implicit outcomes match k explicit ratings
    (``exchange_rate``): 'measured', 'beyond range' (more than max n), or 'explicit no
    better' (k ratings do not beat unpersonalised: no rate). Explicit ratings get the same
    per-fold check (``explicit``)."""
    baseline = curves['explicit']['0']['mean']
    summary = {}
    for flip in flips:
        means = [curves[f'implicit ε={flip}'][str(n)]['mean'] for n in ns]
        worth = {}
        for k in (k for k in ks if k > 0):
            target = curves['explicit'][str(k)]['mean']
            rate = exchange_rate(ns, means, target) if target < baseline else None
            status = 'explicit no better' if target >= baseline else 'beyond range' if rate is None else 'measured'
            worth[str(k)] = {'explicit_mse': target, 'implicit_outcomes': rate, 'status': status}
        summary[f'ε={flip}'] = {'never_worse_than_unpersonalised': all(m <= baseline + 1e-12 for m in means),
                                'worst_excess_over_unpersonalised': max(m - baseline for m in means),
                                'failing_folds': _failing_folds(per_fold, f'implicit ε={flip}'),
                                'implicit_outcomes_worth': worth}
    summary['explicit'] = {'failing_folds': _failing_folds(per_fold, 'explicit')}
    return summary


def _failing_folds(per_fold: list, curve: str) -> list:
    """[(fold, n, excess)] where ``curve``'s MSE is above that fold's unpersonalised one."""
    return [(fold, int(n), value - errors['explicit']['0']) for fold, errors in enumerate(per_fold)
            for n, value in errors[curve].items() if value > errors['explicit']['0'] + 1e-12]


def rewrite(out: Path) -> None:
    """Recompute the summary and results.md from ``out``'s results.json, running nothing."""
    results = json.loads((out / 'results.json').read_text())
    for found in results['datasets'].values():
        found['summary'] = summarise(found['curves'], results['ns'], results['ks'], results['flips'], found['folds'])
    (out / 'results.json').write_text(json.dumps(results, indent=1) + '\n')
    write_report(out, results, results['ns'], results['ks'])


def write_report(out: Path, results: dict, ns, ks) -> None:
    """results.md and implicit.png of a finished run."""
    plt = pyplot()
    figure, axes = plt.subplots(1, len(results['datasets']), figsize=(6 * len(results['datasets']), 4), squeeze=False)
    lines = ['# Implicit outcomes against explicit ratings', '', f"Command: `{results['command']}`", '',
             'MSE on held-out people\'s test ratings (mean ± sd over folds). n = 0 / k = 0: the unpersonalised '
             'model (the population prior\'s mean). Outcomes: P(stayed) = ε/2 + (1 − ε)(y − L)/(H − L) '
             '(`stars_ros/evaluation/implicit.py`).', '']
    for axis, (name, found) in zip(axes[0], results['datasets'].items()):
        lines += [f'## {name} (scale {found["scale"]}, {found["people_covered"]} people covered, '
                  f'{found["people_left_out"]} left out: pool < {max(ks)} ratings)', '',
                  '| curve | ' + ' | '.join(f'{x}' for x in ns) + ' |', '|---' * (len(ns) + 1) + '|']
        for curve, points in found['curves'].items():
            cells = [f"{points[str(x)]['mean']:.4f} ± {points[str(x)]['sd']:.4f}" if str(x) in points else ''
                     for x in ns]
            lines.append(f'| {curve} (n or k) | ' + ' | '.join(cells) + ' |')
            xs = sorted(int(x) for x in points)
            axis.errorbar([max(x, 0.5) for x in xs], [points[str(x)]['mean'] for x in xs],
                          yerr=[points[str(x)]['sd'] for x in xs], marker='o', capsize=2, label=curve)
        axis.axhline(found['unpersonalised_mse'], color='grey', linestyle=':', label='unpersonalised')
        axis.set(xscale='log', xlabel='outcomes n / explicit ratings k (0 drawn at 0.5)', ylabel='test MSE', title=name)
        axis.legend(fontsize=7)
        lines += ['']
        for flip, summary in found['summary'].items():
            failing = summary['failing_folds']
            losing = len({fold for fold, _, _ in failing})
            in_folds = ('in every fold: yes' if not failing else
                        f"in every fold: no ({losing} of {len(found['folds'])} folds, largest excess "
                        f'{max(e for _, _, e in failing):+.5f})')
            if flip == 'explicit':
                lines.append(f'- explicit ratings never worse than unpersonalised {in_folds}')
                continue
            worth = '; '.join(f"{k} explicit ≈ {v['implicit_outcomes']:.1f} implicit" if v['status'] == 'measured' else
                              f'{k} explicit: more than {max(ns)} implicit' if v['status'] == 'beyond range' else
                              f'{k} explicit: no better than unpersonalised, no rate'
                              for k, v in summary['implicit_outcomes_worth'].items())
            lines.append(f"- {flip}: never worse than unpersonalised on the mean: "
                         f"{summary['never_worse_than_unpersonalised']} (largest excess "
                         f"{summary['worst_excess_over_unpersonalised']:+.7f}), {in_folds}; {worth}")
        lines.append('')
    lines += [f"Measured on {results['machine']['platform']}, {results['seconds']:.0f} s."]
    (out / 'results.md').write_text('\n'.join(lines) + '\n')
    save_png(figure, out / 'implicit.png')


