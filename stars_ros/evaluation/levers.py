"""Two levers of StARS, seeds averaged and a longer budget, on a nested protocol run's choices.

For each backbone, reads a rows-protocol results folder: its config and, per outer fold, the
settings and (T1, T2) that its StARS and its base took by nested selection on that fold's
training rows. On the same outer folds it trains that StARS with ``members`` seeds
(``training.seed`` 0, 1, ...; seed 0 is the run's own seed) on the outer-train pool and scores
the mean of their predictions on the outer test rows. The number of members is fixed
beforehand, not chosen, so nothing here is chosen on test rows. Beside it: one seed (member 0,
retrained here), the mean of the first k members, the run's StARS and best peer (their
recorded per-fold scores), and with ``peer_members`` K that peer averaged over K seeds too
(myFM on the h_i of base models trained with seeds 0..K-1 and base's choice), so that the
ensemble is also weighed against an ensemble. Paired tests: the corrected resampled t-test on
per-fold MSE, Holm over the backbones.

``extra_epochs`` E trains every StARS member E joint epochs past the chosen T2: the budget
lever (a diagnostic: the test rows score it, nothing is chosen from it); one seed against the
run's recorded StARS is what the budget adds.

Each member's predictions are kept under ``predictions/`` in the output folder, so a rerun
trains only the missing ones; the summary (``results.json``) is rewritten after every member.
``offline_training.stars_levers`` is the command line.
"""
from __future__ import annotations

import concurrent.futures as futures
import json
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
import yaml

from stars_ros.data.ratings import RatingData
from stars_ros.evaluation import peers
from stars_ros.evaluation.executors import fit_executor, worker_data
from stars_ros.evaluation.folds import make_folds
from stars_ros.evaluation.protocol import DISPLAY, EvaluationResult, ProtocolConfig
from stars_ros.evaluation.stats import corrected_resampled_ttest, holm
from stars_ros.evaluation.summaries import best_peer
from stars_ros.errors import StarsError
from stars_ros.model.metrics import regression_report

#: The paired comparisons (per-fold MSE, a − b), each Holm-adjusted over the backbones.
TESTS = (('ensemble - peer', 'ensemble_mse', 'peer_mse'), ('one seed - peer', 'one_seed_mse', 'peer_mse'),
         ('ensemble - one seed', 'ensemble_mse', 'one_seed_mse'),
         ("one seed - the run's StARS", 'one_seed_mse', 'run_stars_mse'),
         ('ensemble - peer ensemble', 'ensemble_mse', 'peer_ensemble_mse'),
         ('peer ensemble - peer', 'peer_ensemble_mse', 'peer_mse'))


class Levers(NamedTuple):
    """How many StARS seeds are averaged, how many of the peer's (0: none), and the joint
    epochs every StARS member trains past its chosen T2."""

    members: int
    peer_members: int
    extra_epochs: int


def train_member(kind: str, experiment: dict, train: np.ndarray, test: np.ndarray,
                 data: RatingData | None = None) -> tuple[np.ndarray, float]:
    """One member's predictions for the ``test`` rows (``kind`` 'stars', or 'peer': myFM on
    the h_i of a base model trained with ``experiment``), and its seconds; in a
    ``fit_executor`` worker, or inline with ``data``."""
    from stars_ros.model.config import ExperimentConfig
    from stars_ros.model.training import StarsTrainer
    data = worker_data() if data is None else data
    started = time.perf_counter()
    if kind == 'peer':
        predictions, _ = peers.peer_predictions('myfm_encoder', '{}', experiment, data, train, test)
    else:
        predictions = StarsTrainer(ExperimentConfig.from_dict(experiment)).fit(data, train).predict_rows(data, test)
    return predictions, time.perf_counter() - started


