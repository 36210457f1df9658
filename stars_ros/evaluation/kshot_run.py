"""The k-shot run: fit each fold's models, fold each held-out person in from k answers, and
score the methods and the calibration (``kshot_report`` summarises and writes them).
``offline_training.kshot`` is its command line (and says what the methods are); the
pieces it is built from (folds, pools, the fold-in design) are ``evaluation.kshot``.
"""
from __future__ import annotations

import itertools
import json
import time
from dataclasses import dataclass

import numpy as np

from stars_ros import StarsRecommender
from stars_ros.evaluation.executors import FitFailure, fit_outcome, worker_data
from stars_ros.evaluation.kshot import (Design, annotator_folds, coverage,
                                       known_split, random_sets, reveal_pools)
from stars_ros.model.config import ExperimentConfig
from stars_ros.model.metrics import regression_report
from stars_ros.model.scoring import served_predictions

METRICS = ('mse', 'pearson_r', 'ccc')
RANKING = 'regret'  # first-choice regret, where an example rates several actions
NAMES = {'mse': 'MSE', 'pearson_r': 'Pearson r', 'ccc': 'CCC', RANKING: 'first-choice regret'}
BASE_ENCODER = 'base encoder'  # the plain encoder fitted on a fold's training rows: a stranger's alternative


@dataclass(frozen=True)
class KShotSettings:
    """What a k-shot run does (the command line's options of the same names)."""

    folds: int
    seeds: tuple
    pool: int
    ks: tuple
    strategies: tuple
    retrain_ks: tuple | None
    known_test: float
    ridge_lambda: float
    max_train_rows: int | None = None
    random_sets: int = 1  # seeded sets of k pool examples random answers average over, beyond EXACT_SETS
    select: tuple = ()  # ((training setting, (candidate values, ...)), ...) chosen per fold inside its training people


SELECTABLE = ('lr', 'embedding_l2', 'weight_decay', 'pretrain_epochs', 'joint_epochs')  # training settings
SELECTION_SHARE = 0.2  # of a fold's training examples, held out to choose its settings
CALIBRATION_DRAWS = 64  # of the first strategy's draws at one k, seeded, whose intervals the calibration pools


def setting_candidates(select: tuple) -> list:
    """Every combination of ``select``'s values, as {setting: value}; [{}] when nothing is chosen."""
    return [dict(zip([name for name, _ in select], values))
            for values in itertools.product(*[values for _, values in select])]


def with_settings(experiment: dict, chosen: dict) -> dict:
    """``experiment`` (a config dict) with the training settings ``chosen``."""
    return {**experiment, 'training': {**experiment['training'], **chosen}}


def fit_rows(experiment: dict, train: np.ndarray, test: np.ndarray, keep: bool, data=None) -> dict:
    """One fit through the front door, the one recipe (in a ``fit_executor`` worker, or inline
    with ``data``): seconds, the served form's predictions on ``test`` (``model.scoring``), and
    with ``keep`` the fitted model itself (``model.fitted``, on the CPU, with the
    personalisation prior a checkpoint keeps), where the fold-in designs are computed."""
    data = worker_data() if data is None else data
    started = time.perf_counter()
    recommender = StarsRecommender(experiment).fit(data, train)
    seconds = time.perf_counter() - started
    return {'seconds': seconds, 'predictions': served_predictions(recommender.predictor, data, test),
            'recommender': recommender.fitted if keep else None}


def report(data, rows, predictions, examples) -> dict:
    """The metrics of ``predictions`` of ``rows``; ``examples``: ``data.examples`` (computed once)."""
    values = regression_report(data.scores[rows], predictions, data.actions[rows])
    regret = first_choice_regret(data.scores[rows], predictions, examples[rows])
    return values if regret is None else {**values, RANKING: regret}


