"""ROS-free inference: load a checkpoint, rank actions (or alternative scenes) for a user.

Unknown users and scenes are the normal case on a robot: a user gets the personalisation
prior's mean (p_u, b_u) the checkpoint stores (``personalisation.prior``; zero in one without),
a scene q_i = 0, b_i = 0, so the prediction is the content term plus population offsets, and
``Ranking.known_user`` says so (Surprise's fallback-with-a-reason, without an exception).

Users folded in after training (``stars_ros.personalisation.foldin``) are served from an overlay
user_id -> UserModel that scoring consults before the trained table. The overlay is never
changed in place: an update builds a new dict and swaps the reference, so a thread scoring
meanwhile sees the old or the new overlay, never half of one. ``knows_user`` keeps meaning
"in the training data"; ``personalised_from`` counts the ratings a folded-in user was solved from.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from stars_ros.model.checkpoint import load_checkpoint
from stars_ros.errors import SceneGraphError, UnknownActionError
from stars_ros.model.numpy_model import InferenceModel
from stars_ros.model.model import UNKNOWN
from stars_ros.data.scene_graph import SceneGraph, featurise


@dataclass(frozen=True)
class Ranked:
    """One ranked entry: an action name (or a candidate scene's label), its score on the
    rating scale, its 1-based rank, the score's predictive standard deviation and its
    explanation (``explain.Why``; each None where it is not computed)."""

    name: str
    score: float
    rank: int
    score_sd: float | None = None
    why: object = None


def rank_order(names: Sequence[str], scores, sds=None, whys=None) -> list:
    """``Ranked`` entries of ``names`` by ``scores`` (with their ``sds`` and ``whys``), best first."""
    order = sorted(range(len(names)), key=lambda k: (-scores[k], k))  # ties keep input order
    return [Ranked(str(names[k]), float(scores[k]), rank, None if sds is None else float(sds[k]),
                   None if whys is None else whys[k])
            for rank, k in enumerate(order, 1)]


class Predictor:
    """Scores scenes with a trained model.

    Args:
        recommender (StarsTrainer): fitted model and vocabularies.
        metadata (dict): the checkpoint's metadata (config, provenance, metrics).
        digest (str): the checkpoint's SHA-256 digest, its fingerprint.
    """

    def __init__(self, recommender, metadata: dict, digest: str):
        self.recommender = recommender
        self.metadata = metadata
        self.fingerprint = digest
        self.actions = tuple(recommender.action_names)
        self._action_index = {a: i for i, a in enumerate(self.actions)}
        self._user_models = {}
        self._user_models_lock = threading.Lock()  # orders writers; readers take the reference
        self._inference = InferenceModel(recommender.require_model())
        self._stranger = self._prior_mean(recommender)
        self._scene_rows = np.array([UNKNOWN], dtype=np.int64)  # broadcasts: no scene id, no q_i

    def _prior_mean(self, recommender) -> tuple:
        """(p, b_u) a stranger is scored with: the personalisation prior's mean the checkpoint
        stores (personalisation.prior), else zero (content and population offsets only)."""
        stored = getattr(recommender, 'user_prior', None)
        if stored is None or not self._inference.personalised:
            return np.zeros(self._inference.dim, dtype=np.float32), np.float32(0.0)
        mean = np.asarray(stored['mean'], dtype=np.float32)
        return mean[:-1], np.float32(mean[-1])

    @classmethod
    def load(cls, path) -> 'Predictor':
        """Raises CheckpointError for a missing, truncated, corrupted or incompatible file."""
        recommender, metadata, digest = load_checkpoint(path, with_digest=True)
        return cls(recommender, metadata, digest)

    @classmethod
    def from_model(cls, recommender) -> 'Predictor':
        """A predictor over a fitted ``StarsTrainer`` held in memory, not read from a file:
        it has no checkpoint, so its metadata is empty and its fingerprint ''."""
        return cls(recommender, {}, '')

    @property
    def inference(self) -> InferenceModel:
        """The numpy weights and scoring arithmetic this predictor serves with (read-only)."""
        return self._inference

    @property
    def input_kind(self) -> str:
        return self.recommender.model.encoder.input_kind

    def knows_user(self, user_id) -> bool:
        return user_id is not None and str(user_id) in self.recommender.user_vocabulary

    @property
    def user_models(self) -> dict:
        """The current overlay {user_id: UserModel} (a snapshot: do not modify)."""
        return self._user_models

    def user_model(self, user_id):
        """The folded-in UserModel of ``user_id``, or None."""
        return None if user_id is None else self._user_models.get(str(user_id))

    def personalised_from(self, user_id) -> int:
        """How many feedback ratings ``user_id``'s folded-in embedding was solved from (0: none)."""
        model = self.user_model(user_id)
        return 0 if model is None else model.n_ratings

    def set_user_model(self, user_id, model) -> None:
        """Serve ``user_id`` with ``model`` (a foldin.UserModel; None removes the user)."""
        with self._user_models_lock:
            overlay = dict(self._user_models)
            if model is None:
                overlay.pop(str(user_id), None)
            else:
                overlay[str(user_id)] = model
            self._user_models = overlay

    def set_user_models(self, models: dict) -> None:
        """Replace the whole overlay."""
        with self._user_models_lock:
            self._user_models = {str(k): v for k, v in models.items()}

    def _scene_input(self, scenes: Sequence, validate: bool):
        if self.input_kind == 'graph':  # a SceneGraph is a scene featurised already (a data set's)
            return [scene if isinstance(scene, SceneGraph) else featurise(scene, validate=validate)
                    for scene in scenes]
        features = np.asarray(scenes, dtype=np.float32)
        if features.ndim != 2 or features.shape[1] != self.recommender.model.encoder.in_dim or not np.isfinite(features).all():
            raise SceneGraphError(f'tabular scenes must be finite rows of {self.recommender.model.encoder.in_dim} features')
        return features

    def encode(self, scenes: Sequence, validate: bool = True) -> np.ndarray:
        """h_i [len(scenes), dim] (float32) of scene-graph dicts (or featurised ``SceneGraph``)
        or tabular feature rows."""
        if len(scenes) == 0:
            raise SceneGraphError('no scenes to score')
        return self._inference.encode(self._scene_input(scenes, validate), len(scenes))

    def score(self, user_id, scenes: Sequence, scene_ids: Sequence | None = None,
              validate: bool = True) -> np.ndarray:
        """Rating-scale scores [len(scenes), n_actions] of one user for a batch of scenes.

        ``scenes`` are scene-graph dicts (graph models) or feature rows (tabular models);
        ``scene_ids`` optionally name training scenes so their q_i is used. ``validate=False``
        skips the schema check for scenes already validated against it (the node's requests).
        """
        return self.scores_from_h(user_id, self.encode(scenes, validate), scene_ids)

    def scores_from_h(self, user_id, h: np.ndarray, scene_ids: Sequence | None = None) -> np.ndarray:
        """``score`` for scenes already encoded as ``h`` [len(scenes), dim], clipped to the
        rating scale the checkpoint was trained on."""
        scene_rows = self._scene_rows if scene_ids is None else self._scene_rows_of(scene_ids)
        return self.recommender.clip(self._inference.scores(h, self._user_row(user_id), scene_rows))

    def _scene_rows_of(self, scene_ids: Sequence) -> np.ndarray:
        return self.recommender.scene_vocabulary.rows(scene_ids)

    def user_theta(self, user_id) -> np.ndarray:
        """θ = (p_u, b_u) [dim+1] (float64) that scores ``user_id`` (see ``scores_from_h``)."""
        p, b = self._user_row(user_id)
        return np.append(np.asarray(p, dtype=np.float64), float(b))

    def _user_row(self, user_id) -> tuple:
        """(p_u, b_u) that scores ``user_id``: folded in, trained, or zero for a stranger."""
        inference = self._inference
        if not inference.personalised:
            return None
        folded = self.user_model(user_id)
        if folded is not None:
            return folded.p.astype(np.float32), np.float32(folded.b)
        row = self.recommender.user_vocabulary.row(str(user_id)) if user_id is not None else UNKNOWN
        if row == UNKNOWN:
            return self._stranger
        return inference.user_rows[row], inference.user_offsets[row]

    def action_columns(self, actions: Sequence[str]) -> list:
        """The score columns of ``actions`` (UnknownActionError names any the model lacks)."""
        unknown = [a for a in actions if a not in self._action_index]
        if unknown:
            raise UnknownActionError(f'unknown actions {unknown}; this model knows {list(self.actions)}')
        return [self._action_index[a] for a in actions]

    def ranking_action(self, action: str | None) -> str:
        """The action whose score ranks candidate scenes: ``action``, or the model's only one
        (UnknownActionError when it has several and none is named, or names one it lacks)."""
        if action is None:
            if len(self.actions) != 1:
                raise UnknownActionError(f"say which 'action' ranks the candidate scenes; this model knows "
                                         f'{list(self.actions)}')
            return self.actions[0]
        self.action_columns([action])
        return action

    def rank(self, user_id, scene, candidates: Sequence[str] | None = None, scene_id=None) -> list:
        """Candidate actions (all by default) sorted best first for ``user_id`` in ``scene``."""
        names = list(self.actions if candidates is None else candidates)
        if not names:
            raise UnknownActionError('candidate list is empty')
        columns = self.action_columns(names)
        return rank_order(names, self.score(user_id, [scene], [scene_id])[0, columns])

    def rank_scenes(self, user_id, scenes: Sequence, labels: Sequence[str] | None = None,
                    action: str | None = None) -> list:
        """Alternative scenes (e.g. candidate robot placements) sorted best first by the
        score of ``action`` (required when the model has more than one)."""
        column = self.action_columns([self.ranking_action(action)])[0]
        labels = [str(k) for k in range(len(scenes))] if labels is None else list(labels)
        if len(labels) != len(scenes):
            raise ValueError('one label per candidate scene')
        return rank_order(labels, self.score(user_id, scenes)[:, column])
