"""The Python front door: ``StarsRecommender``, in the shape Surprise and LightFM users know.

    from stars_ros import StarsRecommender, load_dataset
    data = load_dataset('socnav1')                    # or a folder (SocNav1 or generic CSV)
    recommender = StarsRecommender('config/quickstart.yaml').fit(data)
    recommender.predict('a', '01792 B', 'navigate')   # a float, with .details
    recommender.rank('a', '01792 B')                  # [Ranked(name, score, rank)], best first
    recommender.fold_in('newcomer', [('01792 B', 'navigate', 0.9)])
    recommender.save('model.pt'); StarsRecommender.load('model.pt', data=data)

Also: ``predict_batch`` (many (user, scene, action) at once), ``rank_scenes`` (candidate
scenes, e.g. robot placements, best first), ``test`` (held-out figures on data rows),
``refit`` (folded-in or logged users made trained ones), ``placement_map`` (a person's scores
of the robot at every cell of a grid), and ``score_sd`` / ``why`` on predictions and rankings
(``uncertainty=True``, ``explain=True``).

A *scene* is either a scene id the data knew, as written in its files (a string), or a
scene's content: a scene-graph dict (msg_schemas/scene_graph.schema.json) for graph models,
a feature row for tabular ones. Ids are looked up in the data the recommender was fitted
on, or the ``data`` given to ``load``; a checkpoint alone knows ids only as rows of q_i and
b_i, not their content (a graph model's scenes are the data set itself, under its own licence).
So a model loaded without ``data`` takes scenes as content, and an id raises UnknownSceneError
saying to pass ``data``, as a scene request to the node carries its graph.

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

Serving goes through the one serving form the ranker node uses: a ``Predictor`` over a
``model.serving.ServedModel`` of the checkpoint's content, whether ``fit`` made it or ``load``
read it, and the fold-in of ``personalisation.stack.serving_stack``. ``save`` writes a
weights-only checkpoint (``model.checkpoint``) that ``load`` and the node read; folded-in users
are served state, not part of it (the node's store keeps them, ``refit`` makes them trained rows).

Serving imports neither training, torch-geometric nor pandas: ``fit``, ``refit``, ``test``,
``save`` of a loaded model and ``load_dataset`` bring them in when called (``fitted``), so
``StarsRecommender.load`` and the predictor stay light.
"""
from __future__ import annotations

import os
import time
from typing import TYPE_CHECKING, Callable, NamedTuple, Sequence

import numpy as np

from stars_ros.errors import NotFittedError, OutOfScaleError, StarsError, UnknownActionError, UnknownSceneError
from stars_ros.model.config import ExperimentConfig
from stars_ros.model.placement_map import PlacementMap, placement_map
from stars_ros.model.predictor import Predictor, RankQuery
from stars_ros.personalisation.foldin import FoldIn
from stars_ros.personalisation.stack import ServingStack, serving_stack
from stars_ros.state import Rating, check_score

if TYPE_CHECKING:
    from stars_ros.data.ratings import RatingData
    from stars_ros.model.fitted import FittedModel

USER_TERMS = frozenset({'p', 'b_u'})
SCENE_TERMS = frozenset({'q', 'b_i'})


class Prediction(float):
    """A predicted score: a float on the rating scale, with ``user``, ``scene`` (the id
    given, None for content), ``action``, ``est`` (the score), ``details`` (see the
    module docstring), ``score_sd`` (its predictive standard deviation) and ``why`` (its
    ``model.explain.Why``), each None unless asked for."""

    def __new__(cls, est: float, user, scene, action: str, details: dict, score_sd: float | None = None,
                why=None):
        prediction = super().__new__(cls, est)
        prediction.user, prediction.scene, prediction.action, prediction.details = user, scene, action, details
        prediction.score_sd, prediction.why = score_sd, why
        return prediction

    @property
    def est(self) -> float:
        return float(self)

    def __reduce__(self):
        return Prediction, (float(self), self.user, self.scene, self.action, self.details, self.score_sd, self.why)

    def __repr__(self) -> str:
        return (f'Prediction(user={self.user!r}, scene={self.scene!r}, action={self.action!r}, '
                f'est={float(self):.4f}, details={self.details!r})')


