"""The posterior head for strangers on SocNav1: every outer fold of the cold-user protocol.

``results/socnav1-cold-user-bayes`` scores only the setting its inner selection chose (the
point estimate in 4 of 5 folds). This scores both in every outer fold of the same protocol
(``make_folds(data, 'cold-user', 5, 0)``, the folds that run used): the packaged settings
trained once per fold, scored as the point estimate, then with the posterior head applied to
those same trained weights (what a fit with ``posterior_sweeps`` returns). A test person is
unseen, so both serve them the zero row. Also the spread of the trained people's rows, rms
‖p_u‖, which the head's learned prior sets instead of ``embedding_l2``.

    OMP_NUM_THREADS=1 python benchmarks/head_strangers.py
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
from stars_ros.model.config import ExperimentConfig
from stars_ros.model.metrics import regression_report
from stars_ros.model.training import StarsTrainer

REPO = Path(__file__).resolve().parents[1]


def row_spread(trainer: StarsTrainer, users: np.ndarray) -> float:
    """rms ‖p_u‖ over the trained people ``users``."""
    p = trainer.model.user_embedding.weight.detach()[trainer.user_index(np.unique(users))]
    return float(p.norm(dim=1).pow(2).mean().sqrt())


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--config', default='config/socnav1_gat_posterior.yaml',
                        help='the head settings, relative to the repository root (default: %(default)s)')
    parser.add_argument('--folds', type=int, default=5)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--out', default=str(REPO / 'results/head-strangers-socnav1'))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format='%(asctime)s %(message)s')
    torch.set_num_threads(1)
    config = ExperimentConfig.from_yaml(REPO / args.config)
    point_config = config.replace(training={'posterior_sweeps': 0})
    data = load_dataset('socnav1')
    started = time.perf_counter()
    folds = []
    for number, fold in enumerate(make_folds(data, 'cold-user', args.folds, args.seed)):
        y, actions = data.scores[fold.test], data.actions[fold.test]
        point = StarsTrainer(point_config).fit(data, fold.train)
        head = point.copy_into(StarsTrainer(config)).with_posterior_head(data, fold.train)  # a copy: point stays
        row = {'fold': number, 'test_people': sorted(map(str, np.unique(data.users[fold.test]))),
               'n_train': len(fold.train), 'n_test': len(fold.test),
               'point_mse': regression_report(y, point.predict_rows(data, fold.test), actions)['mse'],
               'head_mse': regression_report(y, head.predict_rows(data, fold.test), actions)['mse'],
               'point_rms_p': row_spread(point, data.users[fold.train]),
               'head_rms_p': row_spread(head, data.users[fold.train])}
        folds.append(row)
        print(f"fold {number} ({', '.join(row['test_people'])} held out): MSE point {row['point_mse']:.5f}, "
              f"head {row['head_mse']:.5f}; rms |p_u| {row['point_rms_p']:.2f} -> {row['head_rms_p']:.2f}", flush=True)
    better = sum(r['head_mse'] < r['point_mse'] for r in folds)
    summary = {'point_mse': float(np.mean([r['point_mse'] for r in folds])),
               'head_mse': float(np.mean([r['head_mse'] for r in folds])), 'head_better_in': better}
    print(f"mean MSE point {summary['point_mse']:.5f}, head {summary['head_mse']:.5f}; "
          f"the head better in {better} of {len(folds)} folds")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    command = 'python benchmarks/head_strangers.py ' + shlex.join(sys.argv[1:] if argv is None else argv)
    (out / 'results.json').write_text(json.dumps(
        {'command': command.strip(), 'config': args.config, 'protocol': 'cold-user', 'folds_seed': args.seed,
         'folds': folds, 'summary': summary, 'seconds': round(time.perf_counter() - started, 1)}, indent=1) + '\n')


if __name__ == '__main__':
    main()
