"""Two levers of StARS, seeds averaged and a longer budget, on a nested protocol run's choices.

For each backbone, reads a rows-protocol results folder (``--run BACKBONE=FOLDER``): its
config and, per outer fold, the settings and (T1, T2) that its StARS and its base took by
nested selection on that fold's training rows. On the same outer folds it trains that StARS
with ``--members`` seeds (``training.seed`` 0, 1, ...; seed 0 is the run's own seed) on the
outer-train pool and scores the mean of their predictions on the outer test rows. The number
of members is fixed beforehand, not chosen, so nothing here is chosen on test rows. Beside it:
one seed (member 0, retrained here), the mean of the first k members, the run's StARS and best
peer (their recorded per-fold scores), and with ``--peer-members K`` that peer averaged over K
seeds too (myFM on the h_i of base models trained with seeds 0..K-1 and base's choice), so that
the ensemble is also weighed against an ensemble. Paired tests: the corrected resampled t-test
on per-fold MSE, Holm over the backbones.

``--extra-epochs E`` trains every StARS member E joint epochs past the chosen T2: the budget
lever (a diagnostic: the test rows score it, nothing is chosen from it); one seed against the
run's recorded StARS is what the budget adds.

Each member's predictions are kept under ``predictions/`` in the output folder; a rerun
(``--resume``) trains only the missing ones. The summary is rewritten after every member.

    OMP_NUM_THREADS=1 python benchmarks/stars_levers.py --run gin=results/socnav1-bayes-rows \\
        --run graphsage=results/socnav1-bayes-rows --run gat=results/socnav1-bayes-gat-rows --jobs 2 \\
        --members 5 --peer-members 5 --out results/seed-ensemble-socnav1
"""
from __future__ import annotations

import argparse
import concurrent.futures as futures
import json
import logging
import multiprocessing
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from stars_ros.data.ratings import RatingData, load_dataset
from stars_ros.evaluation import peers
from stars_ros.evaluation.folds import make_folds
from stars_ros.evaluation.protocol import DISPLAY, EvaluationResult, ProtocolConfig
from stars_ros.evaluation.stats import corrected_resampled_ttest, holm
from stars_ros.evaluation.summaries import best_peer
from stars_ros.model.metrics import regression_report

REPO = Path(__file__).resolve().parents[1]
#: The paired comparisons (per-fold MSE, a − b), each Holm-adjusted over the backbones.
TESTS = (('ensemble - peer', 'ensemble_mse', 'peer_mse'), ('one seed - peer', 'one_seed_mse', 'peer_mse'),
         ('ensemble - one seed', 'ensemble_mse', 'one_seed_mse'),
         ("one seed - the run's StARS", 'one_seed_mse', 'run_stars_mse'),
         ('ensemble - peer ensemble', 'ensemble_mse', 'peer_ensemble_mse'),
         ('peer ensemble - peer', 'peer_ensemble_mse', 'peer_mse'))
_DATA: RatingData | None = None  # each worker's copy


def _hold(root: str) -> None:
    """Load the data once per worker process, with one torch thread."""
    global _DATA
    import torch
    torch.set_num_threads(1)
    _DATA = load_dataset(root)


def train_member(kind: str, experiment: dict, train: np.ndarray, test: np.ndarray) -> tuple[np.ndarray, float]:
    """One member's predictions for the ``test`` rows (``kind`` 'stars', or 'peer': myFM on
    the h_i of a base model trained with ``experiment``), and its seconds."""
    from stars_ros.model.config import ExperimentConfig
    from stars_ros.model.training import StarsTrainer
    started = time.perf_counter()
    if kind == 'peer':
        predictions, _ = peers.peer_predictions('myfm_encoder', '{}', experiment, _DATA, train, test)
    else:
        predictions = StarsTrainer(ExperimentConfig.from_dict(experiment)).fit(_DATA, train).predict_rows(_DATA, test)
    return predictions, time.perf_counter() - started


def read_run(folder: Path) -> EvaluationResult:
    """The run's config (trained on the CPU here), records and choices."""
    settings = yaml.safe_load((folder / 'config.yaml').read_text())
    if settings['protocol'] != 'rows':
        raise SystemExit(f'{folder}: a {settings["protocol"]} run; this reads rows-protocol runs')
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


