"""What the tables of an evaluation are made of: records by model, the paired tests
(StARS against base, against the best peer library, ablations against base), how often a
choice sat at the top of the epoch grid, and the summaries of the sparsity sweep and of
where the time went."""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from stars_ros.evaluation.executors import METRICS
from stars_ros.evaluation.peers import PEERS
from stars_ros.evaluation.protocol import EvaluationResult
from stars_ros.evaluation.specs import BASELINE_LABELS, DISPLAY, model_specs
from stars_ros.evaluation.stats import corrected_resampled_ttest, holm


def _fold_order(entry: dict) -> tuple:
    return tuple(int(part) for part in entry['fold'].split(':'))


def by_model(records: list) -> dict:
    """model label -> records sorted by fold, in first-seen order."""
    grouped = {}
    for entry in records:
        grouped.setdefault(entry['model'], []).append(entry)
    return {label: sorted(entries, key=_fold_order) for label, entries in grouped.items()}


def corrected_test(result: EvaluationResult, label: str, reference: str, metric: str) -> dict | None:
    """``label`` − ``reference`` on ``metric`` over the outer folds (corrected resampled
    t-test); None when either lacks finite scores."""
    final = by_model(result.final())
    if label not in final or reference not in final:
        return None
    one, other = final[label], final[reference]
    if [e['fold'] for e in one] != [e['fold'] for e in other]:
        raise ValueError(f'{label} and {reference} were scored on different folds')
    values = ([e[metric] for e in one], [e[metric] for e in other])
    if not all(math.isfinite(v) for side in values for v in side):
        return None
    test = corrected_resampled_ttest(*values, [e['n_train'] for e in one], [e['n_test'] for e in one])
    return {'metric': metric, 'delta': test.delta, 't': test.t, 'df': test.df, 'p': test.p}


def paired_tests(result: EvaluationResult, metrics: Sequence[str]) -> list[dict]:
    """StARS − base per backbone and metric; Holm within each metric over the backbones."""
    tests = []
    for metric in metrics:
        family = []
        for backbone in result.config.backbones:
            name = DISPLAY.get(backbone, backbone)
            test = corrected_test(result, f'{name} StARS', f'{name} base', metric)
            if test is not None:
                family.append({'backbone': backbone, **test})
        for entry, adjusted in zip(family, holm([e['p'] for e in family])):
            entry['p_holm'] = float(adjusted)
        tests.extend(family)
    return tests


def best_peer(result: EvaluationResult, backbone: str) -> str | None:
    """The label of the peer library with the lowest mean error on the outer folds among those
    a backbone's StARS meets: the content-free ones and myFM on that backbone's h_i."""
    final = by_model(result.final())
    means = {spec.label: float(np.mean([e[result.config.error] for e in final[spec.label]]))
             for spec in model_specs(result.config)
             if spec.variant in PEERS and spec.backbone in (None, backbone) and spec.label in final}
    means = {label: value for label, value in means.items() if math.isfinite(value)}
    return min(means, key=means.get) if means else None


def peer_tests(result: EvaluationResult, metrics: Sequence[str]) -> list[dict]:
    """StARS − the best peer (``best_peer``) per backbone and metric; Holm within each metric
    over the backbones."""
    tests = []
    for metric in metrics:
        family = []
        for backbone in result.config.backbones:
            peer = best_peer(result, backbone)
            name = DISPLAY.get(backbone, backbone)
            if peer is not None and (test := corrected_test(result, f'{name} StARS', peer, metric)) is not None:
                family.append({'backbone': backbone, 'reference': peer, **test})
        for entry, adjusted in zip(family, holm([e['p'] for e in family])):
            entry['p_holm'] = float(adjusted)
        tests.extend(family)
    return tests


def grid_edge(result: EvaluationResult) -> dict:
    """How many of the base and StARS choices took the largest T2 of the grid: the grid may
    end too early when most do."""
    top = max(t2 for _, t2 in result.config.grid)
    variants = {spec.label for spec in model_specs(result.config) if spec.variant in ('base', 'stars')
                and not spec.follows}
    chosen = [c for c in result.choices if c['model'] in variants]
    return {'top_T2': top, 'at_top': sum(c['T2'] == top for c in chosen), 'choices': len(chosen)}


