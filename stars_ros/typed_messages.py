"""The typed interface (``stars_ros_msgs``) as twins of the JSON payloads (``messages``).

A typed request becomes the JSON text its twin on stars/scene, stars/feedback or
stars/question_request would carry, and the ranker handles that text as it handles the
JSON path's (same schema checks, same core, same error kinds); a scene request becomes a
``messages.Twin``, its payload and a bound of its text's size, so it is neither written
nor decoded before it is ranked. A ranking or question payload becomes its typed
message. Geometry goes through ``data.frames``, the one conversion between SocNav1 and REP 103.

ROS-free: messages are read by their fields, and built from the message classes the caller
passes (``msgs``: a module or namespace holding ``stars_ros_msgs.msg``'s classes; ``geometry``:
``geometry_msgs.msg``'s), so this module imports no ROS package and its tests can use plain objects.
"""
from __future__ import annotations

import math
import re

from stars_ros import messages
from stars_ros.data import frames
from stars_ros.rotations import quaternion_of_yaw, yaw_of_quaternion

FRAME = 'frame'  # error kind: a typed scene in a frame the ranker does not take


def _check_frame(scene, robot_frame: str, scene_id: str | None):
    frame = scene.header.frame_id
    if frame != robot_frame:
        need = ('header.frame_id is empty' if not frame else
                f"it is in '{frame}': transform it first (TF {robot_frame} <- {frame}, e.g. tf2_ros "
                f"Buffer.lookup_transform('{robot_frame}', '{frame}', stamp))")
        raise messages.BadMessage(FRAME, f"the ranker takes scenes in its frame_id '{robot_frame}' (the robot's); "
                                  f'{need}, or set the ranker parameter frame_id', scene_id)


def _check_finite(values: dict, where: str, scene_id) -> None:
    """BadMessage ``non_finite`` naming the first of ``values`` ({field: number}, fields under
    ``where``) that is NaN or infinite, by its typed field path."""
    for name, value in values.items():
        if not math.isfinite(value):
            raise messages.BadMessage('non_finite', f'{where}.{name} is {value}: not a finite number', scene_id)


def _entity(item, where: str, scene_id) -> frames.Entity:
    p, q = item.pose.position, item.pose.orientation
    _check_finite({'pose.position.x': p.x, 'pose.position.y': p.y, 'pose.orientation.x': q.x,
                   'pose.orientation.y': q.y, 'pose.orientation.z': q.z, 'pose.orientation.w': q.w}, where, scene_id)
    return frames.Entity(int(item.id), float(p.x), float(p.y), yaw_of_quaternion(q.x, q.y, q.z, q.w))


def scene_graph(scene, robot_frame: str, scene_id: str | None = None, where: str = 'scene') -> dict:
    """The SocNav1 scene dict (``msg_schemas/scene_graph.schema.json``) of a typed
    ``SceneGraph`` (the field ``where`` of its message), which must be in ``robot_frame``;
    BadMessage (``frame``, ``non_finite``, naming the typed field) otherwise. The schema checks
    the rest, as for a JSON scene: an empty scene is its to refuse (``schema``), whatever its frame."""
    if scene.humans or scene.objects or scene.room or scene.interactions:
        _check_frame(scene, robot_frame, scene_id)
    for k, point in enumerate(scene.room):
        _check_finite({'x': point.x, 'y': point.y}, f'{where}.room[{k}]', scene_id)
    rep103 = frames.Rep103Scene(humans=tuple(_entity(h, f'{where}.humans[{k}]', scene_id)
                                             for k, h in enumerate(scene.humans)),
                                objects=tuple(_entity(o, f'{where}.objects[{k}]', scene_id)
                                              for k, o in enumerate(scene.objects)),
                                room=tuple((float(p.x), float(p.y)) for p in scene.room),
                                interactions=tuple((int(i.a), int(i.b)) for i in scene.interactions))
    return frames.to_socnav(rep103)


# Bytes a scene request twin's parts can take as JSON text (``messages.dumps``): ids are
# int64 (at most 20 characters), coordinates and headings floats (a float's repr is at most
# 24), and a string's character escapes to at most 12 bytes (a surrogate pair, \uXXXX\uXXXX)
_INT, _FLOAT = 20, 24
_ENTITY = len('{"id":,"xPos":,"yPos":,"orientation":},') + _INT + 3 * _FLOAT
_POINT = len('[,],') + 2 * _FLOAT
_LINK = len('[,,"interact"],') + 2 * _INT
_GRAPH = len(messages.dumps(frames.to_socnav(frames.Rep103Scene())))
_REQUEST = len(messages.dumps({'scene_id': '', 'graph': None, 'candidates': [], 'action': '', 'user_id': '',
                               'explain': True}))