def summarise(data, plan, args, out: Path, command: str, started: float) -> dict:
    """Per backbone and fold: one seed, the mean of the first k members, the run's StARS, the
    best peer (and its ensemble); the tests, once every fold of a backbone is in."""
    backbones = {}
    columns = {'one_seed_mse', 'ensemble_mse', 'run_stars_mse', 'peer_mse'}
    columns |= {'peer_ensemble_mse'} if args.peer_members else set()
    tests = [t for t in TESTS if {t[1], t[2]} <= columns and (args.members > 1 or 'ensemble_mse' not in t[1:])]
    for backbone, (folds, run_stars, peer_label, peer_mse) in plan.items():
        rows = []
        for fold_id, (fold, _, _) in folds.items():
            curve = mean_prediction_mse(data, out, backbone, 'stars', fold, fold_id, args.members)
            peer_curve = (mean_prediction_mse(data, out, backbone, 'peer', fold, fold_id, args.peer_members)
                          if args.peer_members else [])
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
    summary = {'command': command, 'members': args.members, 'peer_members': args.peer_members,
               'extra_epochs': args.extra_epochs, 'data': f'{data.source} (fingerprint {data.fingerprint[:12]})',
               'backbones': backbones, 'seconds_this_run': round(time.perf_counter() - started, 1)}
    (out / 'results.json').write_text(json.dumps(summary, indent=1) + '\n')
    return summary


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--run', action='append', required=True, metavar='BACKBONE=FOLDER',
                        help='a backbone and the rows-protocol results folder whose choices it takes')
    parser.add_argument('--members', type=int, default=5, help='StARS seeds averaged (default: %(default)s)')
    parser.add_argument('--peer-members', type=int, default=0,
                        help='seeds of myFM on base h_i averaged (default: %(default)s, none)')
    parser.add_argument('--extra-epochs', type=int, default=0,
                        help='joint epochs past the chosen T2 for every StARS member (default: %(default)s)')
    parser.add_argument('--data-root', default='socnav1')
    parser.add_argument('--jobs', type=int, default=1)
    parser.add_argument('--resume', action='store_true', help='keep the members already in the folder')
    parser.add_argument('--out', required=True, help='results folder (predictions/ and results.json)')
    args = parser.parse_args(argv)
    if args.members < 1 or args.peer_members < 0 or args.extra_epochs < 0:
        parser.error('--members must be positive, --peer-members and --extra-epochs not negative')
    logging.basicConfig(level=logging.WARNING, format='%(asctime)s %(message)s')
    started = time.perf_counter()
    out = Path(args.out)
    (out / 'predictions').mkdir(parents=True, exist_ok=True)
    if not args.resume:
        for stale in (out / 'predictions').glob('*.npy'):
            stale.unlink()
    data = load_dataset(args.data_root)
    command = shlex.join(['python', 'benchmarks/stars_levers.py', *(sys.argv[1:] if argv is None else argv)])
    plan, tasks = {}, []
    for spec in args.run:
        backbone, _, folder = spec.partition('=')
        run = read_run(REPO / folder)
        config = run.config
        if backbone not in config.backbones:
            raise SystemExit(f'{folder} has no backbone {backbone}')
        name = DISPLAY.get(backbone, backbone)
        choices = {(c['model'], c['fold']): c for c in run.choices}
        folds = {}
        for seed in config.seeds:
            for number, fold in enumerate(make_folds(data, 'rows', config.folds, seed)):
                fold_id = f'{seed}:{number}'
                folds[fold_id] = (fold, choices[f'{name} StARS', fold_id], choices[f'{name} base', fold_id])
        peer = best_peer(run, backbone)
        if args.peer_members and peer != peers.encoder_label(name):
            raise SystemExit(f'{folder}: the best peer for {backbone} is {peer}; --peer-members averages myFM on '
                             'base h_i only')
        plan[backbone] = (folds, recorded(run, f'{name} StARS'), peer, recorded(run, peer))
        for fold_id, (fold, stars, base) in folds.items():
            for kind, choice, members, extra in (('stars', stars, args.members, args.extra_epochs),
                                                 ('peer', base, args.peer_members, 0)):
                variant = 'stars' if kind == 'stars' else 'base'
                experiment = config.experiment_config(backbone, variant, choice['settings'])
                for member in range(members):
                    path = member_path(out, backbone, kind, fold_id, member)
                    if not path.exists():
                        training = {'pretrain_epochs': choice['T1'], 'joint_epochs': choice['T2'] + extra,
                                    'threads': 1, 'seed': member}
                        tasks.append((path, kind, experiment.replace(training=training).to_dict(), fold.train,
                                      fold.test))
    print(f'{len(tasks)} members to train with {args.jobs} job(s)', flush=True)
    with futures.ProcessPoolExecutor(args.jobs, mp_context=multiprocessing.get_context('spawn'),
                                     initializer=_hold, initargs=(args.data_root,)) as pool:
        running = {pool.submit(train_member, *task[1:]): task[0] for task in tasks}
        for future in futures.as_completed(running):
            predictions, seconds = future.result()
            np.save(running[future], predictions)
            print(f'{running[future].name}: {seconds:.0f} s', flush=True)
            summarise(data, plan, args, out, command, started)
    summary = summarise(data, plan, args, out, command, started)
    for backbone, entry in summary['backbones'].items():
        if 'peer_mse' in entry:
            print(f"{backbone}: the run's StARS {entry['run_stars_mse']:.5f}, one seed {entry['one_seed_mse']:.5f}, "
                  f"mean of {args.members} {entry['ensemble_mse']:.5f}, {entry['peer']} {entry['peer_mse']:.5f}")
            for name, _, _ in TESTS:
                if name in entry:
                    print(f"  {name}: {entry[name]['delta']:+.5f} (t {entry[name]['t']:.2f}, "
                          f"Holm p {entry[name]['holm_p']:.3f})")


if __name__ == '__main__':
    main()
