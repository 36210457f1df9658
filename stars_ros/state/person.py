"""What a person's state holds: their ratings (``Rating``), their folded-in model
(``UserModel``), and the one check of a rating's score against the checkpoint's rating
scale, made where a rating enters (a client's feedback, a peer's model, a bag given to
refit, the signer), so that nothing off the scale is stored, folded in or passed on.
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from typing import Callable, NamedTuple, Sequence

import numpy as np

from stars_ros.errors import OutOfScaleError


@dataclass(frozen=True)
class Rating:
    """One rating to fold in: ``scene`` is a scene-graph dict (or a tabular feature row),
    ``score`` is on the model's rating scale, ``scene_id`` names a training scene whose q_i
    applies (None for scenes the model never saw, e.g. candidate placements).

    A ranker names each rating it accepts (``rating_id``, unique; ``stamp``, ROS time ns;
    ``origin``, the node that accepted it), so that robots sharing ratings (``fleet``) count
    each once and order them alike. With signed feedback (``feedback_auth``), ``feedback``
    is the signed message it came from and ``rating_id`` its MAC, so peers can check it. An
    implicit outcome (docs/hri.md) keeps its message in ``feedback`` too, which says
    ``"implicit": true``, so the store, peers and the offline refit all see it as such."""

    scene: object
    action: str
    score: float
    scene_id: str | None = None
    rating_id: str = ''
    stamp: int = 0
    origin: str = ''
    feedback: dict | None = None

    @property
    def implicit(self) -> bool:
        """An implicit outcome the robot observed, not a rating the person gave."""
        return self.feedback is not None and self.feedback.get('implicit') is True

    def to_json(self) -> dict:
        """The rating as stars/user_model's ``ratings`` hold it."""
        scene = self.scene if isinstance(self.scene, dict) else [float(v) for v in self.scene]
        values = {'id': self.rating_id, 'stamp': int(self.stamp), 'origin': self.origin, 'scene': scene,
                  'action': self.action, 'score': float(self.score)}
        if self.feedback is not None:
            values['feedback'] = self.feedback
        return values if self.scene_id is None else {**values, 'scene_id': self.scene_id}

    @classmethod
    def from_json(cls, values: dict, fallback_id: str = '') -> 'Rating':
        """The rating of ``to_json``'s form; ``fallback_id`` names one written before ratings
        had ids."""
        return cls(values['scene'], values['action'], float(values['score']), values.get('scene_id'),
                   values.get('id') or fallback_id, int(values.get('stamp', 0)), values.get('origin', ''),
                   values.get('feedback'))


@dataclass(frozen=True)
class UserModel:
    """A folded-in user: embedding ``p`` [dim] and offset ``b`` (float64), solved from
    ``n_ratings`` ratings, by the Gaussian posterior (``regularisation`` 0) or the ridge
    override λ; ``covariance`` [dim+1, dim+1] of θ = (p, b) (None: not known, e.g. restored
    from an earlier version's state file until it is solved again; ``Deferred``: restored
    from the store, read when first used, ``loaded``)."""

    p: np.ndarray
    b: float
    n_ratings: int
    regularisation: float
    covariance: np.ndarray | None = None

    def to_json(self) -> dict:
        return {'p_u': [float(v) for v in self.p], 'b_u': float(self.b), 'n_ratings': int(self.n_ratings),
                'regularisation': float(self.regularisation)}

    @classmethod
    def from_json(cls, values: dict) -> 'UserModel':
        return cls(np.asarray(values['p_u'], dtype=np.float64), float(values['b_u']), int(values['n_ratings']),
                   float(values['regularisation']))



def scene_digest(scene) -> str:
    """Cache key of a scene's content (the same graph under two scene ids is encoded once)."""
    if isinstance(scene, dict):
        text = json.dumps(scene, sort_keys=True, separators=(',', ':'))
    else:
        text = json.dumps(np.asarray(scene, dtype=np.float64).tolist())
    return hashlib.blake2b(text.encode(), digest_size=16).hexdigest()


class Deferred(NamedTuple):
    """Part of a person not read from the store yet: ``load()`` gives it (their ratings,
    [Rating] oldest first, or their model's covariance)."""

    load: Callable[[], object]


def loaded(value):
    """``value``, read now if it is ``Deferred``."""
    return value.load() if isinstance(value, Deferred) else value


def scale_text(scale: Sequence[float]) -> str:
    return f'[{scale[0]:g}, {scale[1]:g}]'


def check_score(score: float, scale: Sequence[float] | None, what: str = 'score') -> None:
    """OutOfScaleError naming ``scale`` (low, high) when ``score`` lies outside it; a
    checkpoint written before it kept its scale (None) takes any finite score. The one check
    of a score: the node's feedback, peers' ratings and the front door's fold-in."""
    if not math.isfinite(score):
        raise OutOfScaleError(f'{what} {score:g} is not a finite number')
    if scale is None:
        return
    low, high = scale
    if not low <= score <= high:
        raise OutOfScaleError(f'{what} {score:g} is outside the rating scale {scale_text(scale)} of the checkpoint '
                              'served: give scores on that scale')


def check_ratings(ratings: Sequence[Rating], scale: Sequence[float] | None, owner: str) -> None:
    """OutOfScaleError naming the first rating of ``owner``'s off ``scale``."""
    for rating in ratings:
        check_score(rating.score, scale, f"rating '{rating.rating_id}' of '{owner}' has score")
