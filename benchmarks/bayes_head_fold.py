"""The Bayesian head (``training.posterior_sweeps``, issue 33) on one outer fold of SocNav1.

The first outer fold of ``config/eval_socnav1_peers.yaml``'s rows protocol (its own fold
code and seed), GAT StARS with the settings that run chose there (T1 = 10, T2 = 40, lr 1e-3,
embedding_l2 0.01), trained once; then, from those trained weights, the posterior head for
each sweep count. Scored on the fold's test rows as the protocol scores a fit (macro MSE over
actions, rating scale): (a) the point estimate, (b) the posterior-mean model (what would be
served), (c) the prediction averaged over the kept draws (not servable at today's cost: for
comparison). The issue's figures for this fold: StARS 0.01619-0.01633, myFM on the base
model's h_i 0.01511.

    OMP_NUM_THREADS=1 python benchmarks/bayes_head_fold.py --sweeps 50 200
"""
from __future__ import annotations

import argparse
import json
import logging
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch

from stars_ros.data.ratings import load_dataset
from stars_ros.evaluation.folds import make_folds
from stars_ros.evaluation.protocol import ProtocolConfig
from stars_ros.model.metrics import regression_report
from stars_ros.model.posterior import Observations, encoded, posterior_head, training_observations
from stars_ros.model.training import StarsTrainer

REPO = Path(__file__).resolve().parents[1]


def query_observations(trainer: StarsTrainer, data, rows: np.ndarray) -> Observations:
    """The test rows as the sampler's queries (their scores are not read)."""
    model = trainer.model
    items = data.item_keys(trainer.config.model.item_key)
    scenes = data.scenes[rows]
    return Observations(trainer.user_index(data.users[rows]), trainer.scene_index([items[s] for s in scenes]),
                        torch.from_numpy(data.actions[rows]), encoded(model, data.store, torch.from_numpy(scenes)),
                        torch.zeros(len(rows), dtype=torch.float64))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--data', default='socnav1')
    parser.add_argument('--protocol', default='config/eval_socnav1_peers.yaml', help='relative to the repository root')
    parser.add_argument('--backbone', default='gat')
    parser.add_argument('--epochs', type=int, nargs=2, default=(10, 40), metavar=('T1', 'T2'))
    parser.add_argument('--embedding-l2', type=float, default=0.01)
    parser.add_argument('--sweeps', type=int, nargs='+', default=(50, 200))
    parser.add_argument('--burn-in', type=int, default=20)
    parser.add_argument('--out', default=str(REPO / 'results/bayes-head-socnav1-fold0'))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format='%(asctime)s %(message)s')
    torch.set_num_threads(1)

    data = load_dataset(args.data)
    protocol = ProtocolConfig.from_yaml(REPO / args.protocol)
    fold = make_folds(data, 'rows', protocol.folds, protocol.seeds[0])[0]
    config = protocol.experiment_config(args.backbone, 'stars', {'embedding_l2': args.embedding_l2}).replace(
        training={'pretrain_epochs': args.epochs[0], 'joint_epochs': args.epochs[1], 'threads': 1})
    y, actions = data.scores[fold.test], data.actions[fold.test]

    started = time.perf_counter()
    trainer = StarsTrainer(config).fit(data, fold.train)
    fit_seconds = time.perf_counter() - started
    model = trainer.model
    trained = {name: value.clone() for name, value in model.state_dict().items()}
    point = regression_report(y, trainer.predict_rows(data, fold.test), actions)
    print(f'point estimate: test MSE {point["mse"]:.5f} (fit {fit_seconds:.0f} s)', flush=True)

    observations = training_observations(model, data.store, trainer.training_set(data, fold.train))
    queries = query_observations(trainer, data, fold.test)
    heads = []
    for sweeps in args.sweeps:
        model.load_state_dict(trained)
        summary = posterior_head(model, observations, sweeps, args.burn_in, config.training.seed, queries)
        averaged_z = summary.averaged_queries.float().unsqueeze(1).expand(-1, model.n_actions)  # each row: its action
        averaged = trainer.clip(model.to_rating_scale(averaged_z).numpy().astype(np.float64))
        averaged = averaged[np.arange(len(y)), actions]
        head = {'sweeps': sweeps, 'burn_in': args.burn_in, 'sampler_seconds': summary.seconds,
                'noise_precision': summary.noise_precision, 'plug_in_gap_z_train': summary.plug_in_gap,
                'posterior_mean': regression_report(y, trainer.predict_rows(data, fold.test), actions),
                'averaged_prediction': regression_report(y, averaged, actions)}
        heads.append(head)
        print(f'{sweeps} sweeps ({args.burn_in} burn-in, {summary.seconds:.1f} s): posterior-mean model '
              f'{head["posterior_mean"]["mse"]:.5f}, averaged prediction {head["averaged_prediction"]["mse"]:.5f}, '
              f'plug-in gap {summary.plug_in_gap:.4f} z on training entries', flush=True)

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / 'results.json').write_text(json.dumps({
        'command': shlex.join(['python', *sys.argv]), 'protocol': args.protocol, 'fold': f'{protocol.seeds[0]}:0',
        'n_train': len(fold.train), 'n_test': len(fold.test), 'n_training_entries': len(observations.targets),
        'experiment': config.to_dict(), 'fit_seconds': fit_seconds, 'point_estimate': point, 'heads': heads,
        'issue_figures': {'stars': [0.01619, 0.01633], 'myfm_on_base_h': 0.01511}}, indent=2))
    print(f'wrote {out / "results.json"}')


if __name__ == '__main__':
    main()
