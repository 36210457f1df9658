"""The JSON payloads of the ranker's topics: parse, check against msg_schemas/, build replies.

ROS-free, so the checks are testable without DDS and the same rules hold for the node, the
companion nodes and offline tools. A bad message raises ``BadMessage`` whose ``kind`` names
the problem for diagnostics (``oversized``, ``malformed_json``, ``non_finite``, ``schema``).

Validation runs on every message on the node's hot path, so the schema files are compiled
once with fastjsonschema (about 40x faster than jsonschema here). fastjsonschema reads
draft-07, so ``draft07`` rewrites the 2020-12 keywords the files use; a test checks that
both validators accept and refuse the same messages.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Callable, Sequence
from urllib.parse import urljoin

from stars_ros.errors import BadMessage, OutOfScaleError, SceneGraphError, StarsError, UnknownActionError
from stars_ros.resources import share_path

SCHEMA_BASE = 'https://stars-ros.dev/msg_schemas/'
DEFAULT_MAX_BYTES = 262144
MAX_ID_CHARS = 256
_UNSUPPORTED = ('$dynamicRef', '$dynamicAnchor', '$anchor', 'unevaluatedItems', 'unevaluatedProperties',
                'dependentRequired', 'dependentSchemas', 'minContains', 'maxContains', 'contentSchema')


@dataclass(frozen=True)
class SceneRequest:
    """One validated /stars/scene message.

    ``graphs`` holds the scene to rank actions in (one graph) or the candidate scenes;
    ``labels`` is None for action ranking and names the candidate scenes otherwise;
    ``explain``: each entry is to carry its ``why``.
    """

    scene_id: str
    user_id: str | None
    graphs: tuple
    labels: tuple | None = None
    actions: tuple | None = None
    action: str | None = None
    explain: bool = False

    @property
    def ranks_scenes(self) -> bool:
        return self.labels is not None


@dataclass(frozen=True)
class Feedback:
    """One validated /stars/feedback message; exactly one of ``action`` and ``candidate``.
    ``signed``: the message as parsed when it carries ``auth``, what ``feedback_auth``
    checks and a folded-in rating keeps, so that peers can check it too. ``implicit``: an
    outcome the robot observed (e.g. the person stayed engaged), not a rating the person
    gave; its score is the rating scale's top or bottom (docs/hri.md)."""

    user_id: str
    scene_id: str
    score: float
    action: str | None = None
    candidate: str | None = None
    signed: dict | None = None
    implicit: bool = False

    def as_message(self) -> dict:
        """The message's fields (without ``auth``), as stars/feedback carries them."""
        key, value = ('action', self.action) if self.action is not None else ('candidate', self.candidate)
        out = {'user_id': self.user_id, 'scene_id': self.scene_id, key: value, 'score': self.score}
        return {**out, 'implicit': True} if self.implicit else out


def draft07(node):
    """The same schema in draft-07 terms: ``prefixItems``/``items`` become
    ``items``/``additionalItems`` and a ``$ref`` with siblings moves into ``allOf``."""
    if isinstance(node, list):
        return [draft07(item) for item in node]
    if not isinstance(node, dict):
        return node
    for keyword in _UNSUPPORTED:
        if keyword in node:
            raise ValueError(f'schema keyword {keyword} has no draft-07 equivalent for the fast validator')
    out = {key: draft07(value) for key, value in node.items() if key not in ('$schema', 'prefixItems')}
    if 'prefixItems' in node:
        out['items'] = draft07(node['prefixItems'])
        if 'items' in node:
            out['additionalItems'] = draft07(node['items'])
    if '$ref' in out and len(out) > 1:
        ref = out.pop('$ref')
        out = {'allOf': [{'$ref': ref}, out]}
    return out


def load_schema(name: str) -> dict:
    """The 2020-12 schema ``msg_schemas/<name>.schema.json`` as shipped."""
    return json.loads(share_path(f'msg_schemas/{name}.schema.json').read_text())


