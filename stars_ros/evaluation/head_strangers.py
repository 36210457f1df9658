"""The posterior head for strangers on SocNav1: every outer fold of the cold-user protocol.

``results/socnav1-cold-user-bayes`` scores only the setting its inner selection chose (the
point estimate in 4 of 5 folds). This scores both in every outer fold of the same protocol
(``make_folds(data, 'cold-user', 5, 0)``, the folds that run used): the packaged settings
trained once per fold, scored as the point estimate, then with the posterior head applied to
those same trained weights (what a fit with ``posterior_sweeps`` returns). A test person is
unseen, so both serve them the zero row. Also the spread of the trained people's rows, rms
‖p_u‖, which the head's learned prior sets instead of ``embedding_l2``.
``offline_training.head_strangers`` is the command line.
"""
from __future__ import annotations

import numpy as np

from stars_ros.data.ratings import RatingData
from stars_ros.evaluation.folds import make_folds
from stars_ros.model.config import ExperimentConfig
from stars_ros.model.metrics import regression_report
from stars_ros.model.training import StarsTrainer


def row_spread(trainer: StarsTrainer, users: np.ndarray) -> float:
    """rms ‖p_u‖ over the trained people ``users``."""
    p = trainer.model.user_embedding.weight.detach()[trainer.user_index(np.unique(users))]
    return float(p.norm(dim=1).pow(2).mean().sqrt())


def compare(data: RatingData, config: ExperimentConfig, folds: int, seed: int, log=print) -> tuple[list, dict]:
    """(per fold, summary): the point estimate and the posterior head of ``config`` in every
    cold-user fold (``folds`` of them, dealt with ``seed``); ``log`` gets a line per fold."""
    point_config = config.replace(training={'posterior_sweeps': 0})
    rows = []
    for number, fold in enumerate(make_folds(data, 'cold-user', folds, seed)):
        y, actions = data.scores[fold.test], data.actions[fold.test]
        point = StarsTrainer(point_config).fit(data, fold.train)
        head = point.copy_into(StarsTrainer(config)).with_posterior_head(data, fold.train)  # a copy: point stays
        row = {'fold': number, 'test_people': sorted(map(str, np.unique(data.users[fold.test]))),
               'n_train': len(fold.train), 'n_test': len(fold.test),
               'point_mse': regression_report(y, point.predict_rows(data, fold.test), actions)['mse'],
               'head_mse': regression_report(y, head.predict_rows(data, fold.test), actions)['mse'],
               'point_rms_p': row_spread(point, data.users[fold.train]),
               'head_rms_p': row_spread(head, data.users[fold.train])}
        rows.append(row)
        log(f"fold {number} ({', '.join(row['test_people'])} held out): MSE point {row['point_mse']:.5f}, "
            f"head {row['head_mse']:.5f}; rms |p_u| {row['point_rms_p']:.2f} -> {row['head_rms_p']:.2f}")
    summary = {'point_mse': float(np.mean([r['point_mse'] for r in rows])),
               'head_mse': float(np.mean([r['head_mse'] for r in rows])),
               'head_better_in': sum(r['head_mse'] < r['point_mse'] for r in rows)}
    return rows, summary
