"""A fitted model as a checkpoint holds it: ``FittedModel`` (the ``StarsModel``, the
vocabularies that map ids to its rows, the rating scale and the personalisation prior).

Serving needs only this (``Predictor``, ``model.checkpoint``'s loading), so it lives apart
from the training (``model.training``, which imports pandas through ``RatingData``):
``StarsTrainer`` is a ``FittedModel`` that can also fit, and a loaded checkpoint is one
that cannot.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import numpy as np
import torch

from stars_ros.errors import ConfigError, NotFittedError, StarsError
from stars_ros.model.config import ExperimentConfig
from stars_ros.model.encoders import resolve_encoder
from stars_ros.model.metrics import regression_report
from stars_ros.model.model import StarsModel
from stars_ros.model.vocabulary import UNKNOWN, Rows, Vocabulary

if TYPE_CHECKING:
    from stars_ros.data.ratings import RatingData

EVAL_BATCH = 2048


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

    # -- prediction on data rows and encoder inputs (torch; the node uses Predictor) ----
    @torch.no_grad()
    def predict_scores(self, users: Sequence[str], scene_keys: Sequence, scene_input) -> np.ndarray:
        """Rating-scale scores [len(users), n_actions] for scenes whose encoder input is given.

        ``scene_keys[k]`` may be None (a scene never seen: q_i = 0, b_i = 0).
        """
        model = self.require_model()
        model.eval()
        scores = self.predict_scores_from_h(users, scene_keys, model.encode(scene_input))
        return self._strangers_served(self.user_index(users), scene_input, np.arange(len(scores)), scores)

    @torch.no_grad()
    def predict_rows(self, data: RatingData, rows: np.ndarray) -> np.ndarray:
        """Rating-scale prediction for each (user, scene, action) row of ``data``; runs on
        the model's device (a GPU inside ``fit``'s ``on_epoch``)."""
        model = self.require_model()
        model.eval()
        items = data.item_keys(self.config.model.item_key)
        predictions = []
        for start in range(0, len(rows), EVAL_BATCH):
            part = rows[start:start + EVAL_BATCH]
            distinct, inverse = np.unique(data.scenes[part], return_inverse=True)
            scenes = data.store.batch(torch.from_numpy(distinct)).to(model.device)
            h = model.encode(scenes)[torch.from_numpy(inverse).to(model.device)]
            keys = [items[s] for s in data.scenes[part]]
            scores = self.predict_scores_from_h(data.users[part], keys, h)
            scores = self._strangers_served(self.user_index(data.users[part]), scenes, inverse, scores)
            predictions.append(scores[np.arange(len(part)), data.actions[part]])
        return np.concatenate(predictions) if predictions else np.zeros(0)

    @torch.no_grad()
    def _strangers_served(self, users: torch.Tensor, scene_input, inverse: np.ndarray,
                          scores: np.ndarray) -> np.ndarray:
        """``scores`` [R, actions] with each stranger's (UNKNOWN ``users``) rows replaced by the
        plain encoder's prediction where the model serves strangers so (``stranger_model``);
        row r scores scene ``inverse[r]`` of ``scene_input``."""
        strangers = (users < 0).numpy()
        if self.stranger_model is None or not strangers.any():
            return scores
        base = self.stranger_model
        base.eval()
        h = base.encode(scene_input.to(base.device) if hasattr(scene_input, 'to') else scene_input)
        served = base.to_rating_scale(base.head(h)).cpu().numpy().astype(np.float64)
        scores = scores.copy()
        scores[strangers] = self.clip(served[np.asarray(inverse)[strangers]])
        return scores

    @torch.no_grad()
    def predict_scores_from_h(self, users, scene_keys, h, user_rows: tuple | None = None) -> np.ndarray:
        """Like ``predict_scores`` for already encoded scenes ``h`` [len(users), dim];
        ``user_rows`` (p, b_u) overrides the user table (see ``StarsModel.forward``).
        Scores are clipped to the training data's rating scale."""
        model = self.require_model()
        users, scenes = self.user_index(users).to(model.device), self.scene_index(scene_keys).to(model.device)
        if user_rows is None:
            user_rows = self._rows_with_strangers(users)
        z = model(users, scenes, h, user_rows)
        return self.clip(model.to_rating_scale(z).cpu().numpy().astype(np.float64))

    def _rows_with_strangers(self, users: torch.Tensor) -> tuple | None:
        """(p, b_u) of ``users`` with each stranger (UNKNOWN) given the prior's mean, as
        ``Predictor`` serves them; None (the table, strangers at zero) without a prior or strangers."""
        model = self.model
        if self.user_prior is None or not model.personalised or bool((users >= 0).all()):
            return None
        mean = torch.as_tensor(self.user_prior['mean'], dtype=torch.float32, device=model.device)
        stranger = (users < 0).unsqueeze(-1)
        known = users.clamp(min=0)
        return (torch.where(stranger, mean[:-1], model.user_embedding(known)),
                torch.where(stranger, mean[-1:], model.user_bias(known)))

    def evaluate(self, data: RatingData, rows: np.ndarray) -> dict:
        """Macro-averaged MSE, RMSE, Pearson r and CCC on ``rows``, on the rating scale."""
        return regression_report(data.scores[rows], self.predict_rows(data, rows), data.actions[rows])
