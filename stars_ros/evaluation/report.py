"""The results folder of an evaluation run (``evaluation.protocol``): its tables
(``tables.md``: the paper's tables, the paired tests, the sparsity table and where the time
went), CSVs, ``results.json``, the sparsity plots, and what a failed or resumed run needs
(``failed.jsonl``, ``previous_entries``). ``offline_training.evaluate`` is the command line.
"""
from __future__ import annotations

import collections
import csv
import json
import math
import os
import sys
from pathlib import Path

import numpy as np
import yaml

from stars_ros.errors import StarsError
from stars_ros.evaluation.plots import label_axis, mean_band, pyplot, save_png
from stars_ros.evaluation.specs import DISPLAY, model_specs, settings_key
from stars_ros.evaluation.stats import format_mean_sd, mean_sd
from stars_ros.evaluation.summaries import (ablation_tests, by_model, grid_edge, paired_tests, peer_tests,
                                            recipe_tests, sparsity_summary, time_accounting)

METRIC_NAMES = {'mse': 'MSE', 'rmse': 'RMSE', 'pearson_r': 'r', 'ccc': 'CCC'}
RECORD_COLUMNS = ('protocol', 'model', 'backbone', 'variant', 'fold', 'fraction', 'stage', 'settings', 'T1', 'T2',
                  'n_train', 'n_test', 'mse', 'rmse', 'pearson_r', 'ccc', 'epochs', 'fit_seconds',
                  'predict_seconds', 'error')
SELECTION_COLUMNS = ('model', 'fold', 'settings', 'T1', 'T2', 'inner_fold', 'n_train', 'n_test', 'z_rmse')
RESUME_MAY_DIFFER = ('data_root', 'jobs', 'threads', 'executor')
#: What a run writes at its end; an earlier run's are removed first, so that they never sit
#: beside records they do not summarise.
SUMMARY_FILES = ('tables.md', 'results.json', 'folds.csv', 'selection.csv', 'tests.csv', 'failed.jsonl',
                 *(f'sparsity_{metric}.png' for metric in ('mse', 'rmse', 'pearson_r', 'ccc')))


def previous_entries(folder: Path, settings: dict) -> list:
    """The entries of ``folder/records.jsonl`` written by an earlier run whose config.yaml
    equals ``settings`` but for RESUME_MAY_DIFFER; [] when the folder has none."""
    records = folder / 'records.jsonl'
    if not records.exists():
        return []
    try:
        earlier = yaml.safe_load((folder / 'config.yaml').read_text()) or {}
    except (OSError, yaml.YAMLError) as error:
        raise StarsError(f'--resume: cannot read the earlier run\'s config.yaml: {error}') from error
    keys = (earlier.keys() | settings.keys()) - set(RESUME_MAY_DIFFER)
    differ = sorted(k for k in keys if earlier.get(k) != settings.get(k))
    if differ:
        raise StarsError(f'--resume: {folder} holds a run with other settings ({", ".join(differ)} differ)')
    entries = []
    for line in records.read_text().splitlines():
        try:
            entries.append(json.loads(line))
        except json.JSONDecodeError:  # the last line, cut short when the run was stopped
            break
    return entries


# -- tables -----------------------------------------------------------------------------
def _number(value: float, digits: int) -> str:
    return '—' if value is None or not math.isfinite(value) else f'{value:.{digits}f}'


def _short(value: float) -> str:
    """``.024`` as in the paper's tables."""
    text = _number(value, 3)
    return text.replace('0.', '.', 1) if text.startswith(('0.', '-0.')) else text


def _p(value: float) -> str:
    if value is None or not math.isfinite(value):
        return '—'
    return '< 0.001' if value < 0.001 else f'{value:.3f}'


def _digits(metric: str) -> int:
    return 4 if metric in ('mse', 'rmse') else 3


def _chosen(entries: list) -> str:
    """The candidates a model took over the folds, most frequent first: '(10, 40) lr 0.001 ×3'."""
    counts = collections.Counter((settings_key(e.get('settings', {})), e['T1'], e['T2']) for e in entries)
    parts = []
    for (settings, t1, t2), count in counts.most_common():
        values = ' '.join(f'{k} {v:g}' if isinstance(v, float) else f'{k} {v}' for k, v in json.loads(settings).items())
        parts.append(f"({t1}, {t2}){' ' + values if values else ''}{f' ×{count}' if len(counts) > 1 else ''}")
    return '; '.join(parts)