def first_choice_regret(y: np.ndarray, p: np.ndarray, groups: np.ndarray) -> float | None:
    """Mean over ``groups`` of two or more rows (one person's ratings of one scene, every
    action: a choice the robot makes) of the best true score less the true score of the row
    predicted best; None where no group has two rows (one action, as SocNav1)."""
    order = np.lexsort((-np.asarray(p, dtype=np.float64), groups))
    grouped, scores = groups[order], np.asarray(y, dtype=np.float64)[order]
    starts = np.flatnonzero(np.r_[True, grouped[1:] != grouped[:-1]])
    several = np.diff(np.r_[starts, len(grouped)]) > 1
    if not several.any():
        return None
    return float(np.mean((np.maximum.reduceat(scores, starts) - scores[starts])[several]))


def plan_folds(settings, data) -> list:
    """(seed, fold id, held-out people, training rows, {person: Person}, left out, known
    people's test rows) of every fold of every seed. Half of the known people's held-out
    examples check their calibration; the other half trains (the recipe holds out its own
    ratings for the prior's noise, ``personalisation.recipe``)."""
    plan = []
    for seed in settings.seeds:
        for fold_id, held_out in enumerate(annotator_folds(data.users, settings.folds, seed)):
            train = np.flatnonzero(~np.isin(data.users, held_out))
            train, held = known_split(data, train, settings.known_test, seed)
            trained_too, known = known_split(data, held, 0.5, seed + 1)  # half to check their calibration
            train = np.sort(np.concatenate([train, trained_too]))
            if settings.max_train_rows and len(train) > settings.max_train_rows:
                train = np.sort(np.random.default_rng([seed, fold_id]).choice(train, settings.max_train_rows,
                                                                              replace=False))
            people, left_out = reveal_pools(data, held_out, settings.pool, seed)
            plan.append((seed, fold_id, held_out, train, people, left_out, known))
    return plan


def fit_rows_of(fold: tuple, k: int) -> np.ndarray:
    """The training rows at ``k``: the fold's, plus each held-out person's first k random answers."""
    _, _, _, train, people, _, _ = fold
    if k == 0:
        return train
    return np.sort(np.concatenate([train, *(person.rows(range(min(k,
                                                                  len(person.pool)))) for person in people.values())]))


def test_rows(people: dict, k: int) -> tuple[list, np.ndarray]:
    """(people who cover k, their test rows)."""
    covered = sorted(name for name, person in people.items() if len(person.pool) >= k)
    rows = np.concatenate([people[name].test for name in covered]) if covered else np.zeros(0, dtype=np.int64)
    return covered, np.sort(rows)


def _stacked(designs: list, empty: tuple) -> tuple:
    """The ``Design.rows`` of the union of pool examples whose designs are ``designs``."""
    if not designs:
        return empty
    return tuple(np.concatenate(parts) for parts in zip(*designs))


