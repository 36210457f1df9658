"""Fold a person into a trained StARS model from a few ratings: the exact Gaussian posterior.

With everything but the person fixed, the model's normalised prediction is linear in
θ_u = (p_u, b_u):

    z(u, i, a) = p_uᵀ(q̄_i ⊙ r_a) + b_u + [h_iᵀ r_a + b_i + b],    q̄_i = q_i + h_i

(q_i = 0, b_i = 0 for scenes unseen in training; the ablations without the residual term
drop h_iᵀ r_a). For ratings (i_j, a_j, y_j) with z_j = (y_j − μ_a) / σ_a, x_j = [q̄_i ⊙ r_a, 1]
and c_j the bracket, the fold-in treats θ_u as Gaussian: a prior N(m₀, S₀) (``prior``: the
person's own trained row and covariance when the checkpoint knows them, else the population
prior) and independent noise z_j − c_j − x_jᵀθ ~ N(0, σ²_{a_j}) give the posterior

    Λ = S₀⁻¹ + Xᵀ D⁻¹ X,    m = Λ⁻¹ (S₀⁻¹ m₀ + Xᵀ D⁻¹ (z − c)),    D = diag(σ²_a),

one (d+1)×(d+1) Cholesky solve in float64 per prior scale: a person's departure from the
population is not known in advance, so the prior covariance is τS₀ with τ one of
``prior.PRIOR_SCALES`` (0: the person is the population mean), each weighted by the
marginal likelihood of the person's answers under it (``scale_mixture_posterior``). A person
whose answers the population explains keeps close to it; one who departs consistently moves
as far as their answers warrant. The served θ is the mixture's mean, its covariance (the
mixture's, moment-matched) what ``uncertainty`` turns into a score's standard deviation. A
person the checkpoint knows starts from their own row and covariance, their departure
already measured, and gets the plain Gaussian posterior above.

**Implicit outcomes** (``Rating.implicit``: the person stayed engaged after the robot acted,
score the rating scale's top H, or disengaged, its bottom L) are observations of their own
kind, not ratings: the outcome o is Bernoulli with P(o = H) = (y − L) / (H − L), y the
person's rating, so E[o] = y and Var[o | y] ≤ (H − L)² / 4. Taken as Gaussian with that bound,
an outcome's noise is σ²_a + ``implicit_variance`` / σ_a² (z units; default (H − L)² / 4 on
the rating scale, the law of total variance): the same linear row as a rating of that scene
and action, weighted less.

**Handing over from the plain encoder.** A checkpoint that keeps a plain encoder for strangers
(``model.strangers`` 'base_encoder') serves a person it was not trained on that encoder's
prediction z⁰ until they rate anything (``Predictor.hands_over``). Their fold-in then solves
for their departure from it: c_j becomes z⁰_j − x_jᵀm₀ (``hand_over_shift`` adds the
difference), so θ = m₀ reproduces the plain encoder exactly and each rating moves the
prediction from there, z = z⁰ + xᵀ(θ − m₀), instead of dropping it to the prior's mean first.

No λ is set by hand; a positive ``regularisation`` λ overrides the posterior with the ridge solve
argmin ‖Xθ − (z − c)‖² + λ‖θ − m₀‖² (covariance σ̄²(XᵀX + λI)⁻¹, σ̄² the mean noise).

Encoding a scene is what costs, so h_i is cached per scene object, and the ranker node hands
over the h its ranking of the rated scene computed (``remember``), with the plain encoder's
scores where that ranking served a person around it: re-solving a user after one more rating
is then one solve. x_j and c_j come from the predictor's
``InferenceModel.linear_form``: the weights and the arithmetic the node scores with, not a
copy of them. ROS-free: the ranker node, the offline refit, the front door and the k-shot
evaluation all use ``FoldIn``.
"""
from __future__ import annotations

import collections
import threading
from typing import Callable, NamedTuple, Sequence

import numpy as np

from stars_ros.errors import OutOfScaleError, StarsError, UnknownActionError
from stars_ros.model.vocabulary import UNKNOWN
from stars_ros.personalisation.gaussian import gaussian_posterior, scale_mixture_posterior, solve_ridge
from stars_ros.personalisation.prior import PRIOR_SCALES, UserPrior, prior_of
from stars_ros.state.person import Rating, UserModel, check_score