def results_table(result, error: str, labels=None, extra=None) -> list[str]:
    """Mean ± sd per model (those in ``labels``, default all); ``extra`` is (headings,
    label -> cells) for the last columns, default the settings each model took."""
    metrics = (error, 'pearson_r', 'ccc')
    final = by_model(result.final())
    specs = {spec.label: spec for spec in model_specs(result.config)}

    def chosen(label):
        spec = specs[label]
        if spec.variant == 'population_mean':
            return ['—']
        return [f'as {spec.follows}' if spec.follows else _chosen(final[label])]
    headings, cells = extra or (['settings (per fold)'], chosen)
    lines = ['| Model | ' + ' | '.join([METRIC_NAMES[m] for m in metrics] + headings) + ' |',
             '|' + ' --- |' * (1 + len(metrics) + len(headings))]
    for label in specs:
        entries = final.get(label, [])
        if not entries or (labels is not None and label not in labels):
            continue
        lines.append(f'| {label} | ' + ' | '.join([format_mean_sd([e[m] for e in entries], _digits(m))
                                                    for m in metrics] + cells(label)) + ' |')
    return lines


def selection_sentence(config) -> str:
    """How the settings were chosen, said only as far as a choice was made."""
    searched = {family: space for family, space in config.search.items() if any(len(v) > 1 for v in space.values())}
    if len(config.grid) == 1 and not searched:
        fixed = ', '.join(f'{family}: {space}' for family, space in config.search.items())
        return (f'No setting was chosen: every model trained with (T1, T2) = {tuple(config.grid[0])}'
                f"{' and ' + fixed if fixed else ''} and the experiment's other settings.")
    spaces = '; '.join(f'{family}: {space}' for family, space in searched.items())
    return (f'Settings chosen per outer fold by {config.inner_folds}-fold inner validation on that fold\'s '
            f'training rows (lowest z-RMSE), from (T1, T2) in {[list(p) for p in config.grid]}'
            f"{' and ' + spaces if spaces else ''}; ablations take their StARS model's choice.")


def ablation_table(result, tests: list, error: str) -> list[str]:
    """Per ablation backbone: the baselines, base, StARS and each ablation, with the
    corrected test of each against that backbone's base."""
    metrics = (error, 'pearson_r', 'ccc')
    lines = []
    for backbone in result.config.ablation_backbones:
        found = {(t['model'], t['metric']): t for t in tests if t['backbone'] == backbone}

        def against_base(label):
            return ['—' if (t := found.get((label, m))) is None else f"{t['delta']:+.{_digits(m)}f}, {_p(t['p_holm'])}"
                    for m in metrics]
        labels = [s.label for s in model_specs(result.config) if s.backbone in (backbone, None)]
        headings = [f'Δ{METRIC_NAMES[m]} vs base, Holm p' for m in metrics]
        lines += [f'### {DISPLAY.get(backbone, backbone)}', '',
                  *results_table(result, error, labels, (headings, against_base)), '']
    return lines


def recipe_table(tests: list, error: str) -> list[str]:
    """One row per shipped model against its hold-out recipe row, with every fold's Δ."""
    lines = [f'| Model | Δ{METRIC_NAMES[error]} | t | Holm p | at or below in folds | Δ per fold |',
             '| --- | --- | --- | --- | --- | --- |']
    for t in tests:
        folds = ', '.join(f"{f['fold']} {f['delta']:+.{_digits(error)}f}" for f in t['folds'])
        lines.append(f"| {t['model']} | {t['delta']:+.{_digits(error)}f} | {_number(t['t'], 2)} | "
                     f"{_p(t['p_holm'])} | {t['at_or_below']} of {len(t['folds'])} | {folds} |")
    return lines


