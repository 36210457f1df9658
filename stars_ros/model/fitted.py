"""A fitted model as a checkpoint holds it: ``FittedModel`` (the ``StarsModel``, the
vocabularies that map ids to its rows, the rating scale and the personalisation prior).

Serving needs only this (``Predictor``, ``model.checkpoint``'s loading), so it lives apart
from the training (``model.training``, which imports pandas through ``RatingData``):
``StarsTrainer`` is a ``FittedModel`` that can also fit, and a loaded checkpoint is one
that cannot.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from stars_ros.errors import ConfigError, NotFittedError, StarsError
from stars_ros.model.config import ExperimentConfig
from stars_ros.model.encoders import resolve_encoder
from stars_ros.model.model import StarsModel
from stars_ros.model.vocabulary import UNKNOWN, Rows, Vocabulary


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


class FittedModel(Rows):
    """A StARS model and the ids behind its rows: what a checkpoint stores and a
    ``Predictor`` serves.

    Args:
        config (ExperimentConfig): encoder, model, training and split settings.
    """

    def __init__(self, config: ExperimentConfig):
        self.config = config
        self.model: StarsModel | None = None
        self.user_vocabulary = Vocabulary()
        self.scene_vocabulary = Vocabulary()
        self.action_names: tuple = ()
        self.rating_scale: tuple | None = None
        self.user_prior: dict | None = None  # personalisation.prior.UserPrior.to_dict(), kept by checkpoints
        self.stranger_model: StarsModel | None = None  # the plain encoder strangers get (model.strangers)

    def user_index(self, users: Sequence[str]) -> torch.Tensor:
        return torch.from_numpy(self.user_vocabulary.rows([str(u) for u in users]))

    def scene_index(self, keys: Sequence) -> torch.Tensor:
        return torch.from_numpy(self.scene_vocabulary.rows(keys))

    def set_vocabularies(self, users, scene_keys, action_names) -> None:
        """The ids behind the model's rows (a checkpoint's, or the training data's)."""
        self.user_vocabulary, self.scene_vocabulary = Vocabulary(users), Vocabulary(scene_keys)
        self.action_names = tuple(action_names)

    def require_model(self) -> StarsModel:
        if self.model is None:
            raise NotFittedError('this recommender is not fitted: call fit() or load a checkpoint first')
        return self.model

    @torch.no_grad()
    def set_user_row(self, user, p, b: float) -> None:
        """Train ``user``'s row of p_u, b_u to (``p``, ``b``): a folded-in user made a
        trained one (the user must be in the vocabulary: ``StarsTrainer.extended``)."""
        model = self.require_model()
        row = self.user_vocabulary.row(str(user))
        if row == UNKNOWN or not model.personalised:
            raise StarsError(f"'{user}' has no row of the user table to set")
        model.user_embedding.weight[row] = torch.as_tensor(np.asarray(p), dtype=torch.float32)
        model.user_bias.weight[row, 0] = float(b)

    def copy_into(self, other: 'FittedModel') -> 'FittedModel':
        """``other`` given this one's weights, vocabularies, scale and prior (shared, not
        copied); returns ``other``. How a loaded checkpoint becomes trainable again."""
        other.model, other.rating_scale, other.user_prior = self.model, self.rating_scale, self.user_prior
        other.stranger_model = self.stranger_model
        other.user_vocabulary, other.scene_vocabulary = self.user_vocabulary, self.scene_vocabulary
        other.action_names = self.action_names
        return other