DEFAULT_REGULARISATION = 0.0  # 0: the Gaussian posterior; a positive λ: the ridge override
DEFAULT_CACHE_SCENES = 4096


class _Encoded(NamedTuple):
    """What ``FoldIn`` keeps of one scene: the scene (kept alive, so its id is not reused), its
    h, whether a store has yet to be handed it, and the plain encoder's scores (None: not kept)."""

    scene: object
    h: np.ndarray
    fresh: bool
    plain: np.ndarray | None


def rating_from_feedback(feedback, request, predictor) -> Rating | str:
    """The Rating a feedback message (messages.Feedback) gives about the scene request it
    names (messages.SceneRequest) under ``predictor``'s model, or why it gives none. The node
    and the offline refit both use this, so they fold in the same ratings: an action's
    feedback rates the scene (with its q_i when it is a training scene); a candidate's
    feedback rates that candidate scene under the action that ranked the candidates. An
    implicit outcome keeps its message (so it stays implicit wherever the rating goes). Its
    score has passed ``check_feedback_score`` (the node's intake, the refit's reader)."""
    source = feedback.as_message() if feedback.implicit else None
    if feedback.action is not None:
        if request.ranks_scenes:
            return (f"feedback names action '{feedback.action}' but scene '{feedback.scene_id}' "
                    'ranked candidate scenes')
        return Rating(request.graphs[0], feedback.action, feedback.score, request.scene_id, feedback=source)
    if not request.ranks_scenes or feedback.candidate not in request.labels:
        return f"scene '{feedback.scene_id}' had no candidate '{feedback.candidate}'"
    try:
        action = predictor.ranking_action(request.action)  # the one the node ranked them by
    except UnknownActionError as error:
        return f"scene '{feedback.scene_id}': {error}"
    return Rating(request.graphs[request.labels.index(feedback.candidate)], action, feedback.score, None,
                  feedback=source)


def check_feedback_score(feedback, scale) -> None:
    """OutOfScaleError for feedback (a ``messages.Feedback`` or a stored ``Rating``: its
    ``score`` and ``implicit``) whose score is off the rating ``scale``, or, for an implicit
    outcome, neither its top nor its bottom: the one check of a feedback's score, before it
    is stored (the node) or refit on (the logs, the store)."""
    check_score(feedback.score, scale, 'feedback score')
    if feedback.implicit:  # an outcome is the scale's top or bottom (docs/hri.md)
        check_outcome(feedback.score, scale)


def check_outcome(score: float, scale) -> None:
    """OutOfScaleError unless ``score`` is an implicit outcome on ``scale``: its top (stayed
    engaged) or bottom (disengaged); any score for a checkpoint without a scale."""
    if scale is not None and score not in (float(scale[0]), float(scale[1])):
        raise OutOfScaleError(f"implicit outcome scores {score:g}: an outcome is the rating scale's top {scale[1]:g} "
                              f'(stayed engaged) or bottom {scale[0]:g} (disengaged)')


