"""Fit and apply a StARS (or base) model on rating data: ``StarsRecommender``.

Training is two-step, as published: (1) ``pretrain_epochs`` of the encoder with a
temporary linear head on per-action z-scored targets, the head then discarded; (2)
``joint_epochs`` of the whole model. For the ``base`` variant the linear head is the
model's own head, so both steps train the same network. AdamW with gradient clipping;
seeds fixed; each distinct scene of a batch is encoded once.

``training.device`` may put the training on a GPU: the scene store stays on the CPU and
each batch is moved, and the model is moved back to the CPU when ``fit`` ends, so
everything after training (checkpoints, fold-in, serving) is the same as for a CPU fit.
"""
from __future__ import annotations

import logging
import math
from typing import Callable, Sequence

import numpy as np
import torch
from torch import nn

from .config import ExperimentConfig
from .data import RatingData
from .encoders import resolve_encoder
from .errors import ConfigError, StarsError, TrainingDivergedError
from .metrics import regression_report
from .model import UNKNOWN, StarsModel

log = logging.getLogger(__name__)
EVAL_BATCH = 2048


class NotFittedError(StarsError):
    """predict() was called before fit() or load()."""


def build_model(config: ExperimentConfig, feature_dim: int, input_kind: str,
                n_users: int, n_scenes: int, n_actions: int) -> StarsModel:
    """The untrained model a config describes (also used to rebuild one from a checkpoint)."""
    enc = config.encoder
    try:
        encoder = resolve_encoder(enc.name, feature_dim, config.model.dim, hidden=enc.hidden,
                                  layers=enc.layers, dropout=enc.dropout, **enc.options)
    except (ValueError, TypeError) as error:
        raise ConfigError(f'encoder: {error}') from error
    if encoder.input_kind != input_kind:
        raise ConfigError(f"encoder '{enc.name}' reads {encoder.input_kind} scenes, the data holds {input_kind} scenes")
    return StarsModel(encoder, n_users, n_scenes, n_actions, variant=config.model.variant,
                      feature_dim=feature_dim if input_kind == 'tabular' else None)


