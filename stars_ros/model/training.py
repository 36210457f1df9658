"""Fit and apply a StARS (or base) model on rating data: ``StarsTrainer``.

(The public, Surprise/LightFM-shaped class is ``stars_ros.StarsRecommender``, the front door
in ``stars_ros/recommender.py``; this module is the training behind it. What a fitted model
is, and what serving needs of it, is ``model.fitted``.)

Training is two-step, as published: (1) ``pretrain_epochs`` of the encoder with a
temporary linear head on per-action z-scored targets; (2) ``joint_epochs`` of the whole
model. For the ``base`` variant the linear head is the model's own head, so both steps
train the same network. A personalised model takes over the pre-trained head as its action
embeddings (``StarsModel.start_from_head``), so joint training starts from the scene-only
model rather than from a random head. With ``posterior_sweeps``, a Gibbs sampler then
replaces the trained factorisation part by its posterior means (``model.posterior``).
A batch holds examples (one user's ratings of one
scene, every action a target), as in the paper. AdamW with gradient clipping; seeds fixed;
each distinct scene of a batch is encoded once.

``training.device`` may put the training on a GPU: the scene store stays on the CPU and
each batch is moved, and the model is moved back to the CPU when ``fit`` ends, so
everything after training (checkpoints, fold-in, serving) is the same as for a CPU fit.
"""
from __future__ import annotations

import contextlib
import copy
import logging
import math
from typing import Callable, NamedTuple, Sequence

import numpy as np
import torch
from torch import nn

from stars_ros.data.ratings import RatingData
from stars_ros.data.splits import held_examples
from stars_ros.errors import ConfigError, TrainingDivergedError
from stars_ros.model.config import ExperimentConfig
from stars_ros.model.fitted import FittedModel, build_model
from stars_ros.model.posterior import posterior_head, training_observations

log = logging.getLogger(__name__)


class TrainingSet(NamedTuple):
    """Training examples: user and item rows [E], store rows of their scenes [E] (CPU),
    z-scored targets [E, actions] and which of them are rated [E, actions]."""

    users: torch.Tensor
    items: torch.Tensor
    scenes: torch.Tensor
    targets: torch.Tensor
    rated: torch.Tensor

    def to(self, device) -> 'TrainingSet':
        return TrainingSet(self.users.to(device), self.items.to(device), self.scenes,
                           self.targets.to(device), self.rated.to(device))


@contextlib.contextmanager
def torch_state_kept():
    """Put back, on leaving, the process-wide torch state that training sets: the number of
    threads, the default dtype and the random generators (the CPU's, and CUDA's when CUDA
    was initialised before). ``fit`` and ``fine_tune`` seed and set threads inside it, so a
    caller's own torch settings and random stream are as they were."""
    threads, dtype = torch.get_num_threads(), torch.get_default_dtype()
    cpu_rng = torch.random.get_rng_state()
    cuda_rng = torch.cuda.get_rng_state_all() if torch.cuda.is_initialized() else None
    try:
        yield
    finally:
        torch.set_num_threads(threads)
        torch.set_default_dtype(dtype)
        torch.random.set_rng_state(cpu_rng)
        if cuda_rng is not None:
            torch.cuda.set_rng_state_all(cuda_rng)