def ablation_tests(result: EvaluationResult, metrics: Sequence[str]) -> list[dict]:
    """Every model of an ablation backbone (MF, StARS and its ablations) against that
    backbone's base, per metric; Holm within each (backbone, metric) over the models."""
    tests = []
    labels = [spec.label for spec in model_specs(result.config)]
    for backbone in result.config.ablation_backbones:
        name = DISPLAY.get(backbone, backbone)
        compared = [label for label in labels if label.startswith(BASELINE_LABELS['mf'])
                    or (label.startswith(f'{name} ') and label != f'{name} base')]  # MF and its hold-out row
        for metric in metrics:
            family = [{'backbone': backbone, 'model': label, 'reference': f'{name} base', **test}
                      for label in compared
                      if (test := corrected_test(result, label, f'{name} base', metric)) is not None]
            for entry, adjusted in zip(family, holm([e['p'] for e in family])):
                entry['p_holm'] = float(adjusted)
            tests.extend(family)
    return tests


def recipe_tests(result: EvaluationResult, metric: str) -> list[dict]:
    """Each shipped model with a hold-out recipe row (``specs.HOLDOUT_RECIPE``) against that row on
    ``metric`` (an error): the corrected test, Holm over the rows, and per fold shipped − hold-out
    with whether the shipped model is at or below it."""
    final = by_model(result.final())
    family = []
    for spec in model_specs(result.config):
        test = corrected_test(result, spec.follows, spec.label, metric) if spec.from_holdout else None
        if test is not None:
            folds = [{'fold': a['fold'], 'delta': a[metric] - b[metric]}
                     for a, b in zip(final[spec.follows], final[spec.label])]
            family.append({'model': spec.follows, 'reference': spec.label, **test, 'folds': folds,
                           'at_or_below': sum(f['delta'] <= 0 for f in folds)})
    for entry, adjusted in zip(family, holm([e['p'] for e in family])):
        entry['p_holm'] = float(adjusted)
    return family


def sparsity_summary(result: EvaluationResult) -> dict:
    """model label -> fraction -> metric -> per-fold values, for swept models."""
    summary = {}
    for entry in result.records:
        summary.setdefault(entry['model'], {}).setdefault(entry['fraction'], {m: [] for m in METRICS})
        for metric in METRICS:
            summary[entry['model']][entry['fraction']][metric].append(entry[metric])
    return {label: dict(sorted(by_fraction.items())) for label, by_fraction in summary.items()
            if len(by_fraction) > 1}


def time_accounting(result: EvaluationResult) -> dict:
    """Worker seconds by stage and by model, s/epoch on full pools, and the wall time."""
    stages, models = {}, {}
    for entry in result.inner + result.records:
        stage = entry.get('stage', 'inner')
        seconds = entry['fit_seconds'] + entry['predict_seconds']
        stages[stage] = stages.get(stage, 0.0) + seconds
        models.setdefault(entry['model'], {}).setdefault(stage, 0.0)
        models[entry['model']][stage] += seconds
    order = [spec.label for spec in model_specs(result.config)]
    models = {label: models[label] for label in order if label in models}
    per_epoch = {}
    for label, entries in by_model([e for e in result.final() if e['epochs']]).items():
        per_epoch[label] = float(np.mean([e['fit_seconds'] / e['epochs'] for e in entries]))
    busy = sum(stages.values())
    return {'wall_seconds': result.wall_seconds, 'worker_seconds': busy, 'jobs': result.jobs,
            'threads_per_job': result.threads,
            'utilisation': busy / (result.wall_seconds * result.jobs) if result.wall_seconds and not result.resumed
            else math.nan, 'resumed_fits': result.resumed,
            'by_stage': stages, 'by_model': models, 'seconds_per_epoch_full_pool': per_epoch}