_CANDIDATE = len('{"candidate":"","graph":},')


def _text_bound(text: str) -> int:
    return 12 * len(text) + 3  # quoted, and a comma


def _graph_bound(scene) -> int:
    """Bytes the twin of typed ``SceneGraph`` ``scene`` cannot exceed."""
    return (_GRAPH + _ENTITY * (len(scene.humans) + len(scene.objects)) + _POINT * len(scene.room)
            + _LINK * len(scene.interactions))


# A scene's fields in its JSON twin -> in the typed message (a schema error names the typed field)
_SCENE_FIELDS = ((re.compile(r'\.links\b'), '.interactions'),
                 (re.compile(r'\.(humans|objects)\[(\d+)\]\.(xPos|yPos|orientation)$'), r'.\1[\2].pose'),
                 (re.compile(r'\.room\[(\d+)\]\[\d+\]$'), r'.room[\1]'))


def _typed_field(path: str, request: str) -> str:
    """The field of a typed ``request`` ('rank_actions' or 'rank_candidates') that the
    twin's field ``path`` (``graph.humans[0].xPos``) comes from (``scene.humans[0].pose``)."""
    if request == 'rank_actions':
        path = re.sub(r'^graph\b', 'scene', re.sub(r'^candidates\b', 'actions', path))
    else:
        path = re.sub(r'^candidates\[(\d+)\]\.candidate$', r'candidates[\1].label',
                      re.sub(r'^candidates\[(\d+)\]\.graph\b', r'candidates[\1].scene', path))
    for pattern, typed_name in _SCENE_FIELDS:
        path = pattern.sub(typed_name, path)
    return path


def _scene_request(payload: dict, user_id: str, explain: bool, size_bound: int, request: str) -> messages.Twin:
    """``payload`` with the optional fields a typed request leaves empty when unset, as the
    twin of a ``request`` whose other parts take at most ``size_bound`` bytes."""
    if user_id:
        payload['user_id'] = user_id
    if explain:
        payload['explain'] = True
    return messages.Twin(payload, _REQUEST + _text_bound(payload['scene_id']) + _text_bound(user_id) + size_bound,
                         lambda path: _typed_field(path, request))


def rank_actions_twin(request, robot_frame: str) -> messages.Twin:
    """The stars/scene JSON twin of a ``RankActions`` request."""
    payload = {'scene_id': request.scene_id,
               'graph': scene_graph(request.scene, robot_frame, request.scene_id or None)}
    if request.actions:
        payload['candidates'] = list(request.actions)
    return _scene_request(payload, request.user_id, request.explain,
                          _graph_bound(request.scene) + sum(_text_bound(a) for a in request.actions), 'rank_actions')


def rank_candidates_twin(request, robot_frame: str) -> messages.Twin:
    """The stars/scene JSON twin of a ``RankCandidates`` request. Without candidates it
    carries ``candidates: []``, which the schema refuses, as it would the JSON request."""
    payload = {'scene_id': request.scene_id,
               'candidates': [{'candidate': c.label, 'graph': scene_graph(c.scene, robot_frame,
                                                                          request.scene_id or None,
                                                                          f'candidates[{k}].scene')}
                              for k, c in enumerate(request.candidates)]}
    if request.action:
        payload['action'] = request.action
    return _scene_request(payload, request.user_id, request.explain,
                          _text_bound(request.action) + sum(_CANDIDATE + _text_bound(c.label) + _graph_bound(c.scene)
                                                            for c in request.candidates), 'rank_candidates')


def feedback_fields(feedback) -> dict:
    """The fields of a typed ``Feedback``'s JSON twin, ``auth`` aside: what a signer signs
    (``feedback_auth.mac(secret, feedback_fields(msg), stamp)`` is its ``auth_mac``)."""
    fields = {'user_id': feedback.user_id, 'scene_id': feedback.scene_id, 'score': float(feedback.score)}
    fields.update({key: value for key in ('action', 'candidate') if (value := getattr(feedback, key))})
    return fields


_FEEDBACK = len(messages.dumps({'user_id': '', 'scene_id': '', 'score': 0, 'action': '', 'candidate': '',
                                 'auth': {'key_id': '', 'stamp': 0, 'mac': ''}})) + _FLOAT + _INT