def _inline_refs(node, document: dict, uri: str, following: tuple = ()):
    """``node`` of the schema at ``uri`` with every ``$ref`` replaced by what it points to
    (another file of msg_schemas/ or a ``#/...`` path), so fastjsonschema compiles one
    function instead of a call per referenced item: 2.5x faster on a SocNav1 scene."""
    if isinstance(node, list):
        return [_inline_refs(item, document, uri, following) for item in node]
    if not isinstance(node, dict):
        return node
    out = {key: _inline_refs(value, document, uri, following) for key, value in node.items()
           if key not in ('$ref', '$defs', '$id')}
    if '$ref' not in node:
        return out
    target_uri, _, pointer = urljoin(uri, node['$ref']).partition('#')
    if (target_uri, pointer) in following:
        raise ValueError(f'schema reference {node["$ref"]} is recursive; the fast validator inlines references')
    if not target_uri.startswith(SCHEMA_BASE):
        raise ValueError(f'schema reference {target_uri} is outside {SCHEMA_BASE}')
    target_document = document if target_uri == uri else draft07(
        load_schema(target_uri[len(SCHEMA_BASE):].removesuffix('.schema.json')))
    target = target_document
    for part in filter(None, pointer.split('/')):
        target = target[part]
    resolved = _inline_refs(target, target_document, target_uri, following + ((target_uri, pointer),))
    return {'allOf': [resolved, out]} if out else resolved


@lru_cache(maxsize=None)
def validator(name: str):
    """A compiled validator for ``msg_schemas/<name>.schema.json`` (raises
    ``fastjsonschema.JsonSchemaValueException``)."""
    import fastjsonschema

    schema = draft07(load_schema(name))
    return fastjsonschema.compile(_inline_refs(schema, schema, schema['$id']), use_default=False)


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f'{text} is not a finite number')
    return value


def _refuse_constant(name: str):
    raise ValueError(f'{name} is not a number')


def check_size(text, max_bytes: int = DEFAULT_MAX_BYTES) -> None:
    """BadMessage ``oversized`` when ``text`` (str or bytes) is larger than ``max_bytes``."""
    size = len(text) if isinstance(text, (bytes, bytearray)) else len(text.encode('utf-8', 'surrogatepass'))
    if size > max_bytes:
        raise BadMessage('oversized', f'message of {size} bytes exceeds the limit of {max_bytes} bytes')


@dataclass(frozen=True)
class Twin:
    """A typed message's JSON twin: the ``payload`` its text would carry (finite by
    construction) and ``size_bound``, bytes that text cannot exceed. It is checked as its text
    would be (``check_size``, then the schema) without being written, which a request would
    wait for; ``text`` writes it for the bag and the logs."""

    payload: dict
    size_bound: int
    typed_field: Callable[[str], str] | None = None  # a twin's field -> the typed message's, which errors name

    @property
    def text(self) -> str:
        return dumps(self.payload)

    def check_size(self, max_bytes: int) -> None:
        """``check_size`` of ``text``, which is written only when ``size_bound`` exceeds ``max_bytes``."""
        if self.size_bound > max_bytes:
            check_size(self.text, max_bytes)


def text_of(message) -> str:
    """The text of a message: itself, or a ``Twin``'s."""
    return message.text if isinstance(message, Twin) else message


def load_json(text, max_bytes: int = DEFAULT_MAX_BYTES):
    """Parse ``text`` (str or bytes), refusing oversized input, NaN and infinities."""
    check_size(text, max_bytes)
    try:
        return json.loads(text, parse_constant=_refuse_constant, parse_float=_finite_float)
    except ValueError as error:
        kind = 'non_finite' if 'not a number' in str(error) or 'not a finite' in str(error) else 'malformed_json'
        raise BadMessage(kind, f'not valid JSON: {error}') from None
    except RecursionError:
        raise BadMessage('malformed_json', 'not valid JSON: nested too deeply') from None


def _scene_id(payload) -> str | None:
    """The scene id of a refused message, if it has one that follows the schema."""
    value = payload.get('scene_id') if isinstance(payload, dict) else None
    return value if isinstance(value, str) and 0 < len(value) <= MAX_ID_CHARS else None