def read_run(folder: Path) -> EvaluationResult:
    """The run's config (trained on the CPU here), records and choices."""
    settings = yaml.safe_load((folder / 'config.yaml').read_text())
    if settings['protocol'] != 'rows':
        raise StarsError(f'{folder}: a {settings["protocol"]} run; this reads rows-protocol runs')
    values = {k: v for k, v in settings.items() if k in ProtocolConfig.model_fields}
    config = ProtocolConfig.from_dict(values, {'experiment': {'training': {'device': 'cpu'}}})
    results = json.loads((folder / 'results.json').read_text())
    return EvaluationResult('rows', config, records=results['records'], choices=results['choices'])


def recorded(run: EvaluationResult, label: str) -> dict:
    """Per-fold MSE of the run's model ``label``."""
    return {r['fold']: r['mse'] for r in run.final() if r['model'] == label}


def member_path(out: Path, backbone: str, kind: str, fold_id: str, member: int) -> Path:
    return out / 'predictions' / f'{backbone}-{kind}-{fold_id.replace(":", "_")}-{member}.npy'


def mean_prediction_mse(data, out, backbone, kind, fold, fold_id, members) -> list | None:
    """MSE of the mean of the first k members, k = 1..members; None until all are in."""
    paths = [member_path(out, backbone, kind, fold_id, m) for m in range(members)]
    if not all(path.exists() for path in paths):
        return None
    kept = [np.load(path) for path in paths]
    y, actions = data.scores[fold.test], data.actions[fold.test]
    return [regression_report(y, np.mean(kept[:k], axis=0), actions)['mse'] for k in range(1, members + 1)]


def plan_members(data: RatingData, runs: list[tuple[str, Path]], levers: Levers, out: Path) -> tuple[dict, list]:
    """(plan, tasks): per backbone of ``runs`` (backbone, results folder), its folds with the
    run's choices, the run's StARS and best peer; and the members not yet in ``out``, each as
    (path, kind, experiment, train rows, test rows)."""
    plan, tasks = {}, []
    for backbone, folder in runs:
        run = read_run(folder)
        config = run.config
        if backbone not in config.backbones:
            raise StarsError(f'{folder} has no backbone {backbone}')
        name = DISPLAY.get(backbone, backbone)
        choices = {(c['model'], c['fold']): c for c in run.choices}
        folds = {}
        for seed in config.seeds:
            for number, fold in enumerate(make_folds(data, 'rows', config.folds, seed)):
                fold_id = f'{seed}:{number}'
                folds[fold_id] = (fold, choices[f'{name} StARS', fold_id], choices[f'{name} base', fold_id])
        peer = best_peer(run, backbone)
        if levers.peer_members and peer != peers.encoder_label(name):
            raise StarsError(f'{folder}: the best peer for {backbone} is {peer}; peer members average myFM on '
                             'base h_i only')
        plan[backbone] = (folds, recorded(run, f'{name} StARS'), peer, recorded(run, peer))
        for fold_id, (fold, stars, base) in folds.items():
            for kind, choice, members, extra in (('stars', stars, levers.members, levers.extra_epochs),
                                                 ('peer', base, levers.peer_members, 0)):
                variant = 'stars' if kind == 'stars' else 'base'
                experiment = config.experiment_config(backbone, variant, choice['settings'])
                for member in range(members):
                    path = member_path(out, backbone, kind, fold_id, member)
                    if not path.exists():
                        training = {'pretrain_epochs': choice['T1'], 'joint_epochs': choice['T2'] + extra,
                                    'threads': 1, 'seed': member}
                        tasks.append((path, kind, experiment.replace(training=training).to_dict(), fold.train,
                                      fold.test))
    return plan, tasks


def train_members(data: RatingData, tasks: list, jobs: int, on_member) -> None:
    """Train ``tasks`` (``plan_members``'), at most ``jobs`` at once, saving each member's
    predictions as it finishes and then calling ``on_member(path, seconds)``."""
    waiting, in_flight = list(tasks), {}
    with fit_executor(data, jobs, threads=1) as pool:
        while waiting or in_flight:
            while waiting and len(in_flight) < jobs:
                path, *task = waiting.pop(0)
                in_flight[pool.submit(train_member, *task)] = path
            finished, _ = futures.wait(list(in_flight), return_when=futures.FIRST_COMPLETED)
            for future in finished:
                path = in_flight.pop(future)
                predictions, seconds = future.result()
                np.save(path, predictions)
                on_member(path, seconds)


