"""ROS-free inference: load a checkpoint, rank actions (or alternative scenes) for a user.

Unknown users and scenes are the normal case on a robot: a user gets the personalisation
prior's mean (p_u, b_u) the checkpoint stores (``personalisation.prior``; zero in one without),
a scene q_i = 0, b_i = 0, so the prediction is the content term plus population offsets, and
``Ranking.known_user`` says so (Surprise's fallback-with-a-reason, without an exception). A
checkpoint that keeps a plain encoder for strangers (``model.strangers`` 'base_encoder') scores
everyone it was not trained on around that encoder instead: its score plus the person's
departure from the prior's mean, xᵀ(θ_u − θ₀) (``hands_over``), which is zero until ratings
are folded in, so the fold-in takes over from the plain encoder rather than from the prior's mean.

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

from stars_ros.data.scene_graph import SceneGraph, featurise
from stars_ros.errors import SceneGraphError, StarsError, UnknownActionError
from stars_ros.model.explain import explain, removal_effects
from stars_ros.model.numpy_model import InferenceModel
from stars_ros.model.serving import ServedModel, arrays
from stars_ros.model.vocabulary import UNKNOWN


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


@dataclass(frozen=True)
class RankQuery:
    """One ranking asked of ``Predictor.rank_many``: the actions ``actions`` (None: all the
    model's) of the one scene ``graphs[0]``, a training scene if ``scene_id`` names one; or,
    with ``labels``, the candidate scenes ``graphs`` (labelled so) under ``action``.
    ``explain``: give each entry its why. (``messages.SceneRequest`` has the same fields.)"""

    graphs: tuple
    scene_id: str | None = None
    actions: tuple | None = None
    labels: tuple | None = None
    action: str | None = None
    explain: bool = False

    @property
    def ranks_scenes(self) -> bool:
        return self.labels is not None


@dataclass(frozen=True)
class Scored:
    """One ranking of ``rank_many``: its entries (best first, cut to ``top_k``), the action
    that ranked candidate scenes (None for action ranking), h_i of the query's scenes
    [len(graphs), dim] (float32: feedback on them is folded in without encoding them again),
    the probability that the first entry is truly the best (None without uncertainty), and for
    a person served around the plain encoder (``Predictor.hands_over``) that encoder's unclipped
    scores of the scenes [len(graphs), n_actions] (None for anyone else: their feedback's
    fold-in needs no pass of it again, ``FoldIn.hand_over_shift``)."""

    ranked: list
    action: str | None
    h: np.ndarray
    p_first_is_best: float | None = None
    plain: np.ndarray | None = None


def rank_order(names: Sequence[str], scores, sds=None, whys=None) -> list:
    """``Ranked`` entries of ``names`` by ``scores`` (with their ``sds`` and ``whys``), best first."""
    order = sorted(range(len(names)), key=lambda k: (-scores[k], k))  # ties keep input order
    return [Ranked(str(names[k]), float(scores[k]), rank, None if sds is None else float(sds[k]),
                   None if whys is None else whys[k])
            for rank, k in enumerate(order, 1)]


class Predictor:
    """Scores scenes with a trained model.

    Args:
        served (ServedModel): the checkpoint in its serving form (``model.serving``).
        metadata (dict): the checkpoint's metadata (config, provenance, metrics).
        digest (str): the checkpoint's SHA-256 digest, its fingerprint.
    """

    def __init__(self, served: ServedModel, metadata: dict, digest: str):
        self.served = served
        self.metadata = metadata
        self.fingerprint = digest
        self.actions = tuple(served.action_names)
        self._action_index = {a: i for i, a in enumerate(self.actions)}
        self._user_models = {}
        self._user_models_lock = threading.Lock()  # orders writers; readers take the reference
        self._inference = served.inference
        self._stranger_inference = served.stranger_inference  # None unless model.strangers is 'base_encoder'
        self._stranger = self._prior_mean(served)
        self._scene_rows = np.array([UNKNOWN], dtype=np.int64)  # broadcasts: no scene id, no q_i

    def _prior_mean(self, served: ServedModel) -> tuple:
        """(p, b_u) a stranger is scored with: the personalisation prior's mean the checkpoint
        stores (personalisation.prior), else zero (content and population offsets only)."""
        stored = served.user_prior
        if stored is None or not self._inference.personalised:
            return np.zeros(self._inference.dim, dtype=np.float32), np.float32(0.0)
        mean = np.asarray(stored['mean'], dtype=np.float32)
        return mean[:-1], np.float32(mean[-1])

    @classmethod
    def load(cls, path) -> 'Predictor':
        """Raises CheckpointError for a missing, truncated, corrupted or incompatible file."""
        return cls(*ServedModel.load(path))

    @classmethod
    def from_model(cls, fitted) -> 'Predictor':
        """A predictor over a fitted model held in memory (``model.fitted.FittedModel``), served
        from the content its checkpoint would hold: it has no file, so its metadata is empty
        and its fingerprint ''."""
        from stars_ros.model.checkpoint import served_content

        metadata, state, prior = served_content(fitted)
        return cls(ServedModel(metadata, arrays(state), prior), {}, '')

    @property
    def inference(self) -> InferenceModel:
        """The numpy weights and scoring arithmetic this predictor serves with (read-only)."""
        return self._inference

    @property
    def input_kind(self) -> str:
        return self.served.input_kind

    @property
    def users(self) -> tuple:
        """The users of the training data, in the rows of the user table."""
        return self.served.users

    @property
    def rating_scale(self) -> tuple | None:
        """(lowest, highest) score a rating can take (None: unbounded)."""
        return self.served.rating_scale

    def clip(self, scores: np.ndarray) -> np.ndarray:
        """``scores`` limited to the rating scale the checkpoint was trained on."""
        return self.served.clip(scores)

    def knows_user(self, user_id) -> bool:
        return user_id is not None and str(user_id) in self.served.user_vocabulary

    def trained_row(self, user_id) -> int:
        """The row of p_u, b_u of a user of the training data (UNKNOWN, -1, for anyone else)."""
        return self.served.user_vocabulary.row(str(user_id)) if user_id is not None else UNKNOWN

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
        if features.ndim != 2 or features.shape[1] != self.served.feature_dim or not np.isfinite(features).all():
            raise SceneGraphError(f'tabular scenes must be finite rows of {self.served.feature_dim} features')
        return features

    def encoder_input(self, scenes: Sequence, validate: bool = True):
        """What the encoders read of scene-graph dicts (or featurised ``SceneGraph``) or
        tabular feature rows, checked."""
        if len(scenes) == 0:
            raise SceneGraphError('no scenes to score')
        return self._scene_input(scenes, validate)

    def encode(self, scenes: Sequence, validate: bool = True) -> np.ndarray:
        """h_i [len(scenes), dim] (float32) of scene-graph dicts (or featurised ``SceneGraph``)
        or tabular feature rows."""
        return self._inference.encode(self.encoder_input(scenes, validate), len(scenes))

    def score(self, user_id, scenes: Sequence, scene_ids: Sequence | None = None,
              validate: bool = True) -> np.ndarray:
        """Rating-scale scores [len(scenes), n_actions] of one user for a batch of scenes.

        ``scenes`` are scene-graph dicts (graph models) or feature rows (tabular models);
        ``scene_ids`` optionally name training scenes so their q_i is used. ``validate=False``
        skips the schema check for scenes already validated against it (the node's requests).
        """
        inputs = self.encoder_input(scenes, validate)
        if self.serves_stranger_encoder(user_id):  # the plain encoder alone: no StARS pass
            return self.clip(self.stranger_scores(inputs, len(scenes)))
        h = self._inference.encode(inputs, len(scenes))
        return self.clip(self.unclipped_scores(user_id, inputs, h, self._rows_of(scene_ids)))

    def hands_over(self, user_id) -> bool:
        """Whether ``user_id`` is scored around the plain encoder the checkpoint keeps for
        strangers (``model.strangers`` 'base_encoder'): anyone it was not trained on. Their
        score is the plain encoder's plus their departure from the prior's mean (``departure``)."""
        return self._stranger_inference is not None and self.trained_row(user_id) == UNKNOWN

    def serves_stranger_encoder(self, user_id) -> bool:
        """Whether ``user_id`` gets exactly the plain encoder's scores: ``hands_over`` them and
        nothing is folded in yet."""
        return self.hands_over(user_id) and self.user_model(user_id) is None

    def stranger_scores(self, inputs, count: int) -> np.ndarray:
        """The plain encoder's rating-scale scores [count, n_actions] (unclipped) of ``encoder_input``'s ``inputs``."""
        inference = self._stranger_inference
        return inference.scores(inference.encode(inputs, count), None, None)

    @property
    def stranger_inference(self) -> InferenceModel | None:
        """The plain encoder's weights and arithmetic strangers are scored with (None: the prior's mean)."""
        return self._stranger_inference

    def departure(self, user_id, h: np.ndarray, scene_rows: np.ndarray) -> np.ndarray:
        """What ``user_id``'s folded-in θ_u adds to the scores of scenes encoded as ``h``
        [n, dim] over the prior's mean θ₀, σ_a xᵀ(θ_u − θ₀) [n, n_actions] on the rating scale
        (zero with nothing folded in): a ``hands_over`` person's personal part."""
        if self.user_model(user_id) is None:
            return np.zeros((len(h), len(self.actions)))
        inference = self._inference
        return inference.scores(h, self._user_row(user_id), scene_rows) - inference.scores(h, self._stranger,
                                                                                           scene_rows)

    def unclipped_scores(self, user_id, inputs, h: np.ndarray, scene_rows: np.ndarray,
                         plain: np.ndarray | None = None) -> np.ndarray:
        """The scores [n, n_actions] ``user_id`` is served, before clipping, of ``encoder_input``'s
        ``inputs`` encoded as ``h`` [n, dim], of training scene rows ``scene_rows`` [n] (or one
        broadcast row): the model's from θ_u, or for one it ``hands_over``, the plain encoder's
        (``plain`` where the caller computed its ``stranger_scores``) plus their ``departure``."""
        if self.hands_over(user_id):
            if plain is None:
                plain = self.stranger_scores(inputs, len(h))
            return plain + self.departure(user_id, h, scene_rows)
        return self._inference.scores(h, self._user_row(user_id), scene_rows)

    def _rows_of(self, scene_ids: Sequence | None) -> np.ndarray:
        """``scene_rows`` of ``scene_ids``; no ids: one UNKNOWN row that broadcasts (no q_i)."""
        return self._scene_rows if scene_ids is None else self.scene_rows(scene_ids)

    def scene_rows(self, scene_ids: Sequence) -> np.ndarray:
        """The rows of q_i, b_i of training scenes ``scene_ids`` (UNKNOWN, -1, for an id the
        model never trained on, and for None)."""
        return self.served.scene_vocabulary.rows(scene_ids)

    def user_theta(self, user_id) -> np.ndarray:
        """θ = (p_u, b_u) [dim+1] (float64) that scores ``user_id`` (see ``unclipped_scores``)."""
        p, b = self._user_row(user_id)
        theta = np.empty(len(p) + 1)
        theta[:-1], theta[-1] = p, b
        return theta

    def _user_row(self, user_id) -> tuple:
        """(p_u, b_u) that scores ``user_id``: folded in, trained, or zero for a stranger."""
        inference = self._inference
        if not inference.personalised:
            return None
        folded = self.user_model(user_id)
        if folded is not None:
            return folded.p.astype(np.float32), np.float32(folded.b)
        row = self.trained_row(user_id)
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

    def rank(self, user_id, scene, candidates: Sequence[str] | None = None, scene_id=None,
             uncertainty=None, explain_entities: int | None = None) -> list:
        """Candidate actions (all by default) sorted best first for ``user_id`` in ``scene``
        (``rank_many``'s entries, with ``score_sd`` given an ``uncertainty`` and ``why`` given
        ``explain_entities``)."""
        if candidates is not None and not list(candidates):
            raise UnknownActionError('candidate list is empty')
        query = RankQuery((scene,), scene_id, None if candidates is None else tuple(candidates),
                          explain=explain_entities is not None)
        return self.rank_many(user_id, [query], uncertainty=uncertainty,
                              explain_entities=explain_entities or 0)[0].ranked

    def rank_scenes(self, user_id, scenes: Sequence, labels: Sequence[str] | None = None,
                    action: str | None = None, uncertainty=None, explain_entities: int | None = None) -> list:
        """Alternative scenes (e.g. candidate robot placements) sorted best first by the
        score of ``action`` (required when the model has more than one)."""
        labels = [str(k) for k in range(len(scenes))] if labels is None else list(labels)
        if len(labels) != len(scenes):
            raise ValueError('one label per candidate scene')
        query = RankQuery(tuple(scenes), None, labels=tuple(labels), action=action,
                          explain=explain_entities is not None)
        return self.rank_many(user_id, [query], uncertainty=uncertainty,
                              explain_entities=explain_entities or 0)[0].ranked

    def query_action(self, query) -> str | None:
        """Check ``query``'s action names against the model; the action that ranks its
        candidate scenes (None for action ranking)."""
        if query.ranks_scenes:
            return self.ranking_action(query.action)
        self.action_columns(query.actions or ())
        return None

    def rank_many(self, user_id, queries: Sequence, top_k: int = 0, uncertainty=None, explain_all: bool = False,
                  explain_entities: int = 5, validate: bool = True) -> list:
        """One ``Scored`` per query of ``queries`` (``RankQuery``, or anything with its
        attributes, such as ``messages.SceneRequest``), every scene of them encoded in one
        pass. Each ranking is cut to ``top_k`` entries (0: all); with ``uncertainty``
        (``personalisation.uncertainty.Uncertainty``) each entry has its ``score_sd`` and the
        ranking its ``p_first_is_best``; an entry has its ``why`` (``explain_entities``
        entities, 0: all) where ``explain_all`` or its query's ``explain`` asks. Raises
        StarsError for the whole group (a bad action name, a non-finite score)."""
        actions = [self.query_action(query) for query in queries]
        graphs = [graph for query in queries for graph in query.graphs]
        scene_ids = [None if query.ranks_scenes else query.scene_id for query in queries for _ in query.graphs]
        inputs = self.encoder_input(graphs, validate)
        h = self._inference.encode(inputs, len(graphs))
        plain = self.stranger_scores(inputs, len(graphs)) if self.hands_over(user_id) else None
        unclipped = self.unclipped_scores(user_id, inputs, h, self.scene_rows(scene_ids), plain)
        scores = self.clip(unclipped)
        served_z = None  # one served around the plain encoder: their z, which their uncertainty centres on
        if plain is not None:
            served_z = (unclipped - self._inference.target_mean) / self._inference.target_std
        if not np.isfinite(scores).all():
            raise StarsError('the model produced a non-finite score')
        results, row = [], 0
        for query, action in zip(queries, actions):
            count = len(query.graphs)
            if query.ranks_scenes:
                names = list(query.labels)
                columns = self.action_columns([action]) * len(names)
                entry_h, rows = h[row:row + count], np.full(len(names), UNKNOWN)
                entry_scores = scores[row:row + count, columns[0]]
                entry_z = None if served_z is None else served_z[row:row + count, columns[0]]
            else:
                names = list(query.actions or self.actions)
                columns = self.action_columns(names)
                entry_h = np.repeat(h[row:row + 1], len(names), axis=0)
                rows = self.scene_rows([query.scene_id] * len(names))
                entry_scores = scores[row, columns]
                entry_z = None if served_z is None else served_z[row, columns]
            spread = (None if uncertainty is None
                      else uncertainty.spread(self, user_id, entry_h, rows, columns, served_z=entry_z))
            whys = (self._whys(user_id, query, entry_h, rows, columns, explain_entities, entry_z)
                    if explain_all or query.explain else None)
            ranked = rank_order(names, entry_scores, None if spread is None else spread.sd, whys)
            p_first = None if spread is None else spread.p_first_is_best(names.index(ranked[0].name))
            results.append(Scored(ranked[:top_k] if top_k else ranked, action, h[row:row + count], p_first,
                                  None if plain is None else plain[row:row + count]))
            row += count
        return results

    def _whys(self, user_id, query, entry_h, scene_rows, columns, entities: int, served_z=None) -> list:
        """``explain.Why`` of each entry of ``query`` (its scenes' removal variants in one pass;
        ``served_z``: the normalised scores of one served around the plain encoder)."""
        scene_ids = None if query.ranks_scenes else [query.scene_id]
        effects = removal_effects(self, user_id, query.graphs, scene_ids)
        if query.ranks_scenes:
            per_entry = [(found, effect[:, columns[0]]) for found, effect in effects]
        else:
            per_entry = [(effects[0][0], effects[0][1][:, column]) for column in columns]
        columns = np.asarray(columns)
        served = None if served_z is None else self._inference.to_rating_scale(served_z, columns)
        return explain(self, user_id, entry_h, scene_rows, columns, per_entry, entities, served)
