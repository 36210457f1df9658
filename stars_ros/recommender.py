"""The Python front door: ``StarsRecommender``, in the shape Surprise and LightFM users know.

    from stars_ros import StarsRecommender, load_dataset
    data = load_dataset('socnav1')                    # or a folder (SocNav1 or generic CSV)
    recommender = StarsRecommender('config/quickstart.yaml').fit(data)
    recommender.predict('a', '01792 B', 'navigate')   # a float, with .details
    recommender.rank('a', '01792 B')                  # [Ranked(name, score, rank)], best first
    recommender.fold_in('newcomer', [('01792 B', 'navigate', 0.9)])
    recommender.save('model.pt'); StarsRecommender.load('model.pt', data=data)

A *scene* is either a scene id the data knew, as written in its files (a string), or a
scene's content: a scene-graph dict (msg_schemas/scene_graph.schema.json) for graph models,
a feature row for tabular ones. Ids are looked up in the data the recommender was fitted
on, or the ``data`` given to ``load``; a checkpoint alone knows ids only as rows of q_i and
b_i, not their content.

``predict`` returns a ``Prediction``: a ``float`` (the score on the rating scale, clipped to
it), so it adds and compares as one, carrying Surprise's fields ``user``, ``scene``,
``action``, ``est`` and ``details``. Nothing raises for an unknown user or scene: as on the
robot, an unknown user gets the population prior's mean (p_u, b_u) (zero for a checkpoint
without a stored prior) and an unknown scene q_i = 0, b_i = 0 (the content term and the
population offsets remain), and ``details['reason']`` says which:
'unknown user', 'unknown scene' or both ('unknown user; unknown scene'). ``details`` also
holds ``known_user`` (in the training data), ``folded_in`` (ratings the user's fold-in was
solved from, 0 for none) and ``known_scene`` (has trained q_i, b_i). A reason is given only
for a term the variant has (``base`` has neither; ``user_bias`` no scene term). ``rank``
returns a ``Ranking``, a list with the same ``details``.

Serving goes through the one serving form the ranker node uses: the recommender holds a
``Predictor`` (``predictor``), built from the fitted model in memory after ``fit`` and read
from the checkpoint by ``load``; ``fold_in`` solves the user with
``personalisation.foldin.FoldIn`` and serves them through ``Predictor.set_user_model``.
``save`` writes a weights-only checkpoint (``model.checkpoint``) that ``load`` and the node
read; folded-in users are served state, not part of it (the node keeps them in its state
file, ``offline_training.refit`` writes them into a checkpoint).
"""
from __future__ import annotations

import math
import os
import time
from typing import Sequence

import numpy as np

from stars_ros.data.ratings import RatingData, load_dataset
from stars_ros.errors import UnknownSceneError
from stars_ros.model.checkpoint import save_checkpoint
from stars_ros.model.config import ExperimentConfig
from stars_ros.model.predictor import Predictor
from stars_ros.model.training import NotFittedError, StarsTrainer, torch_state_kept
from stars_ros.personalisation.foldin import FoldIn
from stars_ros.state import Rating
from stars_ros.personalisation.prior import estimate_prior, held_out_split

USER_TERMS = frozenset({'p', 'b_u'})
SCENE_TERMS = frozenset({'q', 'b_i'})


class Prediction(float):
    """A predicted score: a float on the rating scale, with ``user``, ``scene`` (the id
    given, None for content), ``action``, ``est`` (the score) and ``details`` (see the
    module docstring)."""

    def __new__(cls, est: float, user, scene, action: str, details: dict):
        prediction = super().__new__(cls, est)
        prediction.user, prediction.scene, prediction.action, prediction.details = user, scene, action, details
        return prediction

    @property
    def est(self) -> float:
        return float(self)

    def __reduce__(self):
        return Prediction, (float(self), self.user, self.scene, self.action, self.details)

    def __repr__(self) -> str:
        return (f'Prediction(user={self.user!r}, scene={self.scene!r}, action={self.action!r}, '
                f'est={float(self):.4f}, details={self.details!r})')


class Ranking(list):
    """``Predictor.rank``'s entries (``Ranked``: name, score, rank), best first, with the
    ``details`` a ``Prediction`` of this user and scene has."""

    def __init__(self, entries: Sequence, details: dict):
        super().__init__(entries)
        self.details = details


class SceneCatalogue:
    """The scenes of a RatingData by id: each one's encoder input (a ``SceneGraph`` or a
    feature row, made once and kept, so fold-in's cache of encoded scenes finds it again)
    and its item key (the row of q_i, b_i under ``keying``)."""

    def __init__(self, data: RatingData, keying: str):
        self.data = data
        self.rows = {key: row for row, key in enumerate(data.scene_keys)}
        self.items = data.item_keys(keying)
        self.variants = {}  # SocNav1: an identifier with two contents is kept as '<identifier>#<digest>'
        for key in data.scene_keys:
            if '#' in key:
                self.variants.setdefault(key.rsplit('#', 1)[0], []).append(key)
        self._inputs = {}

    def resolve(self, scene_id: str) -> tuple:
        """(encoder input, item key) of ``scene_id``; UnknownSceneError if the data lacks it."""
        row = self.rows.get(scene_id)
        if row is None:
            if scene_id in self.variants:
                raise UnknownSceneError(f"scene id '{scene_id}' has {len(self.variants[scene_id])} different contents "
                                        f'in {self.data.source}: name one of {self.variants[scene_id]}')
            raise UnknownSceneError(f"no scene '{scene_id}' in {self.data.source}: pass the scene's content "
                                    '(a scene-graph dict or a feature row) instead of an id')
        if row not in self._inputs:
            self._inputs[row] = self.data.store.scene(row)
        return self._inputs[row], self.items[row]