def feedback_twin(feedback) -> messages.Twin:
    """The stars/feedback JSON twin of a typed ``Feedback`` (with ``auth`` when signed),
    checked as its text would be (``messages.parse_feedback``) without being written."""
    if not math.isfinite(feedback.score):
        raise messages.BadMessage('non_finite', f'feedback score {feedback.score} is not a finite number',
                                  feedback.scene_id or None)
    payload = feedback_fields(feedback)
    if feedback.auth_key_id:
        payload['auth'] = {'key_id': feedback.auth_key_id, 'stamp': int(feedback.auth_stamp),
                           'mac': feedback.auth_mac}
    texts = (feedback.user_id, feedback.scene_id, feedback.action, feedback.candidate, feedback.auth_key_id,
             feedback.auth_mac)
    return messages.Twin(payload, _FEEDBACK + sum(_text_bound(text) for text in texts))


def question_request_text(request, robot_frame: str) -> str:
    """The stars/question_request JSON twin of a ``ChooseQuestion`` request."""
    if len(request.scene_ids) != len(request.scenes):
        raise messages.BadMessage('schema', f'question request invalid: {len(request.scenes)} scenes but '
                                  f'{len(request.scene_ids)} scene_ids (one each)')
    payload = {'user_id': request.user_id}
    if request.scenes:
        payload['candidates'] = [
            {'scene_id': scene_id, 'graph': scene_graph(scene, robot_frame, scene_id or None, f'scenes[{k}]'),
             **({'candidates': list(request.candidate_actions)} if request.candidate_actions else {})}
            for k, (scene, scene_id) in enumerate(zip(request.scenes, request.scene_ids))]
    return messages.dumps(payload)


def _nan_if_none(value) -> float:
    return math.nan if value is None else float(value)


def ranking_message(payload: dict, msgs):
    """The typed ``Ranking`` of a stars/ranking payload (header left for the caller)."""
    entries = []
    for entry in payload['ranking']:
        why = entry.get('why')
        typed = msgs.RankedEntry(name=entry.get('action', entry.get('candidate', '')), score=float(entry['score']),
                                 score_sd=_nan_if_none(entry.get('score_sd')), rank=int(entry['rank']),
                                 has_why=why is not None)
        if why is not None:
            typed.why = msgs.Why(content=float(why['content']), personal=float(why['personal']),
                                 scene=float(why['scene']),
                                 entities=[msgs.EntityEffect(kind=e['kind'], id=str(e['id']), effect=float(e['effect']))
                                           for e in why['entities']])
        entries.append(typed)
    return msgs.Ranking(scene_id=payload['scene_id'], user_id=payload['user_id'] or '',
                        known_user=bool(payload['known_user']),
                        personalised_from=int(payload.get('personalised_from', 0)),
                        action=payload.get('action', ''), entries=entries,
                        p_first_is_best=_nan_if_none(payload.get('p_first_is_best')),
                        fingerprint=payload['fingerprint'], processing_time=payload['processing_ms'] / 1e3)


def question_message(payload: dict, msgs):
    """The typed ``Question`` of a stars/question payload."""
    return msgs.Question(user_id=payload['user_id'], scene_id=payload['scene_id'], action=payload['action'],
                         candidate=payload.get('candidate', ''),
                         expected_variance_reduction=float(payload['expected_variance_reduction']),
                         score=float(payload['score']), score_sd=float(payload['score_sd']),
                         candidates=int(payload['candidates']), targets=int(payload['targets']),
                         fingerprint=payload['fingerprint'])


def _pose(entity: frames.Entity, geometry):
    x, y, z, w = quaternion_of_yaw(entity.yaw)
    return geometry.Pose(position=geometry.Point(x=entity.x, y=entity.y, z=0.0),
                         orientation=geometry.Quaternion(x=x, y=y, z=z, w=w))


def scene_message(scene: dict, frame_id: str, msgs, geometry):
    """The typed ``SceneGraph`` (in ``frame_id``, the robot's) of a SocNav1 scene dict: what
    a client that holds SocNav1 scenes sends (the inverse of ``scene_graph``)."""
    rep103 = frames.from_socnav(scene)
    typed = msgs.SceneGraph(
        humans=[msgs.Human(id=h.id, pose=_pose(h, geometry)) for h in rep103.humans],
        objects=[msgs.SceneObject(id=o.id, pose=_pose(o, geometry)) for o in rep103.objects],
        room=[geometry.Point(x=x, y=y, z=0.0) for x, y in rep103.room],
        interactions=[msgs.Interaction(a=a, b=b) for a, b in rep103.interactions])
    typed.header.frame_id = frame_id
    return typed