class Ranking(list):
    """``Predictor.rank``'s entries (``Ranked``: name, score, rank, score_sd, why), best
    first, with the ``details`` a ``Prediction`` of this user and scene has, and, with
    uncertainty, ``p_first_is_best``: the probability that the first entry is truly the best."""

    def __init__(self, entries: Sequence, details: dict, p_first_is_best: float | None = None):
        super().__init__(entries)
        self.details, self.p_first_is_best = details, p_first_is_best


class Refitted(NamedTuple):
    """What ``StarsRecommender.refit`` made: the new ``recommender``, the users ``solved``
    ({user: foldin.UserModel}), those ``failed`` ({user: why}), the fine-tune's ``losses``
    per epoch and the number of ``ratings`` it was fine-tuned on (0 without fine-tuning)."""

    recommender: 'StarsRecommender'
    solved: dict
    failed: dict
    losses: list
    ratings: int


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


def _data(data) -> 'RatingData':
    from stars_ros.data.ratings import RatingData, load_dataset  # pandas: only for data
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
        self._stack: ServingStack | None = None  # the predictor's fold-in and uncertainty, once needed
        self._recipe = None  # the personalisation.recipe.Recipe of the latest fit (None for a loaded model)
        self._fitted: FittedModel | None = None  # the torch model; a loaded one's is read when first needed
        self._path = None  # the checkpoint a loaded model came from
        self._catalogue: SceneCatalogue | None = None
        self._checkpoint: dict = {}  # what save() writes besides the weights: data, metrics, provenance

    def __repr__(self) -> str:
        label = f'{self.config.encoder.name}-{self.config.model.variant}, dim {self.config.model.dim}'
        if self._predictor is None:
            return f'StarsRecommender({label}, not fitted)'
        return (f'StarsRecommender({label}, {len(self.users)} users, '
                f'{len(self._predictor.served.scene_keys)} trained scenes, actions {list(self.actions)})')

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
        return self.predictor.users

    @property
    def actions(self) -> tuple:
        """The action names, in the order of the model's score columns."""
        return self.predictor.actions

    @property
    def rating_scale(self) -> tuple | None:
        """(lowest, highest) score a rating can take, which served scores are clipped to (None: unbounded)."""
        return self.predictor.rating_scale

    @property
    def fingerprint(self) -> str:
        """The loaded checkpoint's digest ('' for a model fitted here: it has no file)."""
        return self.predictor.fingerprint

    @property
    def data(self) -> RatingData | None:
        """The data whose scene ids predict, rank and fold_in accept (None: content only)."""
        return None if self._catalogue is None else self._catalogue.data

    @property
    def fitted(self) -> FittedModel:
        """The torch model and its vocabularies (``model.fitted``): what ``save`` writes,
        what the offline programs fine-tune (``training.StarsTrainer.resume``). A loaded
        model's is read from its checkpoint when first asked for (serving never needs it)."""
        _ = self.predictor  # NotFittedError before fit or load
        if self._fitted is None:
            from stars_ros.model.checkpoint import load_checkpoint  # the torch modules: only for training
            self._fitted = load_checkpoint(self._path)[0]
        return self._fitted

    def fitted_now(self, stage: str, epoch: int) -> FittedModel:
        """Inside ``fit``'s ``on_epoch(stage, epoch)``: the model ``fit`` would return were training
        to end now (``personalisation.recipe.Recipe.now``): what a learning curve scores."""
        if self._recipe is None:
            raise NotFittedError('fitted_now is for on_epoch, while fit runs')
        return self._recipe.now(stage, epoch)

    @property
    def recipe(self):
        """The ``personalisation.recipe.Recipe`` of the latest ``fit`` (None for a loaded model)."""
        return self._recipe

    @property
    def history(self) -> dict:
        """Training losses per epoch of the latest ``fit`` by stage, as they grow (empty if loaded)."""
        trainer = None if self._recipe is None else self._recipe.trainer
        return {'pretrain': [], 'joint': []} if trainer is None else trainer.history

    @property
    def checkpoint_metadata(self) -> dict:
        """What ``save`` writes besides the weights: ``data``, ``metrics``, ``provenance``."""
        return {key: dict(value) for key, value in self._checkpoint.items()}

    def _serve(self, fitted: 'FittedModel | None', predictor: Predictor, data: 'RatingData | None') -> None:
        self._fitted, self._predictor, self._stack = fitted, predictor, None
        self._catalogue = None if data is None else SceneCatalogue(data, predictor.served.config.model.item_key)

    # -- fit, save, load -----------------------------------------------------------------
    def fit(self, data, rows: Sequence[int] | None = None,
            on_epoch: Callable[[str, int], None] | None = None) -> 'StarsRecommender':
        """Train on ``rows`` of ``data`` (a RatingData, or what ``load_dataset`` reads;
        every rating by default) by the one recipe (``personalisation.recipe``): the model learns from
        every rating given, a personalised variant gets the fold-in's prior
        (``personalisation.prior``), its rating noise and tails from a fit on less, so a person
        folded in here is treated as on the robot. Returns self. ``on_epoch(stage, epoch)`` is
        called after each epoch of the model's training (``history`` holds the losses;
        ``fitted_now`` the model so far). Earlier fold-ins are dropped. Leaves torch's threads,
        default dtype and random state as it found them."""
        from stars_ros.personalisation.recipe import Recipe  # training (and pandas): only to fit

        data = _data(data)
        rows = np.arange(len(data)) if rows is None else np.asarray(rows, dtype=np.int64)
        started = time.perf_counter()
        self._recipe = recipe = Recipe(self.config)
        trainer = recipe.fit(data, rows, on_epoch)
        seconds = time.perf_counter() - started
        self._serve(trainer, Predictor.from_model(trainer), data)
        self._checkpoint = {
            'data': {'fingerprint': data.fingerprint, 'source': data.source, 'n_ratings': len(data),
                     'n_train': len(rows)},
            'metrics': {},
            'provenance': {'written_by': 'stars_ros.StarsRecommender', 'train_seconds': round(seconds, 1),
                           'notes': list(data.notes)}}
        return self

    def save(self, path, *, data: dict | None = None, metrics: dict | None = None,
             provenance: dict | None = None) -> str:
        """Write the model to a weights-only checkpoint at ``path`` (what ``load`` and the
        ranker node read); returns its digest, the fingerprint rankings will carry. ``data``,
        ``metrics`` and ``provenance`` add to what ``fit`` recorded of each. Folded-in users
        are not written (see the module docstring)."""
        from stars_ros.model.checkpoint import save_checkpoint

        extra = {'data': data, 'metrics': metrics, 'provenance': provenance}
        written = {key: {**value, **(extra[key] or {})} for key, value in self._checkpoint.items()}
        return save_checkpoint(self.fitted, path, **written)

    @classmethod
    def load(cls, path, data=None) -> 'StarsRecommender':
        """The recommender stored at ``path`` (CheckpointError for a missing, corrupted or
        incompatible file). ``data`` (a RatingData or what ``load_dataset`` reads) lets
        predict, rank and fold_in name its scenes by id; without it, scenes are given as
        content (the module docstring says why a checkpoint does not hold them)."""
        predictor = Predictor.load(path)
        recommender = cls(predictor.served.config)
        recommender._path = path
        recommender._serve(None, predictor, None if data is None else _data(data))
        metadata = predictor.metadata
        recommender._checkpoint = {key: dict(metadata.get(key) or {}) for key in ('data', 'metrics', 'provenance')}
        return recommender

    def test(self, data=None, rows: Sequence[int] | None = None) -> dict:
        """Macro-averaged MSE, RMSE, Pearson r and CCC (and ``n``) on ``rows`` of ``data``
        (default: the data ids are looked up in; every row by default), on the rating scale,
        each rating scored as ``predict`` serves it (``model.scoring``; Surprise's ``test`` on
        a test set)."""
        data = self.data if data is None else _data(data)
        if data is None:
            raise ValueError('test needs data: give it, or load the model with data=...')
        from stars_ros.model.metrics import regression_report
        from stars_ros.model.scoring import served_predictions

        rows = np.arange(len(data)) if rows is None else np.asarray(rows, dtype=np.int64)
        predictions = served_predictions(self.predictor, data, rows)
        return regression_report(data.scores[rows], predictions, data.actions[rows])

    def refit(self, ratings: dict, regularisation: dict | None = None, data=None, epochs: int = 0,
              default_regularisation: float | None = None) -> Refitted:
        """A new recommender in which each user of ``ratings`` ({user: [state.Rating]}, as
        ``personalisation.refit`` reads them from the node's logs or state store) is a
        trained user: their (p_u, b_u) solved as ``fold_in`` and the node solve them, but as
        the model scores a trained row (not around a plain encoder for strangers) (λ from
        ``regularisation`` {user: λ}, else ``default_regularisation``, else the posterior),
        written into new or replaced rows of the user table. With ``epochs`` > 0 every
        parameter is then fine-tuned for that many joint epochs on the feedback (plus the
        rows of ``data``, when given) with this model's training settings. The new
        recommender keeps this one's checkpoint metadata under ``parent``."""
        from stars_ros.model.training import StarsTrainer  # training: only to refit
        from stars_ros.personalisation.foldin import DEFAULT_REGULARISATION
        from stars_ros.personalisation.refit import feedback_data

        solver, solved, failed = self._fold_in_solver(), {}, {}
        for user, user_ratings in ratings.items():
            lam = (regularisation or {}).get(user, default_regularisation)
            try:
                solved[user] = solver.fit(user_ratings, user, DEFAULT_REGULARISATION if lam is None else lam,
                                          hand_over=False)  # a trained row: scored as the model scores
            except StarsError as error:
                failed[user] = str(error)
        trainer = StarsTrainer.resume(self.fitted).extended(users=list(solved))
        for user, model in solved.items():
            trainer.set_user_row(user, model.p, model.b)
        losses, fine_tuned_on = [], 0
        if epochs > 0:
            feedback = feedback_data(trainer, {u: r for u, r in ratings.items() if u in solved},
                                     None if data is None else _data(data))
            trainer = trainer.extended(scene_keys=feedback.scene_keys)
            losses, fine_tuned_on = trainer.fine_tune(feedback, epochs), len(feedback)
        child = StarsRecommender(self.config)
        child._serve(trainer, Predictor.from_model(trainer), self.data)
        parent = self._checkpoint
        child._checkpoint = {'data': dict(parent.get('data', {})), 'metrics': {'parent': dict(parent.get('metrics',
                                                                                                         {}))},
                             'provenance': {'parent': dict(parent.get('provenance', {}))}}
        return Refitted(child, solved, failed, losses, fine_tuned_on)

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
        served = predictor.served
        folded = predictor.user_model(user)
        details = {'known_user': predictor.knows_user(user), 'folded_in': 0 if folded is None else folded.n_ratings,
                   'known_scene': item_key is not None and item_key in served.scene_vocabulary}
        parts, reasons = served.config.model.parts, []
        if parts & USER_TERMS and not details['known_user'] and folded is None:
            reasons.append('unknown user')
        if parts & SCENE_TERMS and not details['known_scene']:
            reasons.append('unknown scene')
        if reasons:
            details['reason'] = '; '.join(reasons)
        return details

    def _options(self, uncertainty: bool, explain: bool) -> dict:
        """``Predictor.rank_many``'s options for ``score_sd`` (``uncertainty``) and ``why``."""
        options = {'explain_all': explain, 'explain_entities': 0}
        if uncertainty:
            self._fold_in_solver()  # StarsError for a model without users
            options['uncertainty'] = self._stack.uncertainty
        return options

    def _fold_in_solver(self) -> FoldIn:
        if self._stack is None:  # each scene encoded on its own, as the node ranks one scene a request:
            # a scene's h (and so a fold-in) does not depend on the scenes encoded beside it
            self._stack = serving_stack(self.predictor, scene_by_scene=True)
        return self._stack.require_foldin()

    def predict(self, user, scene, action: str, uncertainty: bool = False, explain: bool = False) -> Prediction:
        """The score ``user`` would give ``action`` in ``scene`` (an id or content), on the
        rating scale; the same number ``rank`` gives it. ``uncertainty``: with its
        ``score_sd``; ``explain``: with its ``why`` (``model.explain.Why``)."""
        return self.predict_batch([(user, scene, action)], uncertainty, explain)[0]

    def predict_batch(self, requests: Sequence[tuple], uncertainty: bool = False,
                      explain: bool = False) -> list:
        """``predict`` of each ``(user, scene, action)`` of ``requests``, in order; each
        user's scenes are encoded in one pass."""
        predictor, by_user = self.predictor, {}
        for k, (user, scene, action) in enumerate(requests):
            scene_input, scene_id, item_key = self._scene(scene)
            query = RankQuery((scene_input,), item_key, (str(action),))
            by_user.setdefault(user, []).append((k, query, scene_id))
        predictions = [None] * len(requests)
        options = self._options(uncertainty, explain)
        for user, members in by_user.items():
            scored = predictor.rank_many(user, [query for _, query, _ in members], **options)
            for (k, query, scene_id), result in zip(members, scored):
                entry = result.ranked[0]
                predictions[k] = Prediction(entry.score, user, scene_id, entry.name,
                                            self._details(user, query.scene_id), entry.score_sd, entry.why)
        return predictions

    def rank(self, user, scene, candidates: Sequence[str] | None = None, uncertainty: bool = False,
             explain: bool = False) -> Ranking:
        """The model's actions (or ``candidates``) for ``user`` in ``scene``, best first:
        ``Ranked(name, score, rank, score_sd, why)`` entries, scores clipped to the rating
        scale; ``score_sd`` with ``uncertainty``, ``why`` with ``explain`` (else None)."""
        scene_input, _, item_key = self._scene(scene)
        if candidates is not None and not list(candidates):
            raise UnknownActionError('candidate list is empty')
        query = RankQuery((scene_input,), item_key, None if candidates is None else tuple(candidates))
        scored = self.predictor.rank_many(user, [query], **self._options(uncertainty, explain))[0]
        return Ranking(scored.ranked, self._details(user, item_key), scored.p_first_is_best)

    def rank_scenes(self, user, scenes: Sequence, labels: Sequence[str] | None = None, action: str | None = None,
                    uncertainty: bool = False, explain: bool = False) -> Ranking:
        """Candidate ``scenes`` (ids or content; e.g. the robot's possible placements) best
        first by the score of ``action`` (needed when the model has several), labelled by
        ``labels`` (default: their ids, else their positions '0', '1', ...). Each is scored as
        a new scene (no q_i, b_i): the candidates are alternatives the robot could make."""
        if not scenes:
            raise ValueError('no candidate scenes')
        resolved = [self._scene(scene) for scene in scenes]
        if labels is None:
            labels = [scene_id if scene_id is not None else str(k) for k, (_, scene_id, _) in enumerate(resolved)]
        if len(labels) != len(scenes):
            raise ValueError('one label per candidate scene')
        query = RankQuery(tuple(scene_input for scene_input, _, _ in resolved), labels=tuple(map(str, labels)),
                          action=action)
        scored = self.predictor.rank_many(user, [query], **self._options(uncertainty, explain))[0]
        return Ranking(scored.ranked, self._details(user, None), scored.p_first_is_best)

    def placement_map(self, user, scene: dict, size: float = 8.0, resolution: float = 0.125,
                      heading: float | None = None, action: str | None = None) -> PlacementMap:
        """``user``'s scores and ``score_sd`` of the robot placed at the centre of every cell of a
        square grid ``size`` metres wide centred on it in ``scene`` (content), keeping its heading
        or turned by ``heading``: each cell what ``rank_scenes`` gives that placement
        (``model.placement_map``; BadMapRequest, with its ``kind``, for what it refuses)."""
        uncertainty = self._options(True, False)['uncertainty'] if self.predictor.inference.personalised else None
        return placement_map(self.predictor, uncertainty, user, scene, size, resolution, heading, action)

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
            try:
                check_score(score, self.rating_scale, f'rating {k}: score')
            except OutOfScaleError as error:  # the front door's contract: a bad rating is a ValueError
                raise ValueError(str(error)) from None
            scene_input, _, item_key = self._scene(scene)
            folded.append(Rating(scene_input, str(action), score, item_key))
        if not folded:
            predictor.set_user_model(user, None)
            return self
        options = {} if regularisation is None else {'regularisation': regularisation}
        predictor.set_user_model(user, self._fold_in_solver().fit(folded, str(user), **options))
        return self