def _explain(name: str, error, typed_field: Callable[[str], str] | None = None) -> str:
    """fastjsonschema's complaint in a user's words: the field by its place in the message
    (``graph.humans[0].xPos``, not ``data.graph.humans[0].xPos``; a typed request's own field,
    ``scene.humans[0].pose``, through ``typed_field``), missing and unknown fields by name, and
    the choices the schemas' ``oneOf``/``anyOf`` rules stand for."""
    where = error.name.removeprefix('data').lstrip('.')
    if where and typed_field is not None:
        where = typed_field(where)
    subject = f"'{where}'" if where else _SUBJECTS[name]
    if error.rule == 'oneOf' and name == 'feedback' and not where:
        return ("feedback needs either 'action' (the action rated) or 'candidate' (the candidate scene rated), "
                'exactly one of them')
    if error.rule == 'oneOf' and where == 'candidates':
        return _CANDIDATES_SHAPE
    if error.rule == 'anyOf' and name == 'scene_request' and not where:
        return _request_shape(error.value)
    if error.rule == 'required':
        missing = [key for key in error.rule_definition if key not in error.value]
        return f"{subject} needs {' and '.join(repr(key) for key in missing)}"
    if error.rule == 'additionalProperties':
        known = error.definition.get('properties', {})
        unknown = ', '.join(repr(key) for key in sorted(error.value) if key not in known)
        return f"{unknown}: not a field of {subject}" + (f" (its fields: {', '.join(known)})" if known else '')
    return subject + error.message[len(error.name):]


_CANDIDATES_SHAPE = ("'candidates' must be a list of action names or a list of candidate scenes "
                     "({'candidate': label, 'graph': scene})")


def _request_shape(request: dict) -> str:
    """Why a scene request is neither actions ranked in a 'graph' nor candidate scenes (the
    schema's ``anyOf``, which fastjsonschema checks before the fields themselves)."""
    candidates = request.get('candidates')
    kinds = {type(c) for c in candidates} if isinstance(candidates, list) else set()
    if len(kinds) > 1 or kinds - {str, dict}:
        return _CANDIDATES_SHAPE
    if 'graph' not in request and kinds != {dict}:
        return "a scene request needs 'graph' (the scene to rank actions in) or 'candidates' that are scenes"
    return "'graph' goes with action candidates, 'action' with candidate scenes, not the other way round"


_SUBJECTS = {'feedback': 'feedback', 'scene_request': 'a scene request', 'scene_graph': 'a scene graph',
             'ranking': 'a ranking', 'user_model': 'a user model', 'question_request': 'a question request'}


def check(name: str, payload, typed_field: Callable[[str], str] | None = None) -> None:
    """Raise ``BadMessage('schema', ...)`` naming where ``payload`` breaks ``name``'s schema
    (a typed message's twin: its own field, through ``typed_field``)."""
    import fastjsonschema

    try:
        validator(name)(payload)
    except fastjsonschema.JsonSchemaValueException as error:
        raise BadMessage('schema', f'{name} message invalid: {_explain(name, error, typed_field)}',
                         _scene_id(payload)) from None


def parse_scene_request(message, max_bytes: int = DEFAULT_MAX_BYTES) -> SceneRequest:
    """Validate a /stars/scene message (its text, or the ``Twin`` of a typed request) and
    return it as a ``SceneRequest``."""
    typed_field = None
    if isinstance(message, Twin):
        message.check_size(max_bytes)
        payload, typed_field = message.payload, message.typed_field
    else:
        payload = load_json(message, max_bytes)
    check('scene_request', payload, typed_field)
    candidates = payload.get('candidates')
    user_id = payload.get('user_id')
    if candidates is not None and isinstance(candidates[0], dict):
        labels = tuple(c['candidate'] for c in candidates)
        if len(set(labels)) != len(labels):
            raise BadMessage('schema', 'scene_request message invalid: candidate labels repeat', payload['scene_id'])
        return SceneRequest(payload['scene_id'], user_id, tuple(c['graph'] for c in candidates), labels,
                            action=payload.get('action'), explain=payload.get('explain', False))
    return SceneRequest(payload['scene_id'], user_id, (payload['graph'],),
                        actions=None if candidates is None else tuple(candidates),
                        explain=payload.get('explain', False))


def parse_feedback(message, max_bytes: int = DEFAULT_MAX_BYTES) -> Feedback:
    """Validate a /stars/feedback message (its text, or the ``Twin`` of typed feedback) and
    return it as ``Feedback``."""
    if isinstance(message, Twin):
        message.check_size(max_bytes)
        payload = message.payload
    else:
        payload = load_json(message, max_bytes)
    check('feedback', payload)
    try:
        score = float(payload['score'])
    except OverflowError:
        score = math.inf
    if not math.isfinite(score):
        raise BadMessage('non_finite', f"feedback score {payload['score']} is not a finite number",
                         payload['scene_id'])
    return Feedback(payload['user_id'], payload['scene_id'], score, payload.get('action'), payload.get('candidate'),
                    payload if 'auth' in payload else None, payload.get('implicit', False))