def score_fold(settings, data, design: Design, fold: tuple, outcomes: dict,
               base_encoder: dict | None = None) -> tuple[list, dict]:
    """(records, calibration parts) of one fold whose fits are ``outcomes`` {k: fit}, and
    ``base_encoder`` the fit of the plain encoder (``base`` variant) on the fold's training rows,
    scored beside them at every k as what a stranger could be served instead. A strategy's
    metrics at k are the mean over its answer sets: one per person for a question strategy,
    ``random_sets`` for random answers (set ``number`` of every covered person is one draw of
    the fold's metrics)."""
    seed, fold_id, held, _, people, _, known = fold
    examples = data.examples
    orders = {(name, strategy): design.reveal_order(person, strategy, max(settings.ks))
              for name, person in people.items() for strategy in settings.strategies if strategy != 'random'}
    pools = {name: [design.rows(rows) for rows in person.pool] for name, person in people.items()}
    tests = {name: design.rows(person.test) for name, person in people.items()}
    empty = design.rows(np.zeros(0, dtype=np.int64))
    methods = [f'fold-in ({s})' for s in settings.strategies]
    ridge = f'ridge λ={settings.ridge_lambda:g} ({settings.strategies[0]})'
    records, calibration = [], {'new': {}, 'known': None}
    for k in sorted(settings.ks):
        covered, rows = test_rows(people, k)
        if not len(rows):
            continue
        entry = {'seed': seed, 'fold': fold_id, 'k': k, 'held_out': held, 'covered': covered, 'n_test': len(rows),
                 'noise': [round(float(v), 6) for v in design.foldin.user_prior.noise],
                 'unpersonalised': report(data, rows, design.predict(rows, None), examples)}
        if base_encoder is not None:
            entry[BASE_ENCODER] = report(
                data, rows, base_encoder['predictions'][np.searchsorted(fold_test(fold), rows)], examples)
        ridge_predictions, nu = np.zeros(len(data)), design.foldin.user_prior.nu
        for strategy, method in zip(settings.strategies, methods):
            sets = ({name: random_sets(people[name], name, k, settings.random_sets, seed) for name in covered}
                    if strategy == 'random' else {name: [orders[name, strategy][:k]] for name in covered})
            draws = max(len(chosen) for chosen in sets.values())
            first = strategy == settings.strategies[0]  # its draws are the calibration's, its first the ridge's
            rng = np.random.default_rng([seed, fold_id, k])
            calibrated = (set(range(draws)) if draws <= CALIBRATION_DRAWS else
                          set(rng.choice(draws, CALIBRATION_DRAWS, replace=False).tolist()))
            predictions, reports = np.zeros(len(data)), []
            for number in range(draws):
                samples = {'y': [], 'mean': [], 'sd': []}
                for name in covered:
                    person, answered = people[name], sets[name][number % len(sets[name])]
                    calibrating = first and number in calibrated
                    theta, covariance = design.posterior_design(_stacked([pools[name][e] for e in answered], empty),
                                                                with_covariance=calibrating)
                    predictions[person.test] = design.predict_design(tests[name], theta)
                    if calibrating:
                        mean, sd = design.predictive_design(tests[name], theta, covariance)
                        samples['y'].append(data.scores[person.test])
                        samples['mean'].append(mean)
                        samples['sd'].append(sd)
                    if first and number == 0:
                        ridge_theta = (design.posterior(person.rows(answered), regularisation=settings.ridge_lambda)[0]
                                       if k else theta)
                        ridge_predictions[person.test] = design.predict_design(tests[name], ridge_theta)
                if samples['y']:
                    parts = calibration['new'].setdefault(k, [])
                    parts.append(coverage_part(*(np.concatenate(samples[key]) for key in ('y', 'mean', 'sd')), nu,
                                               len(parts)))
                reports.append(report(data, rows, predictions[rows], examples))
            entry[method] = {key: type(value)(np.mean([r[key] for r in reports])) for key, value in reports[0].items()}
        entry[ridge] = report(data, rows, ridge_predictions[rows], examples)
        if calibration['new'].get(k):  # this fold's alone, so that the pooled table hides no fold
            entry['calibration'] = pooled_coverage(calibration['new'][k])
        if k in outcomes:
            entry['retrained'] = report(data, rows, outcomes[k]['predictions'][np.searchsorted(fold_test(fold), rows)],
                                        examples)
        records.append(entry)
    if len(known):
        users = np.asarray(data.users[known])
        means, sds = np.zeros(len(known)), np.zeros(len(known))
        for name in sorted(set(users.tolist())):
            mine = users == name
            theta, covariance = design.posterior(np.zeros(0, dtype=np.int64), user_id=name)
            means[mine], sds[mine] = design.predictive(known[mine], theta, covariance, name)
        calibration['known'] = [coverage_part(data.scores[known], means, sds, design.foldin.user_prior.nu)]
    return records, calibration


