"""The one fit recipe of a shipped model: ``Recipe``. ``StarsRecommender.fit`` is it, and so
``train``, ``evaluate`` (and its learning curves), k-shot and the implicit simulation fit
through it, as do myFM's base h_i.

Given rating rows, it trains

1. the plain encoder strangers are served (the ``base`` variant, same settings), where the
   config serves them so (``model.strangers`` 'base_encoder'), on every row;
2. for a personalised variant, a *hold-out fit*: the same model on the rows less a seeded
   ``prior.NOISE_SHARE`` of each person's examples (``prior.held_out_split``), whose served
   predictions of those examples give the prior its rating noise, tails and mean weight
   (``prior.held_out_residuals``): ratings a fit did not see, as a new person's are;
3. the shipped model on every row, and its prior (``prior.estimate_prior``): Σ₀ and each
   trained person's covariance from its own rows, the noise from step 2.

So the model that ships learns from every rating it is given, and the prior's noise is still
measured on ratings the model that made it did not fit. The hold-out fit is the model the
recipe before this one shipped (the same rows, seeds and settings). A hold-out fit followed by
a refit costs one fit more than that recipe; cross-fitting (K fits, each scoring its held-out
share) would cost K, for a noise estimate from every rating instead of a tenth. The noise is
the hold-out fit's, on 90 % of the rows: how far the refit's own error differs is what the
canonical runs' row of the earlier recipe beside this one shows.
"""
from __future__ import annotations

import copy
from typing import Callable

import numpy as np

from stars_ros.errors import NotFittedError
from stars_ros.model.config import ExperimentConfig
from stars_ros.model.training import StarsTrainer, torch_state_kept
from stars_ros.personalisation.prior import estimate_prior, held_out_residuals, held_out_split


class Recipe:
    """Fit the shipped model of ``config`` (an ``ExperimentConfig``) on rating rows.

    ``fit`` returns the fitted ``StarsTrainer`` (its ``stranger_model`` and ``user_prior``
    set); ``trainer`` is the shipped model's trainer and ``holdout`` the hold-out fit's (None
    for ``base``, which has no prior), fitted on ``holdout_rows``. Inside ``fit``'s ``on_epoch``,
    ``now`` is the model ``fit`` would return were both fits to end at that epoch.
    """

    def __init__(self, config: ExperimentConfig):
        self.config = config
        self.trainer: StarsTrainer | None = None
        self.holdout: StarsTrainer | None = None
        self.holdout_rows: np.ndarray | None = None
        self._fitting = None  # (data, every row, the hold-out fit's rows, its held-out rows)
        self._snapshots = {}  # (stage, epoch) -> the hold-out fit's weights then (only with on_epoch)

    @property
    def personalised(self) -> bool:
        return self.config.model.variant != 'base'

    def fit(self, data, rows=None, on_epoch: Callable[[str, int], None] | None = None) -> StarsTrainer:
        """The shipped model of every row of ``rows`` of ``data`` (all by default). ``on_epoch(stage,
        epoch)`` is called after each epoch of the shipped model's training (``StarsTrainer.fit``).
        Leaves torch's threads, default dtype and random state as it found them."""
        rows = np.arange(len(data)) if rows is None else np.asarray(rows, dtype=np.int64)
        config = self.config
        self._snapshots, self._fitting = {}, (data, rows, None, None)
        with torch_state_kept():
            stranger = None
            if config.model.strangers == 'base_encoder':
                stranger = StarsTrainer(config.stranger_encoder()).fit(data, rows).model
            if self.personalised:
                fit_rows, noise_rows = held_out_split(data, rows, seed=config.split.seed)
                self._fitting, self.holdout_rows = (data, rows, fit_rows, noise_rows), fit_rows
                self.holdout = StarsTrainer(config)
                self.holdout.stranger_model = stranger  # served beside it; its held-out people are known ones
                self.holdout.fit(data, fit_rows, on_epoch=None if on_epoch is None else self._snapshot)
            self.trainer = trainer = StarsTrainer(config)
            trainer.stranger_model = stranger
            trainer.fit(data, rows, on_epoch=on_epoch)
            if self.personalised:
                self._with_prior(trainer, self.holdout)
        return trainer

    def holdout_model(self) -> StarsTrainer:
        """The hold-out fit as the recipe before the refit shipped it: its weights, its plain
        encoder, and the prior of its own rows (Σ₀ and covariances from ``holdout_rows``, the
        noise from the rows it did not see). The canonical runs' ablation row beside the shipped
        model (``evaluation.specs.HOLDOUT_RECIPE``); costs no fit."""
        if self.holdout is None or self.holdout.model is None:
            raise NotFittedError('holdout_model is for a personalised variant, after fit')
        data, _, fit_rows, noise_rows = self._fitting
        earlier = self.holdout.copy_into(StarsTrainer(self.config))
        with torch_state_kept():
            earlier.user_prior = estimate_prior(earlier, data, fit_rows,
                                                held_out_residuals(earlier, data, noise_rows)).to_dict()
        return earlier

    def _snapshot(self, stage: str, epoch: int) -> None:
        state = self.holdout.model.state_dict()
        self._snapshots[stage, epoch] = {key: value.detach().cpu().clone() for key, value in state.items()}

    def _with_prior(self, trainer: StarsTrainer, holdout: StarsTrainer) -> StarsTrainer:
        data, rows, _, noise_rows = self._fitting
        held_out = held_out_residuals(holdout, data, noise_rows)
        trainer.user_prior = estimate_prior(trainer, data, rows, held_out).to_dict()
        return trainer

    def now(self, stage: str, epoch: int) -> StarsTrainer:
        """Inside ``fit``'s ``on_epoch(stage, epoch)``: the model ``fit`` would return were
        training to end now (both fits at this epoch, with the posterior head of their current
        weights where the settings have one, and the prior), so that a learning curve scores
        what its settings describe."""
        if self.trainer is None or self.trainer.model is None:
            raise NotFittedError('now is for on_epoch, while fit runs')
        data, rows, fit_rows, _ = self._fitting
        shipped = self._as_fitted(self.trainer, data, rows)
        if not self.personalised:
            return shipped
        holdout = self._as_fitted(self.holdout, data, fit_rows, self._snapshots[stage, epoch])
        return self._with_prior(shipped, holdout)

    def _as_fitted(self, trainer: StarsTrainer, data, rows, state: dict | None = None) -> StarsTrainer:
        """A CPU copy of ``trainer`` (with the weights ``state``, if given), given its posterior
        head on ``rows`` of ``data`` where the settings have one."""
        child = trainer.copy_into(StarsTrainer(self.config))
        child.model = copy.deepcopy(trainer.model).cpu()
        if state is not None:
            child.model.load_state_dict(state)
        child.model.eval()
        return child.with_posterior_head(data, rows) if self.config.training.posterior_sweeps else child