def tests_table(tests: list, error: str) -> list[str]:
    """One row per backbone of ``tests``; a column names the reference when the tests carry one."""
    metrics = (error, 'pearson_r', 'ccc')
    present = [m for m in metrics if any(t['metric'] == m for t in tests)]
    if not present:
        return ['(no backbone has both variants: no paired tests)']
    df = tests[0]['df']
    against = any('reference' in t for t in tests)
    head = ('against | ' if against else '') + ' | '.join(f'Δ{METRIC_NAMES[m]} | t({df}) | Holm p' for m in present)
    lines = [f'| Backbone | {head} |',
             '| --- | ' + ' | '.join('---' for _ in range(3 * len(present) + against)) + ' |']
    for backbone in dict.fromkeys(t['backbone'] for t in tests):
        cells = [next(t['reference'] for t in tests if t['backbone'] == backbone)] if against else []
        for metric in present:
            found = [t for t in tests if t['backbone'] == backbone and t['metric'] == metric]
            if found:
                t = found[0]
                cells += [f"{t['delta']:+.{_digits(metric)}f}", _number(t['t'], 2), _p(t['p_holm'])]
            else:
                cells += ['—', '—', '—']
        lines.append(f'| {DISPLAY.get(backbone, backbone)} | ' + ' | '.join(cells) + ' |')
    return lines


def comparison_table(result, error: str, name: str) -> list[str]:
    """base → StARS per backbone, at the paper's precision (the layout of its table)."""
    metrics = (error, 'pearson_r', 'ccc')
    final = by_model(result.final())
    lines = [f'| {name}, this run | ' + ' | '.join(f'{METRIC_NAMES[m]} base → StARS' for m in metrics) + ' |',
             '| --- | ' + ' | '.join('---' for _ in metrics) + ' |']
    for backbone in result.config.backbones:
        label = DISPLAY.get(backbone, backbone)
        base, stars = final.get(f'{label} base'), final.get(f'{label} StARS')
        if base is None or stars is None:
            continue
        cells = [f"{_short(mean_sd([e[m] for e in base])[0])} → {_short(mean_sd([e[m] for e in stars])[0])}"
                 for m in metrics]
        lines.append(f'| {label} | ' + ' | '.join(cells) + ' |')
    return lines if len(lines) > 2 else []


def sparsity_table(summary: dict, error: str) -> list[str]:
    fractions = sorted({f for by_fraction in summary.values() for f in by_fraction})
    lines = ['| Model | ' + ' | '.join(f'{f:g}' for f in fractions) + ' |',
             '| --- | ' + ' | '.join('---' for _ in fractions) + ' |']
    for label, by_fraction in summary.items():
        cells = [format_mean_sd(by_fraction[f][error], _digits(error)) if f in by_fraction else '—'
                 for f in fractions]
        lines.append(f'| {label} | ' + ' | '.join(cells) + ' |')
    return lines


def timing_table(timing: dict, load_seconds: float) -> list[str]:
    wall = timing['wall_seconds']
    busy = timing['worker_seconds'] or math.nan
    if timing['resumed_fits']:
        use = (f"{timing['resumed_fits']} fits came from the earlier run's records.jsonl (--resume), so the "
               f"wall time is this run's alone; the worker-seconds ({busy:.0f}) are every fit's, as measured.")
    else:
        use = (f"Fits kept the workers busy {timing['utilisation']:.0%} of the wall time ({busy:.0f} "
               'worker-seconds); the rest is process start-up, fold set-up and the tail where fewer fits '
               'than workers remain.')
    lines = [f"Wall time {wall / 60:.1f} min ({wall:.0f} s) with {timing['jobs']} job(s) × "
             f"{timing['threads_per_job']} torch thread(s); loading and featurising the data took "
             f"{load_seconds:.1f} s before that. {use}", '',
             '| Stage | worker-seconds | share |', '| --- | --- | --- |']
    names = {'inner': 'inner selection', 'final': 'final fit on the outer-train pool',
             'sweep': 'sparsity sweep (fractions < 1)'}
    for stage, seconds in timing['by_stage'].items():
        lines.append(f'| {names.get(stage, stage)} | {seconds:.0f} | {seconds / busy:.0%} |')
    lines += ['', '| Model | selection s | final s | sweep s | s/epoch (full pool) |',
              '| --- | --- | --- | --- | --- |']
    for label, stages in timing['by_model'].items():
        per_epoch = timing['seconds_per_epoch_full_pool'].get(label)
        lines.append(f"| {label} | {stages.get('inner', 0):.0f} | {stages.get('final', 0):.1f} | "
                     f"{stages.get('sweep', 0):.1f} | {_number(per_epoch, 3)} |")
    return lines