class StarsRecommender:
    """A model plus the vocabularies that map ids to its rows (LightFM/Surprise shape).

    Args:
        config (ExperimentConfig): encoder, model, training and split settings.
    """

    def __init__(self, config: ExperimentConfig):
        self.config = config
        self.model: StarsModel | None = None
        self.users: tuple = ()
        self.scene_keys: tuple = ()
        self.action_names: tuple = ()
        self.history: dict = {'pretrain': [], 'joint': []}

    # -- vocabularies -------------------------------------------------------------------
    def user_index(self, users: Sequence[str]) -> torch.Tensor:
        index = self._user_rows
        return torch.tensor([index.get(str(u), UNKNOWN) for u in users], dtype=torch.long)

    def scene_index(self, keys: Sequence) -> torch.Tensor:
        index = self._scene_rows
        return torch.tensor([index.get(k, UNKNOWN) if k is not None else UNKNOWN for k in keys], dtype=torch.long)

    def _set_vocabularies(self, users, scene_keys, action_names):
        self.users, self.scene_keys, self.action_names = tuple(users), tuple(scene_keys), tuple(action_names)
        self._user_rows = {u: i for i, u in enumerate(self.users)}
        self._scene_rows = {k: i for i, k in enumerate(self.scene_keys)}

    # -- training -----------------------------------------------------------------------
    def fit(self, data: RatingData, rows: np.ndarray | None = None,
            on_epoch: Callable[[str, int], None] | None = None) -> 'StarsRecommender':
        """Train on ``rows`` of ``data`` (all rows by default); returns self.

        ``on_epoch(stage, epoch)`` is called after each epoch ('pretrain' or 'joint',
        counted from 1), e.g. to score a learning curve; it must not train the model.
        """
        cfg = self.config.training
        device = torch.device(cfg.device)
        if device.type == 'cuda' and not torch.cuda.is_available():
            raise ConfigError(f"training.device is '{cfg.device}', but torch sees no CUDA GPU")
        torch.manual_seed(cfg.seed)
        torch.set_num_threads(cfg.threads)
        rng = np.random.default_rng(cfg.seed)
        rows = np.arange(len(data)) if rows is None else np.asarray(rows)
        if len(rows) == 0:
            raise ValueError('no training rows')

        train_scenes = np.unique(data.scenes[rows])
        self._set_vocabularies(sorted(set(data.users[rows].tolist())),
                               [data.scene_keys[s] for s in train_scenes], data.action_names)
        self.model = model = build_model(self.config, data.store.feature_dim, data.kind,
                                         len(self.users), len(self.scene_keys), len(self.action_names))
        self._set_statistics(data, rows, train_scenes)

        users = self.user_index(data.users[rows])
        scene_rows = self.scene_index([data.scene_keys[s] for s in data.scenes[rows]])
        store_rows = torch.from_numpy(data.scenes[rows])
        actions = torch.from_numpy(data.actions[rows])
        targets = model.to_z(torch.from_numpy(data.scores[rows]).float(), actions)
        # store_rows stays on the CPU: it indexes the CPU scene store
        batch = (users.to(device), scene_rows.to(device), store_rows, actions.to(device), targets.to(device))
        model.to(device)

        # the temporary head is made on the CPU, as before, so a seed gives the same weights anywhere
        head = model.head if not model.personalised else nn.Linear(model.encoder.out_dim, model.n_actions)
        head.to(device)
        joint_parameters = [p for n, p in model.named_parameters() if model.uses_content or not n.startswith('encoder.')]
        stages = [('pretrain', cfg.pretrain_epochs if model.uses_content else 0,
                   list(model.encoder.parameters()) + list(head.parameters()), lambda u, s, h: head(h), 0.0),
                  ('joint', cfg.joint_epochs, joint_parameters, model, cfg.embedding_l2)]
        for stage, epochs, parameters, score, l2 in stages:
            if epochs == 0:
                continue
            optimiser = torch.optim.AdamW(parameters, lr=cfg.lr, weight_decay=cfg.weight_decay)
            for epoch in range(epochs):
                loss = self._epoch(data, batch, score, parameters, optimiser, rng, l2)
                self.history[stage].append(loss)
                log.info('%s epoch %d/%d loss %.4f', stage, epoch + 1, epochs, loss)
                if on_epoch is not None:
                    on_epoch(stage, epoch + 1)
        model.cpu()
        model.eval()
        return self

    def _set_statistics(self, data, rows, train_scenes):
        model = self.model
        for a in range(len(self.action_names)):
            scores = data.scores[rows][data.actions[rows] == a]
            if len(scores):
                model.target_mean[a] = float(scores.mean())
                model.target_std[a] = float(scores.std()) if scores.std() > 1e-8 else 1.0
        if hasattr(model, 'feature_mean'):
            features = data.store.features[torch.from_numpy(train_scenes)]
            model.feature_mean.copy_(features.mean(0))
            std = features.std(0, unbiased=False)
            model.feature_std.copy_(torch.where(std > 1e-8, std, torch.ones_like(std)))

    def _epoch(self, data, batch, score, parameters, optimiser, rng, l2: float) -> float:
        """One pass over the training ratings; returns the mean squared error (z-scale).

        ``store_rows`` is on the CPU; the other tensors of ``batch`` are on the model's device."""
        users, scene_rows, store_rows, actions, targets = batch
        cfg = self.config.training
        device = self.model.device
        self.model.train()
        order = torch.from_numpy(rng.permutation(len(targets)))
        total, count = 0.0, 0
        for start in range(0, len(order), cfg.batch_size):
            pick = order[start:start + cfg.batch_size]
            distinct, inverse = torch.unique(store_rows[pick], return_inverse=True)
            h = self.model.encode(data.store.batch(distinct).to(device))[inverse.to(device)]
            pick = pick.to(device)
            z = score(users[pick], scene_rows[pick], h).gather(1, actions[pick, None]).squeeze(1)
            loss = nn.functional.mse_loss(z, targets[pick])
            objective = loss
            auxiliary = self.model.encoder.auxiliary_loss()
            if auxiliary is not None:
                objective = objective + auxiliary
            if l2:
                objective = objective + l2 * self.model.embedding_penalty(users[pick], scene_rows[pick])
            optimiser.zero_grad()
            objective.backward()
            nn.utils.clip_grad_norm_(parameters, cfg.grad_clip)
            optimiser.step()
            total += loss.item() * len(pick)
            count += len(pick)
        mean_loss = total / count
        if not math.isfinite(mean_loss) or not all(torch.isfinite(p).all() for p in parameters):
            raise TrainingDivergedError('training diverged (non-finite loss or parameters): lower the learning rate')
        return mean_loss

    # -- prediction ---------------------------------------------------------------------
    def _require_model(self) -> StarsModel:
        if self.model is None:
            raise NotFittedError('this recommender is not fitted: call fit() or load a checkpoint first')
        return self.model

    @torch.no_grad()
    def predict_scores(self, users: Sequence[str], scene_keys: Sequence, scene_input) -> np.ndarray:
        """Rating-scale scores [len(users), n_actions] for scenes whose encoder input is given.

        ``scene_keys[k]`` may be None (a scene never seen: q_i = 0, b_i = 0).
        """
        model = self._require_model()
        model.eval()
        return self.predict_scores_from_h(users, scene_keys, model.encode(scene_input))

    @torch.no_grad()
    def predict_rows(self, data: RatingData, rows: np.ndarray) -> np.ndarray:
        """Rating-scale prediction for each (user, scene, action) row of ``data``; runs on
        the model's device (a GPU inside ``fit``'s ``on_epoch``)."""
        model = self._require_model()
        model.eval()
        predictions = []
        for start in range(0, len(rows), EVAL_BATCH):
            part = rows[start:start + EVAL_BATCH]
            distinct, inverse = np.unique(data.scenes[part], return_inverse=True)
            scenes = data.store.batch(torch.from_numpy(distinct)).to(model.device)
            h = model.encode(scenes)[torch.from_numpy(inverse).to(model.device)]
            keys = [data.scene_keys[s] for s in data.scenes[part]]
            scores = self.predict_scores_from_h(data.users[part], keys, h)
            predictions.append(scores[np.arange(len(part)), data.actions[part]])
        return np.concatenate(predictions) if predictions else np.zeros(0)

    @torch.no_grad()
    def predict_scores_from_h(self, users, scene_keys, h, user_rows: tuple | None = None) -> np.ndarray:
        """Like ``predict_scores`` for already encoded scenes ``h`` [len(users), dim];
        ``user_rows`` (p, b_u) overrides the user table (see ``StarsModel.forward``)."""
        model = self._require_model()
        users, scenes = self.user_index(users).to(model.device), self.scene_index(scene_keys).to(model.device)
        z = model(users, scenes, h, user_rows)
        return model.to_rating_scale(z).cpu().numpy().astype(np.float64)

    def evaluate(self, data: RatingData, rows: np.ndarray) -> dict:
        """Macro-averaged MSE, RMSE, Pearson r and CCC on ``rows``, on the rating scale."""
        return regression_report(data.scores[rows], self.predict_rows(data, rows), data.actions[rows])


def split_rows(n: int, test_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Seeded random split of ``n`` annotation rows into (train, test) index arrays."""
    order = np.random.default_rng(seed).permutation(n)
    n_test = int(round(n * test_fraction))
    return np.sort(order[n_test:]), np.sort(order[:n_test])