class FoldIn:
    """Closed-form user fold-in against one trained model (see the module docstring).

    Args:
        predictor (Predictor): the model to fold users into; its weights are only read.
        prior (UserPrior, optional): the population prior and noise; default: the one the
            checkpoint stores (``prior.prior_of``).
        implicit_variance (float, optional): an implicit outcome's extra noise variance on
            the rating scale (default: (H − L)² / 4 of the checkpoint's rating scale; 1.0 in z
            units for a model without one).
        cache_scenes (int, optional): most encoded scenes, and most ratings' regression rows,
            kept (least recently used go).
        scene_by_scene (bool, optional): encode each scene in a forward pass of its own. A
            scene's h then does not depend on the scenes encoded with it (in a batch it
            differs by float rounding), so robots that solve a user from the same shared
            ratings get the same model to the last bit.

    ``fit`` may be called from several threads; the caches are locked. A user is re-solved
    from all their ratings at each new one, so each rating's row of the regression is built
    once and kept rather than at every solve (``benchmarks/foldin.py`` times both ways in one
    run; docs/personalisation.md).
    """

    def __init__(self, predictor, cache_scenes: int = DEFAULT_CACHE_SCENES, scene_by_scene: bool = False,
                 prior: UserPrior | None = None, implicit_variance: float | None = None):
        served = predictor.served
        if not served.personalised:
            raise StarsError(f"fold-in needs a personalised model; this one is '{served.variant}'")
        self.predictor = predictor
        self.inference = predictor.inference  # the weights and the scoring arithmetic, shared
        self.actions = tuple(predictor.actions)
        self._action_index = {a: k for k, a in enumerate(self.actions)}
        self.dim = self.inference.dim
        self.user_prior = prior_of(served, self.inference) if prior is None else prior
        self.population = self.user_prior.mean
        self.noise = self.user_prior.noise
        self.implicit_noise = self._implicit_noise(implicit_variance, served.rating_scale)
        self._population_precision = np.linalg.inv(self.user_prior.covariance)
        self._population_logdet = float(np.linalg.slogdet(self.user_prior.covariance)[1])
        self._stranger_covariance = float(np.mean(PRIOR_SCALES)) * self.user_prior.covariance  # read per ranking
        self._stranger_covariance.flags.writeable = False
        self._precisions = collections.OrderedDict()  # trained user row -> precision of their prior
        self._cache = collections.OrderedDict()  # id(scene) -> _Encoded
        self.stored: Callable[[list], dict] | None = None  # scenes -> {id(scene): h} a store keeps for them
        self._cache_scenes = cache_scenes
        self.scene_by_scene = scene_by_scene
        self._rows = collections.OrderedDict()  # id(Rating) -> (rating, x row, y = z - c, hand_over_shift)
        self._lock = threading.Lock()
        scale_mixture_posterior(np.ones((1, self.dim + 1)), np.zeros(1), np.ones(1), self.population,
                                self._population_precision, self._population_logdet)
        # a process's first LAPACK solve costs milliseconds: paid at load, not by the first feedback

    def _implicit_noise(self, variance: float | None, scale) -> np.ndarray:
        """z-scale noise variance an implicit outcome adds, per action, on rating ``scale``."""
        if variance is None:
            if scale is None:
                return np.ones(len(self.actions))
            variance = (float(scale[1]) - float(scale[0])) ** 2 / 4.0
        if not variance > 0:
            raise ValueError(f'implicit_variance must be positive, got {variance}')
        return variance / np.asarray(self.inference.target_std, dtype=np.float64) ** 2

    def rating_noise(self, ratings: Sequence[Rating]) -> np.ndarray:
        """z-scale noise variance of each rating (``noise_of``)."""
        return self.noise_of(self.action_index([r.action for r in ratings]), [r.implicit for r in ratings])

    def noise_of(self, actions: np.ndarray, implicit) -> np.ndarray:
        """z-scale noise variance of observations of ``actions`` (indices): the action's, plus
        ``implicit_noise`` where ``implicit`` (bools) marks an implicit outcome."""
        return self.noise[actions] + np.where(np.asarray(implicit, dtype=bool), self.implicit_noise[actions], 0.0)

    @property
    def cached(self) -> tuple[int, int]:
        """(scenes whose h_i is kept, ratings whose regression row is kept): both bounded by
        ``cache_scenes``, least recently used dropped first."""
        with self._lock:
            return len(self._cache), len(self._rows)

    def forget_rows(self, ratings: Sequence[Rating]) -> int:
        """Let go of the regression rows of ``ratings`` (each row keeps its rating, and a
        rating of signed or implicit feedback its message); how many were kept."""
        with self._lock:
            gone = [key for key in {id(rating) for rating in ratings} if key in self._rows]
            for key in gone:
                del self._rows[key]
        return len(gone)

    def _user_row(self, row) -> np.ndarray:
        """θ = (p_u, b_u) (float64) of trained row(s) ``row``."""
        inference = self.inference
        return np.concatenate([inference.user_rows[row], inference.user_offsets[row, None]], axis=-1).astype(np.float64)

    # -- pieces ------------------------------------------------------------------------
    def prior(self, user_id=None) -> np.ndarray:
        """θ₀ = (p, b_u): the user's trained row if the checkpoint knows them, else the
        population mean."""
        return self.prior_distribution(user_id)[0]

    def prior_distribution(self, user_id=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(mean, covariance, precision) of θ before any feedback: the trained row with the
        covariance of their training ratings for a person the checkpoint knows, else the
        population prior."""
        row = self.predictor.trained_row(user_id)
        prior = self.user_prior
        if row == UNKNOWN:
            return self.population.copy(), prior.covariance, self._population_precision
        if prior.user_covariance is None or row >= len(prior.user_covariance):  # e.g. a refit's new rows
            return self._user_row(row), prior.covariance, self._population_precision
        with self._lock:
            precision = self._precisions.get(row)
        if precision is None:
            precision = np.linalg.inv(prior.user_covariance[row])
            with self._lock:
                self._precisions[row] = precision
                while len(self._precisions) > self._cache_scenes:
                    self._precisions.popitem(last=False)
        return self._user_row(row), prior.user_covariance[row], precision

    def posterior(self, x: np.ndarray, y: np.ndarray, actions: np.ndarray, user_id=None, implicit=None,
                  with_covariance: bool = True) -> tuple:
        """(mean, covariance) of θ of ``user_id`` after ratings with rows x [n, dim+1], targets
        y = z − c [n] and action columns ``actions`` [n], the one way every caller folds a
        person in: from the population prior, the scale mixture of the module docstring;
        from a known person's own trained row and covariance, the Gaussian posterior (their
        departure from the population is already measured). ``implicit`` (bools [n]) marks
        implicit outcomes, which take ``noise_of``'s larger noise. ``with_covariance`` False:
        the covariance of a new person's posterior is not computed (None), only its mean."""
        noise = self.noise_of(actions, np.zeros(len(actions), dtype=bool) if implicit is None else implicit)
        mean, covariance, precision = self.prior_distribution(user_id)
        if precision is self._population_precision:
            return scale_mixture_posterior(x, y, noise, mean, precision, self._population_logdet,
                                           with_covariance=with_covariance)[:2]
        if not len(x):
            return mean, covariance
        return gaussian_posterior(x, y, noise, mean, precision)

    def covariance(self, user_id=None) -> np.ndarray:
        """Cov θ of ``user_id`` before any feedback, as ``fit`` gives it with no ratings: a
        known person's own, else the population's scale mixture's (Σ₀ times the mean scale)."""
        _, covariance, precision = self.prior_distribution(user_id)
        return self._stranger_covariance if precision is self._population_precision else covariance

    def action_index(self, actions: Sequence[str]) -> np.ndarray:
        unknown = sorted({a for a in actions if a not in self._action_index})
        if unknown:
            raise UnknownActionError(f'unknown actions {unknown}; this model knows {list(self.actions)}')
        return np.array([self._action_index[a] for a in actions], dtype=np.int64)

    def to_z(self, scores, actions: np.ndarray) -> np.ndarray:
        return self.inference.to_z(scores, actions)

    def to_rating_scale(self, z, actions: np.ndarray) -> np.ndarray:
        """Scores of normalised predictions, clipped to the checkpoint's rating scale."""
        return self.predictor.clip(self.inference.to_rating_scale(z, actions))

    def design_from_h(self, h, scene_keys: Sequence, actions: np.ndarray) -> tuple:
        """(x [n, dim+1], c [n]) (float64) for ratings whose scenes are encoded as ``h``
        [n, dim]: ``InferenceModel.linear_form``, the model's z = xᵀθ + c."""
        rows = self.predictor.scene_rows(list(scene_keys))
        return self.inference.linear_form(np.asarray(h, dtype=np.float64), rows, actions)

    def remember(self, scenes: Sequence, rows: np.ndarray, fresh: bool = True,
                 plain: np.ndarray | None = None) -> None:
        """Cache h [len(scenes), dim] of ``scenes``, encoded by this FoldIn's predictor (the
        node passes what ranking them computed), and ``plain``, its plain encoder's unclipped
        scores [len(scenes), n_actions] where that ranking computed them (``Scored.plain``);
        ``fresh``: not read from a store, so ``take_encodings`` hands it over. The key is the
        scene object, which the entry keeps alive so its id cannot be reused."""
        rows = np.asarray(rows, dtype=np.float64)
        plain = [None] * len(rows) if plain is None else np.asarray(plain, dtype=np.float64)
        with self._lock:
            for scene, row, scores in zip(scenes, rows, plain):
                self._cache[id(scene)] = _Encoded(scene, row, fresh, scores)
                self._cache.move_to_end(id(scene))
            while len(self._cache) > self._cache_scenes:
                self._cache.popitem(last=False)

    def take_encodings(self, scenes: Sequence) -> dict:
        """id(scene) -> h of those of ``scenes`` encoded here and not handed over before: what
        a store may keep (``PersonUpdate.encoded``)."""
        taken = {}
        with self._lock:
            for scene in scenes:
                entry = self._cache.get(id(scene))
                if entry is not None and entry.fresh:
                    taken[id(scene)] = entry.h
                    self._cache[id(scene)] = entry._replace(fresh=False)
        return taken

    def _read_stored(self, scenes: Sequence) -> None:
        """Cache the h that ``stored`` keeps of those of ``scenes`` not cached: no encoding."""
        if self.stored is None:
            return
        with self._lock:
            missing = list({id(s): s for s in scenes if id(s) not in self._cache}.values())
        if missing:
            found = self.stored(missing)
            kept = [s for s in missing if id(s) in found]
            if kept:
                self.remember(kept, np.stack([found[id(s)] for s in kept]), fresh=False)

    def encode(self, scenes: Sequence) -> np.ndarray:
        """h_i [len(scenes), dim] (float64): cached rows, then those a store keeps, the other
        scenes encoded now."""
        self._read_stored(scenes)
        with self._lock:
            found = {id(s): self._cache[id(s)].h for s in scenes if id(s) in self._cache}
        missing = list({id(s): s for s in scenes if id(s) not in found}.values())
        if missing:
            h = (np.concatenate([self.predictor.encode([scene]) for scene in missing]) if self.scene_by_scene
                 else self.predictor.encode(missing)).astype(np.float64)
            self.remember(missing, h)
            found.update((id(s), row) for s, row in zip(missing, h))
        return np.stack([found[id(s)] for s in scenes])

    def design(self, ratings: Sequence[Rating]) -> tuple:
        """(x, c, z) for ``ratings``: the regression's inputs, offsets and z-scored targets."""
        actions = self.action_index([r.action for r in ratings])
        x, c = self.design_from_h(self.encode([r.scene for r in ratings]), [r.scene_id for r in ratings], actions)
        return x, c, self.to_z([r.score for r in ratings], actions)

    def hand_over_shift(self, ratings: Sequence[Rating], x: np.ndarray, c: np.ndarray) -> np.ndarray:
        """Per rating with rows ``x`` and offsets ``c``, what a person the predictor
        ``hands_over`` has in place of c beyond it: the plain encoder's z minus the model's at
        the prior's mean, z_plain − (xᵀθ₀ + c) (zeros for a checkpoint without a plain encoder).
        Their regression targets are z − c − shift, so θ₀ reproduces the plain encoder. The
        plain encoder's scores are those ``remember`` kept of a scene, else one scene per pass,
        row by row: a rating's shift does not depend on the ratings built with it (the node
        builds each as it comes, the front door all of a person's at once)."""
        predictor = self.predictor
        if predictor.stranger_inference is None:
            return np.zeros(len(ratings))
        with self._lock:
            kept = [entry.plain if (entry := self._cache.get(id(r.scene))) is not None else None for r in ratings]
        plain = np.stack([predictor.stranger_scores(predictor.encoder_input([r.scene], validate=False), 1)[0]
                          if scores is None else scores for r, scores in zip(ratings, kept)])
        actions = self.action_index([r.action for r in ratings])
        return self.shift(self.to_z(plain[np.arange(len(ratings)), actions], actions), x, c)

    def shift(self, plain_z: np.ndarray, x: np.ndarray, c: np.ndarray) -> np.ndarray:
        """z_plain − (xᵀθ₀ + c): how far the model at the prior's mean θ₀ is from the plain
        encoder's normalised predictions ``plain_z`` of rows ``x`` with offsets ``c``."""
        return np.asarray(plain_z, dtype=np.float64) - (np.einsum('rd,d->r', np.asarray(x, dtype=np.float64),
                                                                  self.population) + c)

    def prepare(self, ratings: Sequence[Rating], limit: int) -> bool:
        """Build the regression rows of ``ratings`` not built yet whose scenes' h is cached
        or stored, and of at most ``limit`` others (encoding their scenes); True once every
        one is built, unless this call built more than ``limit`` rows (then the next call
        says so). A caller that must stay responsive (the node's executor, solving a person
        restored with hundreds of ratings) spreads that person's first solve over several
        calls this way: the rows in one, the solve in the next. With a plain encoder for
        strangers a row whose plain scores are not kept takes a pass of it (``hand_over_shift``),
        so only a row with both kept counts as free."""
        with self._lock:
            missing = [rating for rating in ratings if id(rating) not in self._rows]
        if not missing:
            return True
        self._read_stored([rating.scene for rating in missing])
        with self._lock:
            needs_plain = self.predictor.stranger_inference is not None
            free = [(entry := self._cache.get(id(rating.scene))) is not None
                    and not (needs_plain and entry.plain is None) for rating in missing]
        encoded = [rating for rating, cached in zip(missing, free) if cached]
        to_encode = [rating for rating, cached in zip(missing, free) if not cached]
        built = encoded + to_encode[:limit]
        self.regression(built)
        return len(to_encode) <= limit and len(built) <= limit

    # -- the solve ---------------------------------------------------------------------
    def fit(self, ratings: Sequence[Rating], user_id=None, regularisation: float | None = None,
            hand_over: bool | None = None) -> UserModel:
        """The user's posterior θ = (p_u, b_u) from ``ratings`` (see the module docstring);
        a positive ``regularisation`` λ: the ridge solve towards the prior mean instead.
        ``hand_over`` (default: whether the predictor ``hands_over`` ``user_id``): solve θ
        as the departure from the plain encoder (``hand_over_shift``); False solves it as a
        trained row is scored (the refit, which makes the person a trained one)."""
        lam = float(regularisation or 0.0)
        if not ratings:
            theta, covariance = self.posterior(np.zeros((0, self.dim + 1)), np.zeros(0), np.zeros(0, dtype=np.int64),
                                               user_id)
            return UserModel(theta[:-1], float(theta[-1]), 0, lam, covariance)
        if hand_over is None:
            hand_over = self.predictor.hands_over(user_id)
        x, y = self.regression(ratings, hand_over)
        actions = self.action_index([r.action for r in ratings])
        if lam > 0:  # implicit outcomes weigh less here too: rows scaled by their noise ratio
            weight = np.sqrt(self.noise[actions] / self.rating_noise(ratings))[:, None]
            theta = solve_ridge(x * weight, y * weight[:, 0], self.prior(user_id), lam)
            weighted = x * weight
            covariance = float(self.noise.mean()) * np.linalg.inv(weighted.T @ weighted + lam * np.eye(len(theta)))
        else:
            theta, covariance = self.posterior(x, y, actions, user_id, [r.implicit for r in ratings])
        return UserModel(theta[:-1], float(theta[-1]), len(ratings), lam, covariance)

    def regression(self, ratings: Sequence[Rating], hand_over: bool = False) -> tuple:
        """(x [n, dim+1], y = z − c [n]) of ``ratings``, the rows ``design`` gives (``hand_over``:
        y = z − c − ``hand_over_shift``), each computed once per rating and then kept (the
        entry keeps the rating alive, so its id cannot be reused)."""
        keys = [id(rating) for rating in ratings]
        with self._lock:
            rows = [self._rows.get(key) for key in keys]
            for key, entry in zip(keys, rows):
                if entry is not None:
                    self._rows.move_to_end(key)
        missing = list({key: r for key, r, entry in zip(keys, ratings, rows) if entry is None}.values())
        if missing:
            x, c, z = self.design(missing)
            shift = self.hand_over_shift(missing, x, c)
            new = {id(rating): (rating, row, target, moved)
                   for rating, row, target, moved in zip(missing, x, z - c, shift)}
            with self._lock:
                self._rows.update(new)
                while len(self._rows) > self._cache_scenes:
                    self._rows.popitem(last=False)
            rows = [new[key] if entry is None else entry for key, entry in zip(keys, rows)]
        y = np.array([target - moved if hand_over else target for _, _, target, moved in rows])
        return np.array([row for _, row, _, _ in rows]), y

    def predict(self, user: UserModel, ratings: Sequence[Rating], user_id=None) -> np.ndarray:
        """Rating-scale predictions of ``user`` (``user_id``'s model) for the (scene, action)
        of ``ratings``, as the predictor serves them."""
        actions = self.action_index([r.action for r in ratings])
        x, c = self.design_from_h(self.encode([r.scene for r in ratings]), [r.scene_id for r in ratings], actions)
        if self.predictor.hands_over(user_id):
            c = c + self.hand_over_shift(ratings, x, c)
        return self.to_rating_scale(x @ np.append(user.p, user.b) + c, actions)