def write_tables(path: Path, result, tests, timing, load_seconds, header: dict) -> None:
    config = result.config
    error = config.error
    k = len(result.folds)
    lines = [f"# {config.name}: {result.protocol} protocol", '',
             f"Command: `{header['command']}`  ", f"Data: {header['data']}  ",
             f"Commit: {header['git']['commit']}{' (uncommitted changes)' if header['git']['dirty'] else ''}  ",
             f"Machine: {header['machine']['processor']}, {header['machine']['cpus']} CPUs, "
             f"torch {header['machine']['torch']}; training on {header['machine']['device']}"
             f"{' (' + header['machine']['cuda_device'] + ')' if 'cuda_device' in header['machine'] else ''}; "
             f"load average at start {header['load_start']}", '',
             f'## Results ({k} outer folds; mean ± sd over folds)', '',
             *results_table(result, error), '',
             'Metrics macro-averaged over actions on the rating scale, predictions clipped to it; a row '
             'of the protocol is an example (one user\'s ratings of one scene, every action). '
             + selection_sentence(config), '',
             '## Paired tests, StARS − base', '',
             *tests_table(tests, error), '',
             'Bouckaert–Frank corrected resampled t-test (variance × (1/k + n_test/n_train)), two-sided; '
             'p Holm-adjusted over the backbones within each metric. '
             f'Negative Δ{METRIC_NAMES[error]} and positive Δr, ΔCCC favour StARS.', '']
    if header['peer_tests']:
        lines += ['## StARS − the best peer library', '', *tests_table(header['peer_tests'], error), '',
                  'Per backbone, the peer with the lowest mean error over the outer folds among the '
                  'content-free ones and myFM on that backbone\'s h_i; the same test, Holm over the backbones.',
                  '']
    edge = grid_edge(result)
    if edge['choices']:
        lines += [f"The base and StARS selections chose T2 = {edge['top_T2']}, the top of the grid, in "
                  f"{edge['at_top']} of {edge['choices']} choices.", '']
    comparison = comparison_table(result, error, config.name)
    if comparison:
        lines += ['## base → StARS at the paper\'s precision', '', *comparison, '']
    if config.ablation_backbones:
        lines += ['## Ablation: the parts of StARS', '', *ablation_table(result, header['ablation_tests'], error),
                  'Each ablation is StARS with the named part held at zero (or items keyed by the numeric '
                  'identifier prefix), trained with the full StARS model\'s choice of settings in each fold. '
                  'Δ against the backbone\'s base, corrected resampled t-test, Holm over the models of one '
                  'backbone and metric.', '']
    if header.get('recipe_tests'):
        lines += ['## The shipped recipe against its hold-out fit', '',
                  *recipe_table(header['recipe_tests'], error), '',
                  f'Δ{METRIC_NAMES[error]}: the shipped model (the refit on every training row) less the '
                  'hold-out fit with its own prior (the model the recipe before the refit shipped), on the '
                  'same test rows, from the same fit; the corrected test, Holm over the rows.', '']
    summary = sparsity_summary(result)
    if summary:
        lines += [f'## Sparsity: {METRIC_NAMES[error]} against the training fraction', '',
                  *sparsity_table(summary, error), '',
                  'Fractions sampled without replacement from each outer-train pool (nested), '
                  'scored on the fixed outer test fold; plots: ' +
                  ', '.join(f'`sparsity_{m}.png`' for m in (error, 'pearson_r', 'ccc')) + '.', '']
    diverged = [r for r in result.records if 'error' in r]
    if diverged:
        lines += ['## Diverged fits', ''] + [f"- {r['model']} fold {r['fold']} fraction {r['fraction']}: {r['error']}"
                                             for r in diverged] + ['']
    lines += ['## Where the time goes', '', *timing_table(timing, load_seconds), '']
    path.write_text('\n'.join(lines))