def summarise(data, plan, levers: Levers, out: Path, record: dict, started: float) -> dict:
    """Per backbone and fold: one seed, the mean of the first k members, the run's StARS, the
    best peer (and its ensemble); the tests, once every fold of a backbone is in. Written to
    ``out/results.json`` with ``record`` (the run's provenance) in front."""
    backbones = {}
    columns = {'one_seed_mse', 'ensemble_mse', 'run_stars_mse', 'peer_mse'}
    columns |= {'peer_ensemble_mse'} if levers.peer_members else set()
    tests = [t for t in TESTS if {t[1], t[2]} <= columns and (levers.members > 1 or 'ensemble_mse' not in t[1:])]
    for backbone, (folds, run_stars, peer_label, peer_mse) in plan.items():
        rows = []
        for fold_id, (fold, _, _) in folds.items():
            curve = mean_prediction_mse(data, out, backbone, 'stars', fold, fold_id, levers.members)
            peer_curve = (mean_prediction_mse(data, out, backbone, 'peer', fold, fold_id, levers.peer_members)
                          if levers.peer_members else [])
            if curve is None or peer_curve is None:
                continue
            rows.append({'fold': fold_id, 'n_train': len(fold.train), 'n_test': len(fold.test),
                         'one_seed_mse': curve[0], 'ensemble_mse': curve[-1], 'first_k_mse': curve,
                         'run_stars_mse': run_stars[fold_id], 'peer_mse': peer_mse[fold_id],
                         **({'peer_ensemble_mse': peer_curve[-1], 'peer_first_k_mse': peer_curve}
                            if peer_curve else {})})
        entry = {'peer': peer_label, 'folds': rows}
        if len(rows) == len(folds):
            n_train, n_test = [r['n_train'] for r in rows], [r['n_test'] for r in rows]
            entry.update({k: float(np.mean([r[k] for r in rows])) for k in sorted(columns)})
            entry['ensemble_below_peer_in'] = sum(r['ensemble_mse'] < r['peer_mse'] for r in rows)
            for name, a, b in tests:
                test = corrected_resampled_ttest([r[a] for r in rows], [r[b] for r in rows], n_train, n_test)
                entry[name] = {'delta': float(np.mean([r[a] - r[b] for r in rows])), 't': float(test.t),
                               'p': float(test.p)}
        backbones[backbone] = entry
    for name, _, _ in tests:
        done = [b for b, entry in backbones.items() if name in entry]
        for backbone, adjusted in zip(done, holm([backbones[b][name]['p'] for b in done])):
            backbones[backbone][name]['holm_p'] = float(adjusted)
    summary = {**record, 'members': levers.members, 'peer_members': levers.peer_members,
               'extra_epochs': levers.extra_epochs, 'data': f'{data.source} (fingerprint {data.fingerprint[:12]})',
               'backbones': backbones, 'seconds_this_run': round(time.perf_counter() - started, 1)}
    (out / 'results.json').write_text(json.dumps(summary, indent=1) + '\n')
    return summary


def run(data: RatingData, runs: list[tuple[str, Path]], levers: Levers, out: Path, jobs: int, record: dict,
        log=print) -> dict:
    """Train the members ``out`` lacks and summarise (``summarise``); ``log`` gets progress lines."""
    started = time.perf_counter()
    plan, tasks = plan_members(data, runs, levers, out)
    log(f'{len(tasks)} members to train with {jobs} job(s)')

    def on_member(path, seconds):
        log(f'{path.name}: {seconds:.0f} s')
        summarise(data, plan, levers, out, record, started)
    train_members(data, tasks, jobs, on_member)
    return summarise(data, plan, levers, out, record, started)