class StarsTrainer(FittedModel):
    """The training side of a StARS model: a ``FittedModel`` that fits and fine-tunes on
    ``RatingData`` rows (``fit``, ``fine_tune``, ``extended``). The shipped model is fitted by
    ``personalisation.recipe`` and scored by its served form (``model.scoring``); the user-facing API
    (fit, predict, rank, fold_in, test, save, load) is ``stars_ros.StarsRecommender``.

    Args:
        config (ExperimentConfig): encoder, model, training and split settings.
    """

    def __init__(self, config: ExperimentConfig):
        super().__init__(config)
        self.history: dict = {'pretrain': [], 'joint': []}

    @classmethod
    def resume(cls, fitted: FittedModel) -> 'StarsTrainer':
        """A trainer over ``fitted``'s weights (a loaded checkpoint's, say), to extend and fine-tune."""
        return fitted.copy_into(cls(fitted.config))

    def extended(self, users: Sequence[str] = (), scene_keys: Sequence = ()) -> 'StarsTrainer':
        """A copy whose vocabularies also hold ``users`` and ``scene_keys``: the same weights,
        new rows zero (a stranger's), to be set or fine-tuned (``fine_tune``)."""
        model = self.require_model()
        child = StarsTrainer(self.config)
        child.rating_scale = self.rating_scale
        child.user_prior = self.user_prior  # the population's; the new people have no training covariance
        child.stranger_model = self.stranger_model
        child.set_vocabularies(self.user_vocabulary.extended([str(u) for u in users]).keys,
                               self.scene_vocabulary.extended(scene_keys).keys, self.action_names)
        child.model = build_model(self.config, model.encoder.in_dim, model.encoder.input_kind, len(child.users),
                                  len(child.scene_keys), len(child.action_names))
        grown = child.model.state_dict()
        for name, value in model.state_dict().items():
            grown[name] = torch.zeros_like(grown[name])  # new rows of a grown table stay zero
            grown[name][:len(value)] = value
        child.model.load_state_dict(grown)
        child.model.eval()
        return child

    # -- training -----------------------------------------------------------------------
    def fit(self, data: RatingData, rows: np.ndarray | None = None,
            on_epoch: Callable[[str, int], None] | None = None) -> 'StarsTrainer':
        """Train on ``rows`` of ``data`` (all rows by default); returns self.

        ``on_epoch(stage, epoch)`` is called after each epoch ('pretrain' or 'joint',
        counted from 1), e.g. to score a learning curve; it must not train the model.
        The seeds and ``training.threads`` apply inside ``fit`` only (``torch_state_kept``).
        """
        with torch_state_kept():
            return self._fit(data, rows, on_epoch)

    def _fit(self, data, rows, on_epoch) -> 'StarsTrainer':
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

        items = data.item_keys(self.config.model.item_key)
        train_scenes = np.unique(data.scenes[rows])
        self.set_vocabularies(sorted(set(data.users[rows].tolist())),
                              list(dict.fromkeys(items[s] for s in train_scenes)), data.action_names)
        self.rating_scale = data.scale
        self.model = model = build_model(self.config, data.store.feature_dim, data.kind,
                                         len(self.users), len(self.scene_keys), len(self.action_names))
        self._set_statistics(data, rows, train_scenes)
        examples = self.training_set(data, rows).to(device)
        model.to(device)

        # The pre-training head is made on the CPU under a fresh seed, so a seed gives the same
        # weights anywhere and every variant with content pre-trains exactly as base does.
        head = model.head if not model.personalised else nn.Linear(model.encoder.out_dim, model.n_actions)
        torch.manual_seed(cfg.seed)
        head.reset_parameters()
        head.to(device)
        if model.uses_content and cfg.pretrain_epochs:
            parameters = list(model.encoder.parameters()) + list(head.parameters())
            self._run_epochs('pretrain', cfg.pretrain_epochs, data, examples, lambda u, s, h: head(h),
                             parameters, rng, 0.0, on_epoch)
            if model.personalised:
                model.start_from_head(head)
        self._run_epochs('joint', cfg.joint_epochs, data, examples, model, self.trainable_parameters(), rng,
                         cfg.embedding_l2, on_epoch)
        model.cpu()
        model.eval()
        if cfg.posterior_sweeps:
            self._apply_posterior_head(data, examples)
        return self

    def with_posterior_head(self, data: RatingData, rows: np.ndarray) -> 'StarsTrainer':
        """A copy, on the CPU, whose factorisation part is the posterior head (``posterior_sweeps``)
        of the current weights on ``rows``: what ``fit`` would return were joint training to end
        now, so that a learning curve scored in ``on_epoch`` scores the model its settings describe."""
        child = self.copy_into(StarsTrainer(self.config))
        child.model = copy.deepcopy(self.require_model()).cpu()
        child._apply_posterior_head(data, child.training_set(data, rows))
        return child

    def _apply_posterior_head(self, data, examples) -> None:
        cfg, model = self.config.training, self.model
        summary = posterior_head(model, training_observations(model, data.store, examples),
                                 cfg.posterior_sweeps, cfg.posterior_burn_in, cfg.seed)
        log.info('posterior head: %d sweeps (%d kept) in %.1f s, noise precision %.3f, plug-in means '
                 '%.4f (z RMS) from the averaged prediction on the training entries', summary.sweeps,
                 summary.kept, summary.seconds, summary.noise_precision, summary.plug_in_gap)

    def fine_tune(self, data: RatingData, epochs: int, rows: np.ndarray | None = None) -> list:
        """``epochs`` joint epochs on ``rows`` of ``data`` from the current weights (a refit
        after new users or scenes were added with ``extended``); returns the epoch losses.
        Like ``fit``, it leaves the process's torch state as it found it."""
        model = self.require_model()
        cfg = self.config.training
        with torch_state_kept():
            torch.manual_seed(cfg.seed)
            torch.set_num_threads(cfg.threads)
            rows = np.arange(len(data)) if rows is None else np.asarray(rows)
            losses = self._run_epochs('joint', epochs, data, self.training_set(data, rows), model,
                                      self.trainable_parameters(), np.random.default_rng(cfg.seed),
                                      cfg.embedding_l2)
        model.eval()
        return losses

    def trainable_parameters(self) -> list:
        """What joint training updates: everything but the parts a variant holds at zero
        (and the unused encoder of a content-free model)."""
        model = self.require_model()
        return [p for n, p in model.named_parameters()
                if p.requires_grad and (model.uses_content or not n.startswith('encoder.'))]

    def training_set(self, data: RatingData, rows: np.ndarray) -> 'TrainingSet':
        """``rows`` grouped into examples: one user's ratings of one scene, all actions as
        targets (z-scores under the model's normalisation) with a mask of those rated."""
        model = self.require_model()
        rows = np.asarray(rows)
        _, first, inverse = np.unique(data.examples[rows], return_index=True, return_inverse=True)
        inverse = inverse.ravel()
        items = data.item_keys(self.config.model.item_key)
        scenes = data.scenes[rows[first]]
        actions = torch.from_numpy(data.actions[rows])
        targets = torch.zeros(len(first), model.n_actions)
        rated = torch.zeros(len(first), model.n_actions, dtype=torch.bool)
        targets[inverse, actions] = model.to_z(torch.from_numpy(data.scores[rows]).float(), actions)
        rated[inverse, actions] = True
        return TrainingSet(self.user_index(data.users[rows[first]]), self.scene_index([items[s] for s in scenes]),
                           torch.from_numpy(scenes), targets, rated)

    def _run_epochs(self, stage, epochs, data, examples, score, parameters, rng, l2, on_epoch=None) -> list:
        """``epochs`` epochs of ``stage``; returns their losses."""
        cfg = self.config.training
        optimiser = torch.optim.AdamW(parameters, lr=cfg.lr, weight_decay=cfg.weight_decay)
        losses = []
        for epoch in range(epochs):
            loss = self._epoch(data, examples, score, parameters, optimiser, rng, l2)
            losses.append(loss)
            self.history[stage].append(loss)
            log.info('%s epoch %d/%d loss %.4f', stage, epoch + 1, epochs, loss)
            if on_epoch is not None:
                on_epoch(stage, epoch + 1)
        return losses

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

    def _epoch(self, data, examples, score, parameters, optimiser, rng, l2: float) -> float:
        """One pass over the training examples; returns the mean squared error over the
        rated targets (z-scale). ``examples.scenes`` stays on the CPU (it indexes the store)."""
        cfg = self.config.training
        device = self.model.device
        self.model.train()
        order = torch.from_numpy(rng.permutation(len(examples.users)))
        total, count = 0.0, 0
        for start in range(0, len(order), cfg.batch_size):
            pick = order[start:start + cfg.batch_size]
            distinct, inverse = torch.unique(examples.scenes[pick], return_inverse=True)
            h = self.model.encode(data.store.batch(distinct).to(device))[inverse.to(device)]
            pick = pick.to(device)
            users, items, rated = examples.users[pick], examples.items[pick], examples.rated[pick]
            squared = (score(users, items, h) - examples.targets[pick]).pow(2)
            n_rated = int(rated.sum())
            loss = squared[rated].sum() / n_rated
            objective = loss
            auxiliary = self.model.encoder.auxiliary_loss()
            if auxiliary is not None:
                objective = objective + auxiliary
            if l2:
                objective = objective + l2 * self.model.embedding_penalty(users, items)
            optimiser.zero_grad()
            objective.backward()
            nn.utils.clip_grad_norm_(parameters, cfg.grad_clip)
            optimiser.step()
            total += loss.item() * n_rated
            count += n_rated
        mean_loss = total / count
        if not math.isfinite(mean_loss) or not all(torch.isfinite(p).all() for p in parameters):
            raise TrainingDivergedError('training diverged (non-finite loss or parameters): lower the learning rate')
        return mean_loss


def split_rows(data: RatingData, test_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Seeded random split of ``data``'s rating rows into (train, test) index arrays, by
    example: one user's ratings of one scene (every action) land on the same side."""
    examples = data.examples
    count = int(round(len(np.unique(examples)) * test_fraction))
    test = held_examples(examples, count, np.random.default_rng(seed))
    return np.flatnonzero(~test), np.flatnonzero(test)
