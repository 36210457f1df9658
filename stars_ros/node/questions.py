"""Which question the ranker asks a person: the (scene, action) whose rating the model is
least sure of for them (the largest predictive variance; for one Gaussian rating the same
choice as BALD, the expected information gain about θ_u of Houlsby et al. 2014), answered on
stars/question. ROS-free; ``RankerCore`` calls it. Chosen over the A-optimal and the
choice-aimed criteria (``uncertainty``) on held-out people: all three were never worse than
unpersonalised in any fold, and it alone was never behind random answers on both data sets
(docs/personalisation.md).

The candidates are the scene requests of a stars/question_request, or without them the
``recent_scenes`` latest scenes the node remembers (``SceneMemory``): each action of an
action-ranking request, each candidate scene of a candidate-scenes request under the action
that ranks them. The reply says how much the answer is expected to reduce the summed
predictive variance over a target set: the candidates together with those remembered scenes
whose encodings the node already holds. The candidates of a request are remembered as scenes
the node has seen, so that the person's answer, sent as ordinary feedback, is folded in.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stars_ros import messages
from stars_ros.errors import NoQuestion, StarsError
from stars_ros.model.vocabulary import UNKNOWN


@dataclass(frozen=True)
class Candidate:
    """One question: rate ``action`` in scene ``scene_id`` (its candidate ``candidate``,
    the scene ``graph``)."""

    scene_id: str
    action: str
    candidate: str | None
    x: np.ndarray  # [dim+1]: the row of the linear form this rating would add
    c: float
    column: int
    graph: object


def candidates_of(predictor, request: messages.SceneRequest, h: np.ndarray) -> list:
    """The questions one scene request offers, from its scenes' encodings ``h`` [len(graphs), dim]."""
    h = np.asarray(h, dtype=np.float64)
    if request.ranks_scenes:
        action = predictor.ranking_action(request.action)
        columns = np.full(len(request.labels), predictor.action_columns([action])[0])
        x, c = predictor.inference.linear_form(h, np.full(len(columns), UNKNOWN), columns)
        return [Candidate(request.scene_id, action, label, x[k], float(c[k]), int(columns[k]), request.graphs[k])
                for k, label in enumerate(request.labels)]
    names = list(request.actions or predictor.actions)
    columns = np.asarray(predictor.action_columns(names))
    rows = predictor.scene_rows([request.scene_id] * len(names))
    x, c = predictor.inference.linear_form(np.repeat(h[:1], len(names), axis=0), rows, columns)
    return [Candidate(request.scene_id, name, None, x[k], float(c[k]), int(columns[k]), request.graphs[0])
            for k, name in enumerate(names)]


def choose_question(personalisation, user_id: str, requests: list, recent_scenes: int) -> dict:
    """The stars/question reply for ``user_id`` over ``requests`` [(SceneRequest, text)]
    (empty: the remembered scenes); raises StarsError when there is nothing to ask about."""
    predictor, uncertainty = personalisation.serving.predictor, personalisation.serving.uncertainty
    if uncertainty is None:
        raise StarsError('this checkpoint has no fold-in (no users), so there is no question to choose')
    remembered = personalisation.recent_scenes(recent_scenes)
    offered, targets = [], []
    for request, text in requests:
        h = predictor.encode(request.graphs, validate=False)  # parse_scene_request validated them
        personalisation.scene_received(request.scene_id, text)
        personalisation.scene_ranked(request.scene_id, text, predictor, h)
        offered += candidates_of(predictor, request, h)
    for _, message, encoded in remembered:
        request = messages.parse_scene_request(message)
        mine = encoded is not None and encoded[0] is predictor
        if not requests or mine:
            try:
                found = candidates_of(predictor, request, encoded[1] if mine else
                                      predictor.encode(request.graphs, validate=False))
            except StarsError:  # e.g. candidate scenes that do not say which action ranks them
                continue
            targets += found
            if not requests:
                offered += found
    if not offered:
        raise NoQuestion('no scene to ask about: the request has no candidates and the node has seen no scene '
                         'it can ask about yet')
    targets = targets + offered if requests else targets
    covariance = uncertainty.covariance(user_id, predictor.user_model(user_id))
    target_rows = (np.stack([t.x for t in targets]), np.array([t.column for t in targets]))
    spread = uncertainty.rating_sd(np.stack([q.x for q in offered]), np.array([q.column for q in offered]), covariance)
    best = offered[int(np.argmax(spread))]
    gain = uncertainty.variance_reduction([(best.x[None], np.array([best.column]))], target_rows, covariance)[0]
    if predictor.hands_over(user_id):  # the score served around the plain encoder
        scene_ids = None if best.candidate is not None else [best.scene_id]
        score = float(predictor.score(user_id, [best.graph], scene_ids, validate=False)[0, best.column])
    else:
        z = float(best.x @ predictor.user_theta(user_id) + best.c)
        score = float(predictor.clip(predictor.inference.to_rating_scale(np.array([z]), np.array([best.column])))[0])
    reply = {'user_id': user_id, 'scene_id': best.scene_id, 'action': best.action,
             'expected_variance_reduction': float(gain), 'score': score, 'score_sd': float(spread.max()),
             'candidates': len(offered), 'targets': len(targets), 'fingerprint': predictor.fingerprint}
    if best.candidate is not None:
        reply['candidate'] = best.candidate
    return reply
