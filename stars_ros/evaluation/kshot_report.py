"""The k-shot run's summary and report: the metrics per method and k, the goals met or not (per
fold where a mean can hide a loser), results.json, results.md and kshot.png
(``kshot_run.run`` makes the records they read)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from stars_ros.evaluation.kshot import EXACT_SETS, LEVELS, NODE_STRATEGY
from stars_ros.evaluation.kshot_run import (BASE_ENCODER, CALIBRATION_DRAWS, METRICS, NAMES, RANKING,
                                            SELECTION_SHARE, methods_of)
from stars_ros.evaluation.plots import label_axis, pyplot, save_png
from stars_ros.evaluation.stats import mean_sd


def metrics_of(records: list) -> tuple:
    """The metrics the records hold: ``METRICS``, and ``RANKING`` where examples rate several actions."""
    return METRICS + ((RANKING,) if records and RANKING in records[0]['unpersonalised'] else ())


def summarise(records: list) -> dict:
    """{method: {k: {metric: [mean, sd, n_folds]}}}"""
    summary = {}
    for method in methods_of(records[0]) if records else []:
        summary[method] = {}
        for k in sorted({r['k'] for r in records if method in r}):
            values = {m: [r[method][m] for r in records if r['k'] == k] for m in metrics_of(records)}
            summary[method][k] = {m: [*mean_sd(v), len(v)] for m, v in values.items()}
    return summary


def goals(records: list, summary: dict, strategies: list, ks: list) -> dict:
    """The issue's goals, measured: each fold-in strategy at or below unpersonalised MSE in
    every fold at every k >= 1 (the folds that fail named); for each question strategy (the
    node's is ``NODE_STRATEGY``), the fewest questions reaching random's mean MSE at k = 10
    and whether it is never behind random on the mean; and each fold-in's ``hand_over_k``."""
    never_worse = {}
    for method in summary:
        if method.startswith('fold-in'):
            failing = sorted({(r['seed'], r['fold'], r['k']) for r in records
                              if r['k'] >= 1 and method in r and r[method]['mse'] > r['unpersonalised']['mse']})
            never_worse[method] = {'met': not failing, 'failing': [list(f) for f in failing]}
    out = {'never_worse': never_worse, 'questions': {}, 'hand_over': {}}
    for method in summary:
        if method.startswith('fold-in') and BASE_ENCODER in summary:
            out['hand_over'][method] = hand_over_k(records, method)
    if 'random' in strategies and 10 in summary.get('fold-in (random)', {}):
        random = summary['fold-in (random)']
        for strategy in strategies:
            method = f'fold-in ({strategy})'
            if strategy == 'random' or method not in summary:
                continue
            reached = [k for k in sorted(summary[method]) if summary[method][k]['mse'][0] <= random[10]['mse'][0]]
            out['questions'][strategy] = {
                'to_match_random_at_10': reached[0] if reached else None,
                'never_behind_random': all(summary[method][k]['mse'][0] <= random[k]['mse'][0]
                                           for k in ks if k in summary[method])}
    return out


def hand_over_k(records: list, method: str) -> int | None:
    """The smallest k from which ``method`` is at or below the base encoder's MSE in every
    fold at that k and every larger one (None: not even at the largest): where serving a new
    person the plain encoder could hand over to the fold-in."""
    scored = [r for r in records if method in r and BASE_ENCODER in r]
    worse = {r['k'] for r in scored if r[method]['mse'] > r[BASE_ENCODER]['mse']}
    ks = sorted({r['k'] for r in scored})
    later = [k for k in ks if all(w < k for w in worse)]
    return later[0] if later else None


def write_results(folder: Path, result: dict, header: dict) -> dict:
    summary = summarise(result['records'])
    metrics = metrics_of(result['records'])
    ks = sorted(summary.get('unpersonalised', {}))
    checks = goals(result['records'], summary, header['strategies'], ks) if summary else {}
    payload = {**header, 'folds': result['folds'], 'left_out': result['left_out'], 'records': result['records'],
               'selection': result.get('selection', []),
               'fits': result['fits'], 'failed': result['failed'], 'calibration': result['calibration'],
               'summary': {m: {str(k): v for k, v in s.items()} for m, s in summary.items()}, 'goals': checks}
    (folder / 'results.json').write_text(json.dumps(payload, indent=1))
    partitions = '; '.join(f'seed {seed}: {folds}' for seed, folds in result['folds'].items())
    random_note = (f" Random answers: each fold's metrics are the mean over every set of k pool examples where there "
                   f"are at most {EXACT_SETS} (the exact expectation), else over {header['random_sets']} seeded sets.")
    regret_note = (" First-choice regret: per test example (a person's ratings of one scene, every action), the "
                   'best true score less the true score of the action predicted best, averaged.'
                   if RANKING in metrics else '')
    covered = {k: sorted({(r['seed'], name) for r in result['records'] if r['k'] == k for name in r['covered']})
               for k in ks}
    ran = (f"Commit: {header['git']['commit']}{' (uncommitted changes)' if header['git']['dirty'] else ''}; "
           f"every fit on {header['machine'].get('device', 'cpu')}, {header['machine']['cpus']} CPUs.")
    lines = ['# k-shot personalisation of new people', '', f"`{header['command']}`", '', ran, '',
             f"{len({(r['seed'], r['fold']) for r in result['records']})} folds of held-out people ({partitions}); "
             f"pools of up to {header['pool']} examples per person; {len(result['left_out'])} people left out for "
             f"having a single example; epochs T1={header['epochs'][0]}, T2={header['epochs'][1]}. "
             'Mean ± sd over folds.' + random_note + regret_note, '',
             '| k | people covered | method | ' + ' | '.join(NAMES[m] for m in metrics) + ' |',
             '| --- | --- | --- |' + ' --- |' * len(metrics)]
    for k in ks:
        for method in summary:
            if k in summary[method]:
                cells = [f'{s[0]:.4f} ± {s[1]:.4f}' for s in (summary[method][k][m] for m in metrics)]
                lines.append(f'| {k} | {len(covered[k])} | {method} | ' + ' | '.join(cells) + ' |')
    if any(entry['validation_mse'] for entry in result.get('selection', [])):
        lines += ['', f'Training settings chosen per fold inside its training people (fitted on their examples less '
                      f'a seeded {SELECTION_SHARE:.0%}, lowest MSE on those):', '']
        lines += [f"- seed {e['seed']} fold {e['fold']}: {e['chosen']} (validation MSE "
                  + ', '.join(f'{k} {v:.4f}' for k, v in e['validation_mse'].items()) + ')'
                  for e in result['selection']]
    calibration = result['calibration']
    levels = [str(level) for level in LEVELS]
    lines += ['', f"Calibration: share of held-out ratings inside the central predictive intervals "
                  f"(new people: {header['strategies'][0]} questions, up to {CALIBRATION_DRAWS} of its draws at "
                  'each k; pooled over folds; ratings: those of one draw).', '',
              '| people | k | ratings | mean score_sd | ν | '
              + ' | '.join(f'{float(level):.0%}' for level in levels) + ' |',
              '| --- | --- | --- | --- | --- |' + ' --- |' * len(levels)]
    rows = [('new', k, calibration['new'][k]) for k in calibration.get('new', {})]
    if 'known' in calibration:
        rows.append(('known', '–', calibration['known']))
    for who, k, cells in rows:
        nus = ', '.join(f'{v:g}' for v in cells['nu'])
        lines.append(f"| {who} | {k} | {cells['n']} | {cells['mean_sd']:.4f} | {nus} | "
                     + ' | '.join(f'{100 * cells[level]:.1f}' for level in levels) + ' |')
    by_fold = [r for r in result['records'] if 'calibration' in r]
    if by_fold:
        folds = sorted({(r['seed'], r['fold']) for r in by_fold})
        cells = {(r['seed'], r['fold'], r['k']): r['calibration'] for r in by_fold}
        lines += ['', 'The same per fold (new people; ' + ', '.join(f'{float(level):.0%}' for level in levels) + '):',
                  '',
                  '| k | ' + ' | '.join(f'seed {s} fold {f}' for s, f in folds) + ' |',
                  '| --- |' + ' --- |' * len(folds)]
        for k in sorted({r['k'] for r in by_fold}):
            lines.append(f'| {k} | ' + ' | '.join(
                ', '.join(f'{100 * cells[s, f, k][level]:.1f}' for level in levels) if (s, f, k) in cells else '–'
                for s, f in folds) + ' |')
    if checks:
        lines += ['', 'Goals:', '']
        for method, held in checks['never_worse'].items():
            lines.append(f"- {method} at or below unpersonalised MSE in every fold at every k ≥ 1: "
                         + ('met' if held['met'] else 'NOT met (seed, fold, k: '
                            + ', '.join(f'{s}/{f}/{k}' for s, f, k in held['failing']) + ')'))
        for strategy, held in checks['questions'].items():
            reached = held['to_match_random_at_10']
            mark = " (the node's)" if strategy == NODE_STRATEGY else ''
            lines.append(f"- {strategy} questions{mark} needed to reach random's MSE at k = 10: "
                         f"{reached if reached is not None else 'not reached'} "
                         f"(goal ≤ 5: {'met' if reached is not None and reached <= 5 else 'NOT met'}); never behind "
                         f"random: {'met' if held['never_behind_random'] else 'NOT met'}")
        for method, k in checks.get('hand_over', {}).items():
            lines.append(f'- {method} at or below the {BASE_ENCODER} in every fold from k = '
                         + ('(not at any k)' if k is None else f'{k} on'))
        worst = max((abs(100 * cells[level] - 100 * float(level)) for _, _, cells in rows for level in levels),
                    default=0.0)
        lines.append(f"- interval coverage within ±3 points of nominal: {'met' if worst <= 3 else 'NOT met'} "
                     f'(largest gap {worst:.1f} points)')
        gaps = {}  # a fold's largest gap over its ks and levels: a pooled figure hides no fold
        for r in by_fold:
            gap = max(abs(100 * r['calibration'][level] - 100 * float(level)) for level in levels)
            gaps[r['seed'], r['fold']] = max(gap, gaps.get((r['seed'], r['fold']), 0.0))
        missed = [f'{seed}/{fold} ({gap:.1f})' for (seed, fold), gap in sorted(gaps.items()) if gap > 3]
        lines.append('- the same in every fold (new people, every k): ' + ('met' if not missed else
                     'NOT met (seed/fold, largest gap in points: ' + ', '.join(missed) + ')'))
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
