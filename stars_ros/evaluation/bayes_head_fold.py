"""The Bayesian head (``training.posterior_sweeps``, issue 33) on one outer fold of SocNav1.

The first outer fold of a rows protocol (``config/eval_socnav1_peers.yaml``'s: its own fold
code and seed), a StARS model with the settings that run chose there (GAT, T1 = 10, T2 = 40,
lr 1e-3, embedding_l2 0.01), trained once; then, from those trained weights, the posterior
head for each sweep count. Scored on the fold's test rows as the protocol scores a fit (macro
MSE over actions, rating scale): (a) the point estimate, (b) the posterior-mean model (what
would be served), (c) the prediction averaged over the kept draws (not servable at today's
cost: for comparison). The issue's figures for this fold: StARS 0.01619-0.01633, myFM on the
base model's h_i 0.01511. ``offline_training.bayes_head_fold`` is the command line.
"""
from __future__ import annotations

import time

import numpy as np
import torch

from stars_ros.data.ratings import RatingData
from stars_ros.evaluation.folds import make_folds
from stars_ros.evaluation.protocol import ProtocolConfig
from stars_ros.model.metrics import regression_report
from stars_ros.model.posterior import Observations, encoded, posterior_head, training_observations
from stars_ros.model.training import StarsTrainer

#: The issue's figures for this fold, kept beside the results.
ISSUE_FIGURES = {'stars': [0.01619, 0.01633], 'myfm_on_base_h': 0.01511}


def query_observations(trainer: StarsTrainer, data, rows: np.ndarray) -> Observations:
    """The test rows as the sampler's queries (their scores are not read)."""
    model = trainer.model
    items = data.item_keys(trainer.config.model.item_key)
    scenes = data.scenes[rows]
    return Observations(trainer.user_index(data.users[rows]), trainer.scene_index([items[s] for s in scenes]),
                        torch.from_numpy(data.actions[rows]), encoded(model, data.store, torch.from_numpy(scenes)),
                        torch.zeros(len(rows), dtype=torch.float64))


def heads_on_first_fold(data: RatingData, protocol: ProtocolConfig, backbone: str, epochs: tuple[int, int],
                        embedding_l2: float, sweeps: list[int], burn_in: int, log=print) -> dict:
    """The point estimate and the posterior head for each of ``sweeps`` on ``protocol``'s
    first rows fold: the fold, the experiment, the fit's seconds and each head's scores."""
    fold = make_folds(data, 'rows', protocol.folds, protocol.seeds[0])[0]
    config = protocol.experiment_config(backbone, 'stars', {'embedding_l2': embedding_l2}).replace(
        training={'pretrain_epochs': epochs[0], 'joint_epochs': epochs[1], 'threads': 1})
    y, actions = data.scores[fold.test], data.actions[fold.test]

    started = time.perf_counter()
    trainer = StarsTrainer(config).fit(data, fold.train)
    fit_seconds = time.perf_counter() - started
    model = trainer.model
    trained = {name: value.clone() for name, value in model.state_dict().items()}
    point = regression_report(y, trainer.predict_rows(data, fold.test), actions)
    log(f'point estimate: test MSE {point["mse"]:.5f} (fit {fit_seconds:.0f} s)')

    observations = training_observations(model, data.store, trainer.training_set(data, fold.train))
    queries = query_observations(trainer, data, fold.test)
    heads = []
    for count in sweeps:
        model.load_state_dict(trained)
        summary = posterior_head(model, observations, count, burn_in, config.training.seed, queries)
        averaged_z = summary.averaged_queries.float().unsqueeze(1).expand(-1, model.n_actions)  # each row: its action
        averaged = trainer.clip(model.to_rating_scale(averaged_z).numpy().astype(np.float64))
        averaged = averaged[np.arange(len(y)), actions]
        head = {'sweeps': count, 'burn_in': burn_in, 'sampler_seconds': summary.seconds,
                'noise_precision': summary.noise_precision, 'plug_in_gap_z_train': summary.plug_in_gap,
                'posterior_mean': regression_report(y, trainer.predict_rows(data, fold.test), actions),
                'averaged_prediction': regression_report(y, averaged, actions)}
        heads.append(head)
        log(f'{count} sweeps ({burn_in} burn-in, {summary.seconds:.1f} s): posterior-mean model '
            f'{head["posterior_mean"]["mse"]:.5f}, averaged prediction {head["averaged_prediction"]["mse"]:.5f}, '
            f'plug-in gap {summary.plug_in_gap:.4f} z on training entries')
    return {'fold': f'{protocol.seeds[0]}:0', 'n_train': len(fold.train), 'n_test': len(fold.test),
            'n_training_entries': len(observations.targets), 'experiment': config.to_dict(),
            'fit_seconds': fit_seconds, 'point_estimate': point, 'heads': heads, 'issue_figures': ISSUE_FIGURES}