def coverage_part(y: np.ndarray, mean: np.ndarray, sd: np.ndarray, nu: float, draw: int = 0) -> dict:
    """One draw's share of ratings ``y`` inside each central interval (``coverage``), with
    what pooling needs: its count, its summed sd, its ν and which of its fold's it is."""
    return {'coverage': coverage(y, mean, sd, nu), 'n': len(y), 'sd_sum': float(np.sum(sd)), 'nu': float(nu),
            'draw': int(draw)}


def retrained_ks(settings) -> list:
    """The ks whose fits run: 0 (the fold's model) and those of ``--retrain-ks`` (default: all)."""
    chosen = settings.ks if settings.retrain_ks is None else [k for k in settings.retrain_ks if k in settings.ks]
    return sorted({0, *chosen})


def fold_test(fold: tuple) -> np.ndarray:
    """Every test row of a fold's held-out people (what each fit predicts), sorted."""
    people = fold[4]
    return np.sort(np.concatenate([person.test for person in people.values()]))


def run(settings: 'KShotSettings', config, data, fits, log=print, on_fold=None) -> dict:
    """Every fold of the plan, its fits run by ``fits`` (an executor and how many fits run at
    once: ``offline_training.common.FitExecutor``); ``on_fold(records, fits, folds, failed,
    left_out, calibration)`` after each fold, so that partial results survive a stop."""
    plan = plan_folds(settings, data)
    executor = fits.executor
    submitted, selection = {}, {}

    def submit(folds):  # the largest fits first, so that the last wave is short
        experiments = {fold[:2]: with_settings(config.to_dict(), selection[fold[:2]]['chosen']) for fold in folds}
        order = sorted(((fold, k) for fold in folds for k in retrained_ks(settings)),
                       key=lambda f: -len(fit_rows_of(*f)))
        for fold, k in order:
            submitted[fold[:2] + (k,)] = executor.submit(fit_rows, experiments[fold[:2]], fit_rows_of(fold, k),
                                                         fold_test(fold), k == 0)
        for fold in folds:  # the plain encoder beside them, trained on what the fold's model is
            experiment = experiments[fold[:2]]
            if experiment['model']['strangers'] == 'base_encoder':  # the fold's model serves new people that one
                submitted[fold[:2] + (BASE_ENCODER,)] = submitted[fold[:2] + (0,)]
                continue
            submitted[fold[:2] + (BASE_ENCODER,)] = executor.submit(
                fit_rows, ExperimentConfig.from_dict(experiment).stranger_encoder().to_dict(), fit_rows_of(fold, 0),
                fold_test(fold), False)

    records, timings, folds, failed, left_out = [], [], {}, [], {}
    pooled = {'new': {}, 'known': []}
    try:
        selection.update(select_settings(settings, data, plan, config.to_dict(), executor, log))
        if fits.jobs > 1:  # every fit at once; inline, fold by fold, so that partial results come as it goes
            submit(plan)
        for fold in plan:
            seed, fold_id, held, train, people, skipped, known = fold
            if fits.jobs == 1:
                submit([fold])
            outcomes = {k: fit_outcome(submitted.pop((seed, fold_id, k)), f'seed {seed} fold {fold_id} k={k}')
                        for k in retrained_ks(settings)}
            base_encoder = fit_outcome(submitted.pop((seed, fold_id, BASE_ENCODER)),
                                       f'seed {seed} fold {fold_id} {BASE_ENCODER}')
            lost = [{'seed': seed, 'fold': fold_id, 'k': k, 'error': outcome.error}
                    for k, outcome in [*outcomes.items(), (BASE_ENCODER, base_encoder)]
                    if isinstance(outcome, FitFailure)]
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
            fold_records, calibration = score_fold(settings, data, Design(base['recommender'], data), fold, outcomes,
                                                   base_encoder)
            records += fold_records
            for k, parts in calibration['new'].items():
                pooled['new'].setdefault(k, []).extend(parts)
            if calibration['known'] is not None:
                pooled['known'].extend(calibration['known'])
            for entry in fold_records:
                log(f"seed {seed} fold {fold_id} k={entry['k']}: MSE " + '  '.join(
                    f"{m} {entry[m]['mse']:.4f}" for m in methods_of(entry)))
            if on_fold is not None:
                on_fold(records, timings, folds, failed, left_out, calibration_table(pooled))
    finally:
        executor.shutdown(cancel_futures=True)
    return {'records': records, 'fits': timings, 'folds': folds, 'failed': failed, 'left_out': left_out,
            'calibration': calibration_table(pooled),
            'selection': [{'seed': key[0], 'fold': key[1], **value} for key, value in selection.items()]}