@dataclass(frozen=True)
class QuestionRequest:
    """One validated stars/question_request: whom to ask, and the scene requests to choose
    the question from (empty: the scenes the node saw recently), each with its JSON text."""

    user_id: str
    candidates: tuple = ()


def parse_question_request(text, max_bytes: int = DEFAULT_MAX_BYTES) -> QuestionRequest:
    """Validate a stars/question_request message; its candidates parse as scene requests."""
    payload = load_json(text, max_bytes)
    check('question_request', payload)
    candidates = []
    for candidate in payload.get('candidates', ()):
        candidate_text = dumps(candidate)
        candidates.append((parse_scene_request(candidate_text, max_bytes), candidate_text))
    return QuestionRequest(payload['user_id'], tuple(candidates))


def parse_user_id(text: str) -> str | None:
    """The id on /stars/user_id: plain text, surrounding blanks dropped; empty means nobody."""
    user_id = text.strip()
    if len(user_id) > MAX_ID_CHARS or not user_id.isprintable():
        raise BadMessage('schema', f'user id must be printable text of at most {MAX_ID_CHARS} characters')
    return user_id or None


def ranking_payload(request: SceneRequest, user_id: str | None, known_user: bool, ranked: Sequence,
                    fingerprint: str, processing_ms: float, action: str | None = None,
                    personalised_from: int = 0, p_first_is_best: float | None = None) -> dict:
    """The /stars/ranking reply (a dict following ranking.schema.json) for ``ranked`` entries
    (``predictor.Ranked``), best first. ``personalised_from`` > 0: the user was scored with an
    embedding folded in from that many feedback ratings (the field is omitted when 0).
    Entries carry ``score_sd``, ``why`` and the ranking ``p_first_is_best`` where they are computed."""
    key = 'candidate' if request.ranks_scenes else 'action'
    entries = []
    for r in ranked:
        entry = {key: r.name, 'score': r.score, 'rank': r.rank}
        if r.score_sd is not None:
            entry['score_sd'] = r.score_sd
        if r.why is not None:
            entry['why'] = {'content': r.why.content, 'personal': r.why.personal, 'scene': r.why.scene,
                            'entities': [{'id': i, 'kind': kind, 'effect': effect} for i, kind,
                                         effect in r.why.entities]}
        entries.append(entry)
    reply = {
        'scene_id': request.scene_id,
        'user_id': user_id,
        'known_user': known_user,
        'ranking': entries,
        'fingerprint': fingerprint,
        'processing_ms': processing_ms,
    }
    if request.ranks_scenes:
        reply['action'] = action
    if personalised_from:
        reply['personalised_from'] = int(personalised_from)
    if p_first_is_best is not None:
        reply['p_first_is_best'] = p_first_is_best
    return reply


def user_model_payload(user_id: str, model, fingerprint: str, origin: str | None = None,
                       ratings: Sequence | None = None) -> dict:
    """The stars/user_model message (user_model.schema.json) for a folded-in ``model``
    (``foldin.UserModel``) solved against the checkpoint ``fingerprint``; with fleet sharing,
    the node that solved it (``origin``) and the ``ratings`` (``foldin.Rating``) it was
    solved from."""
    payload = {'user_id': str(user_id), **model.to_json(), 'fingerprint': fingerprint}
    if ratings is not None:
        payload.update(origin=origin, ratings=[r.to_json() for r in ratings])
    return payload


def parse_user_model(text, max_bytes: int = DEFAULT_MAX_BYTES) -> dict:
    """Validate a stars/user_model message (a peer's, with fleet sharing) and return it."""
    payload = load_json(text, max_bytes)
    check('user_model', payload)
    return payload


def dumps(payload: dict) -> str:
    """Compact JSON that refuses NaN and infinities, as the schemas do."""
    return json.dumps(payload, separators=(',', ':'), allow_nan=False)


def error_kind(error: Exception) -> str:
    """The diagnostics category of an error raised while handling a message."""
    if isinstance(error, BadMessage):
        return error.kind
    if isinstance(error, UnknownActionError):
        return 'unknown_action'
    if isinstance(error, OutOfScaleError):
        return 'out_of_scale'
    if isinstance(error, SceneGraphError):
        return 'scene_graph'
    if isinstance(error, StarsError):
        return 'model'
    return 'internal'