def plot_sparsity(folder: Path, summary: dict, error: str) -> list[str]:
    """One PNG per metric, one panel per swept backbone (base, StARS and the baselines)."""
    plt = pyplot()
    panels = {}
    for label in summary:
        backbone = label.rsplit(' ', 1)[0] if label.endswith((' base', ' StARS')) else None
        panels.setdefault(backbone, []).append(label)
    baselines = panels.pop(None, [])
    if not panels:
        panels = {'baselines': []}
    written = []
    for metric in (error, 'pearson_r', 'ccc'):
        figure, axes = plt.subplots(1, len(panels), figsize=(4.5 * len(panels), 3.6), squeeze=False)
        for axis, (backbone, labels) in zip(axes[0], panels.items()):
            for label in labels + baselines:
                fractions = list(summary[label])
                stats = [mean_sd(summary[label][f][metric]) for f in fractions]
                means = np.array([s[0] for s in stats])
                sds = np.array([s[1] for s in stats])
                if np.isnan(means).all():
                    continue
                mean_band(axis, fractions, means, sds, label)
            axis.set_title(backbone)
            label_axis(axis, 'training fraction of the outer-train pool', METRIC_NAMES[metric], legend_size=7)
        written.append(save_png(figure, folder / f'sparsity_{metric}.png'))
    return written


def write_csv(path: Path, rows: list, columns) -> None:
    with path.open('w', newline='') as handle:
        writer = csv.DictWriter(handle, fieldnames=columns, extrasaction='ignore')
        writer.writeheader()
        writer.writerows(rows)


def json_default(value):
    """What ``json.dumps`` writes for numpy values and other objects of a record."""
    if isinstance(value, (np.integer, np.floating)):
        return value.item()
    raise TypeError(f'cannot write {type(value).__name__} as JSON')


def report_failures(folder: Path, result, shown: int = 50) -> None:
    """Write ``failed.jsonl`` and tell on stderr which fits failed and which selections
    they stopped (the first ``shown`` fits; all are in the file)."""
    with (folder / 'failed.jsonl').open('w') as stream:
        for entry in result.failed:
            stream.write(json.dumps(entry, default=json_default) + '\n')
    lines = [f'error: {len(result.failed)} fit(s) failed:', *(f"  {e['fit']}: {e['error']}"
                                                               for e in result.failed[:shown])]
    if len(result.failed) > shown:
        lines.append(f"  ... and {len(result.failed) - shown} more in {folder / 'failed.jsonl'}")
    lines += [f"  {e['model']} fold {e['fold']}: no settings chosen (an inner fit failed), so its final fit and "
              'those of the models that follow its choice did not run' for e in result.unchosen]
    lines.append(f'No tables: they would compare models on different folds. records.jsonl keeps the '
                 f'{len(result.records) + len(result.inner)} entries that completed; run again with --resume to run '
                 'the rest.')
    print('\n'.join(lines), file=sys.stderr)


def write_results(folder: Path, result, config, header: dict, command: str, protocol: str,
                  load_seconds: float) -> None:
    """Every summary file of a run whose fits all completed (``SUMMARY_FILES``)."""
    tests = paired_tests(result, (config.error, 'pearson_r', 'ccc'))
    header['ablation_tests'] = ablation_tests(result, (config.error, 'pearson_r', 'ccc'))
    header['peer_tests'] = peer_tests(result, (config.error, 'pearson_r', 'ccc'))
    header['recipe_tests'] = recipe_tests(result, config.error)
    timing = {**time_accounting(result), 'load_seconds': load_seconds,
              'load_average_end': [round(v, 2) for v in os.getloadavg()]}
    write_csv(folder / 'folds.csv', [{**r, 'settings': settings_key(r['settings'])} for r in result.records],
              RECORD_COLUMNS)
    write_csv(folder / 'selection.csv', result.selection, SELECTION_COLUMNS)
    write_csv(folder / 'tests.csv', tests, ('backbone', 'metric', 'delta', 't', 'df', 'p', 'p_holm'))
    summary = sparsity_summary(result)
    plots = plot_sparsity(folder, summary, config.error) if summary else []
    write_tables(folder / 'tables.md', result, tests, timing, load_seconds, header)
    (folder / 'results.json').write_text(json.dumps(
        {'command': command, 'protocol': protocol, 'config': config.to_dict(), 'folds': result.folds,
         'records': result.records, 'inner': result.inner, 'selection': result.selection,
         'choices': result.choices, 'tests': tests, 'ablation_tests': header['ablation_tests'],
         'peer_tests': header['peer_tests'], 'recipe_tests': header['recipe_tests'],
         'grid_edge': grid_edge(result), 'timing': timing,
         'plots': plots, 'git': header['git'], 'machine': header['machine']},
        indent=1, default=json_default))