def select_settings(settings, data, plan: list, experiment: dict, executor, log=print) -> dict:
    """{(seed, fold id): {'chosen': {setting: value}, 'validation_mse': {candidate: MSE}}}: per
    fold, each candidate of ``settings.select`` fitted on the fold's training rows less a seeded
    ``SELECTION_SHARE`` of their examples and scored on those (MSE on the rating scale), the
    lowest chosen. Only the fold's training people are seen; a candidate whose fit fails
    counts as infinite error."""
    candidates = setting_candidates(settings.select)
    # the validation people are trained ones: a plain encoder kept for strangers would go unused
    experiment = {**experiment, 'model': {**experiment['model'], 'strangers': 'prior_mean'}}
    if len(candidates) == 1:
        return {fold[:2]: {'chosen': candidates[0], 'validation_mse': {}} for fold in plan}
    pending = {}
    for fold in plan:
        inner, validation = known_split(data, fold[3], SELECTION_SHARE, fold[0] + 2)
        for number, candidate in enumerate(candidates):
            pending[fold[:2] + (number,)] = (executor.submit(fit_rows, with_settings(experiment, candidate), inner,
                                                             validation, False), validation)
    selection = {}
    for fold in plan:
        errors = {}
        for number, candidate in enumerate(candidates):
            future, validation = pending.pop(fold[:2] + (number,))
            outcome = fit_outcome(future, f'seed {fold[0]} fold {fold[1]} selection {candidate}')
            errors[json.dumps(candidate, sort_keys=True)] = (
                float('inf') if isinstance(outcome, FitFailure) else
                regression_report(data.scores[validation], outcome['predictions'], data.actions[validation])['mse'])
        best = min(errors, key=errors.get)
        selection[fold[:2]] = {'chosen': json.loads(best), 'validation_mse': errors}
        log(f'seed {fold[0]} fold {fold[1]}: chose {best} on its training people '
            f'(validation MSE {errors[best]:.4f})')
    return selection


def methods_of(entry: dict) -> list:
    """The scored methods of a record, in table order."""
    return [key for key in entry if isinstance(entry[key], dict) and 'mse' in entry[key]]


def pooled_coverage(parts: list) -> dict:
    """{level: coverage, 'n', 'draws', 'mean_sd', 'nu'} of ``coverage_part``s pooled, each
    weighted by its ratings; ``n``: the ratings of their draw 0s, ``draws``: how many parts."""
    sizes = np.array([p['n'] for p in parts])
    return {**{level: float(np.average([p['coverage'][level] for p in parts], weights=sizes))
               for level in parts[0]['coverage']},
            'n': int(sum(p['n'] for p in parts if p['draw'] == 0)), 'draws': len(parts),
            'mean_sd': float(sum(p['sd_sum'] for p in parts) / sizes.sum()),
            'nu': sorted({p['nu'] for p in parts})}


def calibration_table(pooled: dict) -> dict:
    """{'new': {k: {level: coverage}}, 'known': {level: coverage}, 'n': ...} pooled over folds
    and draws (``pooled_coverage``; each fold's intervals from its own prior's ν, each draw of a
    fold weighted by its ratings); ``n``: the ratings of one draw of every fold."""
    table = {'new': {str(k): pooled_coverage(parts) for k, parts in sorted(pooled['new'].items())}}
    if pooled['known']:
        table['known'] = pooled_coverage(pooled['known'])
    return table
