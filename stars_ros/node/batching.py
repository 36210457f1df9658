"""Rank a batch of queued scene requests with one model snapshot; ``stars_ros.node.core`` uses it.

ROS-free. When scenes arrive faster than they are scored, the node scores everything
queued (up to ``max_batch``) in one call, and the requests of one user (and one mode) are
ranked by ``Predictor.rank_many``, their scenes encoded in one forward pass, which is what
lets a single core keep up. Results are those of ``Predictor.rank`` and
``Predictor.rank_scenes`` on the same input (same scores, ties kept in input order). A bad
request only fails itself: a group that raises is ranked again one request at a time.
"""
from __future__ import annotations

from dataclasses import dataclass

from stars_ros.errors import StarsError
from stars_ros.messages import SceneRequest, Twin


@dataclass(frozen=True)
class Pending:
    """A validated request waiting to be scored.

    ``user_id`` is the one it is served for (the message's own, else the latest on
    /stars/user_id at arrival); ``received`` is when the middleware received it (system
    clock, ns, as ``time.time_ns()``), so a ranking's processing time includes any wait
    behind other callbacks; ``message`` (its text, or a typed request's ``Twin``) and
    ``log_time`` (ROS time, ns) are the message as received, which the node records once the
    ranking is out.
    """

    request: SceneRequest
    user_id: str | None
    received: int
    message: str | Twin = ''
    log_time: int = 0


def rank_batch(predictor, batch, top_k: int = 0, uncertainty=None, explanations=None) -> list:
    """One ``predictor.Scored`` or one exception per ``Pending`` of ``batch``, in order (with
    ``uncertainty``: with each entry's score_sd and the ranking's p_first_is_best; with
    ``explanations`` = (explain every request?, entities per why): each entry's why where
    that or its request's ``explain`` asks)."""
    results = [None] * len(batch)
    groups = {}
    for k, item in enumerate(batch):
        try:
            predictor.query_action(item.request)
        except StarsError as error:
            results[k] = error
            continue
        groups.setdefault((item.user_id, item.request.ranks_scenes), []).append((k, item.request))
    explain_all, entities = explanations or (False, 0)
    options = {'top_k': top_k, 'uncertainty': uncertainty, 'explain_all': explain_all, 'explain_entities': entities,
               'validate': False}  # parse_scene_request validated the scenes
    for (user_id, _), members in groups.items():
        try:
            scored = predictor.rank_many(user_id, [request for _, request in members], **options)
        except StarsError:
            scored = []
            for _, request in members:  # find which request spoils the group
                try:
                    scored.append(predictor.rank_many(user_id, [request], **options)[0])
                except StarsError as error:
                    scored.append(error)
        for (k, _), result in zip(members, scored):
            results[k] = result
    return results