def _config(config) -> ExperimentConfig:
    if isinstance(config, ExperimentConfig):
        return config
    if config is None or isinstance(config, dict):
        return ExperimentConfig.from_dict(config or {})
    if isinstance(config, (str, os.PathLike)):
        return ExperimentConfig.from_yaml(config)
    raise TypeError(f'config must be an ExperimentConfig, a YAML path or a dict, got {type(config).__name__}')


def _data(data) -> RatingData:
    return data if isinstance(data, RatingData) else load_dataset(data)


class StarsRecommender:
    """Fit a StARS model, predict and rank for a user, fold a user in, save and load.

    Args:
        config (ExperimentConfig or str or dict, optional): the experiment settings, or the
            path of a YAML file of them (``config/``), or their dict (default: the defaults).
    """

    def __init__(self, config=None):
        self.config = _config(config)
        self._predictor: Predictor | None = None
        self._fold_in: FoldIn | None = None
        self._catalogue: SceneCatalogue | None = None
        self._checkpoint: dict = {}  # what save() writes besides the weights: data, metrics, provenance

    def __repr__(self) -> str:
        label = f'{self.config.encoder.name}-{self.config.model.variant}, dim {self.config.model.dim}'
        if self._predictor is None:
            return f'StarsRecommender({label}, not fitted)'
        return (f'StarsRecommender({label}, {len(self.users)} users, '
                f'{len(self._predictor.recommender.scene_keys)} scenes, actions {list(self.actions)})')

    # -- state ---------------------------------------------------------------------------
    @property
    def predictor(self) -> Predictor:
        """The serving form the node uses; predict, rank and fold_in go through it."""
        if self._predictor is None:
            raise NotFittedError('this StarsRecommender is not fitted: call fit() or StarsRecommender.load(path)')
        return self._predictor

    @property
    def users(self) -> tuple:
        """The users of the training data (folded-in users: ``predictor.user_models``)."""
        return self.predictor.recommender.users

    @property
    def actions(self) -> tuple:
        """The action names, in the order of the model's score columns."""
        return self.predictor.actions

    @property
    def rating_scale(self) -> tuple | None:
        """(lowest, highest) score a rating can take, which served scores are clipped to (None: unbounded)."""
        return self.predictor.recommender.rating_scale

    @property
    def fingerprint(self) -> str:
        """The loaded checkpoint's digest ('' for a model fitted here: it has no file)."""
        return self.predictor.fingerprint

    @property
    def data(self) -> RatingData | None:
        """The data whose scene ids predict, rank and fold_in accept (None: content only)."""
        return None if self._catalogue is None else self._catalogue.data

    def _serve(self, trainer: StarsTrainer, predictor: Predictor, data: RatingData | None) -> None:
        self._predictor, self._fold_in = predictor, None
        self._catalogue = None if data is None else SceneCatalogue(data, trainer.config.model.item_key)

    # -- fit, save, load -----------------------------------------------------------------
    def fit(self, data, rows: Sequence[int] | None = None,
            noise_rows: Sequence[int] | None = None) -> 'StarsRecommender':
        """Train on ``rows`` of ``data`` (a RatingData, or what ``load_dataset`` reads;
        every rating by default); returns self. A personalised variant also gets the
        fold-in's prior (``personalisation.prior``), its rating noise and tails from
        ``noise_rows`` (held-out ratings of the trained people) when given; else a seeded
        ``prior.NOISE_SHARE`` of each person's examples is held out of the training for them
        (``prior.held_out_split``), as ``train`` and ``kshot`` hold out theirs, so a person
        folded in here is treated as on the robot. Earlier fold-ins are dropped. Leaves
        torch's threads, default dtype and random state as it found them."""
        data = _data(data)
        rows = np.arange(len(data)) if rows is None else np.asarray(rows, dtype=np.int64)
        started = time.perf_counter()
        if self.config.model.variant != 'base' and noise_rows is None:  # base: no fold-in, no prior
            rows, noise_rows = held_out_split(data, rows, seed=self.config.split.seed)
        with torch_state_kept():
            trainer = StarsTrainer(self.config).fit(data, rows)
            if trainer.require_model().personalised:
                trainer.user_prior = estimate_prior(trainer, data, rows, noise_rows=noise_rows).to_dict()
        self._serve(trainer, Predictor.from_model(trainer), data)
        self._checkpoint = {
            'data': {'fingerprint': data.fingerprint, 'source': data.source, 'n_ratings': len(data),
                     'n_train': len(rows)},
            'metrics': {},
            'provenance': {'written_by': 'stars_ros.StarsRecommender', 'train_seconds':
                           round(time.perf_counter() - started, 1), 'notes': list(data.notes)}}
        return self

    def save(self, path) -> str:
        """Write the model to a weights-only checkpoint at ``path`` (what ``load`` and the
        ranker node read); returns its digest, the fingerprint rankings will carry. Folded-in
        users are not written (see the module docstring)."""
        return save_checkpoint(self.predictor.recommender, path, **self._checkpoint)

    @classmethod
    def load(cls, path, data=None) -> 'StarsRecommender':
        """The recommender stored at ``path`` (CheckpointError for a missing, corrupted or
        incompatible file). ``data`` (a RatingData or what ``load_dataset`` reads) lets
        predict, rank and fold_in name its scenes by id; without it, scenes are given as
        content."""
        predictor = Predictor.load(path)
        trainer = predictor.recommender
        recommender = cls(trainer.config)
        recommender._serve(trainer, predictor, None if data is None else _data(data))
        metadata = predictor.metadata
        recommender._checkpoint = {key: dict(metadata.get(key) or {}) for key in ('data', 'metrics', 'provenance')}
        return recommender

    # -- serving -------------------------------------------------------------------------
    def _scene(self, scene) -> tuple:
        """(encoder input, the id given or None, item key or None) of a scene id or content."""
        if isinstance(scene, str):
            if self._catalogue is None:
                raise UnknownSceneError(f"scene '{scene}' is named by id, but this recommender has no data to "
                                        "look ids up in: StarsRecommender.load(path, data=...), or pass the "
                                        "scene's content")
            scene_input, item_key = self._catalogue.resolve(scene)
            return scene_input, scene, item_key
        return scene, None, None

    def _details(self, user, item_key) -> dict:
        predictor = self.predictor
        trainer = predictor.recommender
        folded = predictor.user_model(user)
        details = {'known_user': predictor.knows_user(user), 'folded_in': 0 if folded is None else folded.n_ratings,
                   'known_scene': item_key is not None and item_key in trainer.scene_vocabulary}
        parts, reasons = trainer.config.model.parts, []
        if parts & USER_TERMS and not details['known_user'] and folded is None:
            reasons.append('unknown user')
        if parts & SCENE_TERMS and not details['known_scene']:
            reasons.append('unknown scene')
        if reasons:
            details['reason'] = '; '.join(reasons)
        return details

    def predict(self, user, scene, action: str) -> Prediction:
        """The score ``user`` would give ``action`` in ``scene`` (an id or content), on the
        rating scale; the same number ``rank`` gives it."""
        predictor = self.predictor
        scene_input, scene_id, item_key = self._scene(scene)
        column = predictor.action_columns([action])[0]
        score = predictor.score(user, [scene_input], [item_key])[0, column]
        return Prediction(float(score), user, scene_id, action, self._details(user, item_key))

    def rank(self, user, scene, candidates: Sequence[str] | None = None) -> Ranking:
        """The model's actions (or ``candidates``) for ``user`` in ``scene``, best first:
        ``Ranked(name, score, rank)`` entries, scores clipped to the rating scale."""
        predictor = self.predictor
        scene_input, _, item_key = self._scene(scene)
        return Ranking(predictor.rank(user, scene_input, candidates, scene_id=item_key), self._details(user, item_key))

    def fold_in(self, user, ratings: Sequence[tuple], regularisation: float | None = None) -> 'StarsRecommender':
        """Solve ``user`` from ``ratings``, ``(scene, action, score)`` triples (scores on the
        rating scale), and serve them with it from now on; returns self. The solve starts
        from the user's trained row if the training data had them, else from the population
        prior, and uses exactly these ratings: pass all of a user's ratings each time (an
        earlier fold-in of the user is replaced; an empty list removes it). ``regularisation``:
        a ridge λ instead of ``FoldIn``'s default."""
        if user is None:
            raise ValueError('fold_in needs a user id')
        predictor = self.predictor
        folded = []
        for k, triple in enumerate(ratings):
            try:
                scene, action, score = triple
                score = float(score)
            except (TypeError, ValueError):
                raise ValueError(f'rating {k}: expected (scene, action, score), got {triple!r}') from None
            scale = self.rating_scale
            if not math.isfinite(score) or (scale is not None and not scale[0] <= score <= scale[1]):
                raise ValueError(f'rating {k}: score {score} is not on the rating scale {scale}')
            scene_input, _, item_key = self._scene(scene)
            folded.append(Rating(scene_input, str(action), score, item_key))
        if not folded:
            predictor.set_user_model(user, None)
            return self
        if self._fold_in is None:
            self._fold_in = FoldIn(predictor)
        options = {} if regularisation is None else {'regularisation': regularisation}
        predictor.set_user_model(user, self._fold_in.fit(folded, str(user), **options))
        return self
