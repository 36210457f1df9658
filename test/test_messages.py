"""The JSON payloads of the ranker topics: parsing, refusals by kind, schema equivalence."""
import json
import random

import jsonschema
import pytest
from referencing import Registry, Resource

from mutations import mutate
from stars_ros import messages
from stars_ros.model.predictor import Ranked
from stars_ros.data.scene_source import read_scenes, scene_request

SCHEMAS = ('scene_graph', 'scene_request', 'ranking', 'feedback')


@pytest.fixture(scope='module')
def scenes(synthetic_root):
    return read_scenes(synthetic_root / 'raw' / 'a.jsonl')[:20]


@pytest.fixture(scope='module')
def reference():
    """jsonschema validators on the untouched 2020-12 files: the independent judge."""
    loaded = {name: messages.load_schema(name) for name in SCHEMAS}
    registry = Registry().with_resources([(s['$id'], Resource.from_contents(s)) for s in loaded.values()])
    return {name: jsonschema.Draft202012Validator(s, registry=registry) for name, s in loaded.items()}


def test_schemas_are_valid_2020_12():
    for name in SCHEMAS:
        jsonschema.Draft202012Validator.check_schema(messages.load_schema(name))


def test_socnav1_format_line_parses(scenes):
    text = json.dumps({'scene_id': 's1', 'user_id': 'g', 'graph': scenes[0]})
    request = messages.parse_scene_request(text)
    assert (request.scene_id, request.user_id, request.graphs, request.ranks_scenes) == ('s1', 'g', (scenes[0],), False)
    assert request.actions is None


def test_action_and_scene_candidates(scenes):
    request = messages.parse_scene_request(json.dumps({'scene_id': 's', 'graph': scenes[0],
                                                       'candidates': ['navigate']}))
    assert request.actions == ('navigate',)
    payload = scene_request('s', scenes[1], placements=3)
    request = messages.parse_scene_request(json.dumps(payload))
    assert request.ranks_scenes and request.labels == ('stay', 'left_50cm', 'right_50cm') and len(request.graphs) == 3


@pytest.mark.parametrize('text, kind', [
    ('{"scene_id": "s", "graph": ', 'malformed_json'),
    ('', 'malformed_json'),
    ('[' * 100000, 'malformed_json'),
    ('{"scene_id": "s", "graph": {"humans": [], "room": [[0, 0], [1, NaN], [2, 3]]}}', 'non_finite'),
    ('{"scene_id": "s", "graph": {"humans": [], "room": [[0, 0], [1, Infinity], [2, 3]]}}', 'non_finite'),
    ('{"scene_id": "s", "graph": {"humans": [], "room": [[0, 0], [1, 1e999], [2, 3]]}}', 'non_finite'),
    ('{"scene_id": "s"}', 'schema'),
    ('{"scene_id": "s", "graph": {}}', 'schema'),
    ('{"scene_id": "s", "graph": {"humans": [], "room": []}}', 'schema'),
    ('{"scene_id": "s", "graph": {"humans": [], "room": [[0, 0], [1, 1], [2, 3]]}, "typo": 1}', 'schema'),
    ('{"scene_id": "s", "graph": {"humans": [], "room": [[0, 0], [1, 1], [2, 3]]}, "candidates": []}', 'schema'),
    ('{"scene_id": "s", "graph": {"humans": [], "room": [[0, 0], [1, 1], [2, 3]]}, "action": "navigate"}', 'schema'),
    ('{"scene_id": "", "graph": {"humans": [], "room": [[0, 0], [1, 1], [2, 3]]}}', 'schema'),
    ('["not", "an", "object"]', 'schema'),
])
def test_refusals_name_their_kind(text, kind):
    with pytest.raises(messages.BadMessage) as caught:
        messages.parse_scene_request(text)
    assert caught.value.kind == kind


def test_oversized_and_absurd_sizes(scenes):
    with pytest.raises(messages.BadMessage) as caught:
        messages.parse_scene_request(json.dumps({'scene_id': 's', 'graph': scenes[0]}), max_bytes=100)
    assert caught.value.kind == 'oversized' and '100 bytes' in str(caught.value)
    crowd = dict(scenes[0], humans=[{'id': k, 'xPos': 0, 'yPos': 50, 'orientation': 0} for k in range(1, 3000)])
    with pytest.raises(messages.BadMessage, match='humans') as caught:
        messages.parse_scene_request(json.dumps({'scene_id': 's', 'graph': crowd}), max_bytes=1 << 24)
    assert caught.value.kind == 'schema'


def test_both_graph_and_candidate_scenes_refused_clearly(scenes):
    payload = scene_request('s', scenes[0], placements=2)
    payload['graph'] = scenes[0]
    with pytest.raises(messages.BadMessage, match="'graph' goes with action candidates"):
        messages.parse_scene_request(json.dumps(payload))


def test_repeated_candidate_labels_refused(scenes):
    payload = {'scene_id': 's', 'candidates': [{'candidate': 'a', 'graph': scenes[0]}, {'candidate': 'a',
                                                                                        'graph': scenes[1]}]}
    with pytest.raises(messages.BadMessage, match='labels repeat'):
        messages.parse_scene_request(json.dumps(payload))


def test_feedback():
    feedback = messages.parse_feedback('{"user_id": "g", "scene_id": "s", "action": "navigate", "score": 0.25}')
    assert (feedback.user_id, feedback.scene_id, feedback.action, feedback.candidate, feedback.score) == \
        ('g', 's', 'navigate', None, 0.25)
    feedback = messages.parse_feedback('{"user_id": "g", "scene_id": "s", "candidate": "left", "score": 1}')
    assert feedback.candidate == 'left'
    for text, kind in [('{"user_id": "g", "scene_id": "s", "score": 1}', 'schema'),
                       ('{"user_id": "g", "scene_id": "s", "action": "a", "candidate": "b", "score": 1}', 'schema'),
                       ('{"user_id": "g", "scene_id": "s", "action": "a", "score": "high"}', 'schema'),
                       ('{"user_id": "g", "scene_id": "s", "action": "a", "score": NaN}', 'non_finite'),
                       ('{"user_id": "g", "scene_id": "s", "action": "a", "score": 1' + '0' * 400 + '}', 'non_finite')]:
        with pytest.raises(messages.BadMessage) as caught:
            messages.parse_feedback(text)
        assert caught.value.kind == kind, text


GRAPH = {'humans': [], 'room': [[0, 0], [1, 1], [2, 3]]}


@pytest.mark.parametrize('parse, payload, words', [
    (messages.parse_feedback, {'user_id': 'g', 'scene_id': 's', 'score': 1},
     "feedback needs either 'action' (the action rated) or 'candidate'"),
    (messages.parse_feedback, {'user_id': 'g', 'scene_id': 's', 'action': 'a', 'candidate': 'b', 'score': 1},
     "either 'action' (the action rated) or 'candidate' (the candidate scene rated), exactly one of them"),
    (messages.parse_feedback, {'user_id': 'g', 'scene_id': 's', 'action': 'a'}, "feedback needs 'score'"),
    (messages.parse_feedback, {'user_id': 'g', 'scene_id': 's', 'action': 'a', 'score': 'high'},
     "'score' must be number"),
    (messages.parse_feedback, {'user_id': 'g', 'scene_id': 's', 'action': 'a', 'score': 1, 'rating': 1},
     "'rating': not a field of feedback (its fields: user_id, scene_id, action, candidate, score, implicit, auth)"),
    (messages.parse_scene_request, {'scene_id': 's'}, "a scene request needs 'graph'"),
    (messages.parse_scene_request, {'scene_id': 's', 'graph': {}}, "'graph' needs 'humans' and 'room'"),
    (messages.parse_scene_request, {'scene_id': 's', 'graph': dict(GRAPH, humans=[
        {'id': 1, 'xPos': 'near', 'yPos': 0, 'orientation': 0}])}, "'graph.humans[0].xPos' must be number"),
    (messages.parse_scene_request, {'scene_id': 's', 'graph': GRAPH, 'candidates': [1]},
     "'candidates' must be a list of action names or a list of candidate scenes"),
    (messages.parse_scene_request, {'scene_id': 's', 'graph': GRAPH, 'candidates': ['a', {'candidate': 'b'}]},
     "'candidates' must be a list of action names or a list of candidate scenes"),
    (messages.parse_scene_request, {'scene_id': 's', 'candidates': ['a']}, "a scene request needs 'graph'"),
    (messages.parse_scene_request, {'scene_id': 's', 'graph': GRAPH, 'action': 'a'},
     "'graph' goes with action candidates, 'action' with candidate scenes"),
])
def test_schema_errors_name_the_field_in_words(parse, payload, words):
    with pytest.raises(messages.BadMessage) as caught:
        parse(json.dumps(payload))
    assert caught.value.kind == 'schema' and words in str(caught.value)
    assert 'data' not in str(caught.value) and 'definition' not in str(caught.value)
    assert caught.value.scene_id == 's'


@pytest.mark.parametrize('parse, text, scene_id', [
    (messages.parse_feedback, '{"user_id": "g", "scene_id": "s7", "score": 1}', 's7'),
    (messages.parse_feedback, '{"user_id": "g", "scene_id": "s7", "action": "a", "score": 1' + '0' * 400 + '}', 's7'),
    (messages.parse_scene_request, '{"scene_id": "s7", "graph": {"humans": []}}', 's7'),
    (messages.parse_scene_request, json.dumps({'scene_id': 's7', 'candidates': [
        {'candidate': 'a', 'graph': GRAPH}, {'candidate': 'a', 'graph': GRAPH}]}), 's7'),
    (messages.parse_scene_request, '{"scene_id": 7, "graph": {"humans": []}}', None),
    (messages.parse_scene_request, '{"scene_id": "s7", "graph": ', None),
])
def test_refused_messages_carry_their_scene_id(parse, text, scene_id):
    """stars/errors reports carry the request's scene id whenever the message had a usable one."""
    with pytest.raises(messages.BadMessage) as caught:
        parse(text)
    assert caught.value.scene_id == scene_id


def test_user_id():
    assert messages.parse_user_id('  g \n') == 'g'
    assert messages.parse_user_id('') is None
    for bad in ('x' * 300, 'a\x00b'):
        with pytest.raises(messages.BadMessage):
            messages.parse_user_id(bad)


def test_ranking_payload_follows_its_schema(reference):
    request = messages.SceneRequest('s', 'g', ({},))
    reply = messages.ranking_payload(request, 'g', True, [Ranked('navigate', 0.7, 1)], 'ab' * 32, 1.5)
    reference['ranking'].validate(json.loads(messages.dumps(reply)))
    scenes_request = messages.SceneRequest('s', None, ({}, {}), labels=('a', 'b'))
    reply = messages.ranking_payload(scenes_request, None, False, [Ranked('b', 0.7, 1), Ranked('a', 0.2, 2)],
                                     'ab' * 32, 0.1, action='navigate')
    reference['ranking'].validate(reply)
    assert reply['ranking'][0] == {'candidate': 'b', 'score': 0.7, 'rank': 1} and 'personalised_from' not in reply
    folded = messages.ranking_payload(request, 'g', False, [Ranked('navigate', 0.7, 1)], 'ab' * 32, 1.5,
                                      personalised_from=3)
    reference['ranking'].validate(folded)
    messages.check('ranking', folded)
    assert folded['personalised_from'] == 3
    with pytest.raises(messages.BadMessage):
        messages.check('ranking', {**folded, 'personalised_from': 0})
    with pytest.raises(ValueError):
        messages.dumps({'score': float('nan')})


def _reference_accepts(validator, text):
    try:
        payload = json.loads(text, parse_constant=lambda name: float('nan'))
    except (ValueError, RecursionError):
        return None
    return validator.is_valid(payload)


def test_fast_validator_agrees_with_jsonschema(scenes, reference):
    """The compiled draft-07 translation accepts and refuses exactly what jsonschema does
    with the original 2020-12 files, on 600 mutated messages."""
    rng = random.Random(7)
    agreed = decided = 0
    for k in range(600):
        payload = scene_request(f's{k}', scenes[k % len(scenes)], user_id='g', placements=2 if k % 3 == 0 else 0)
        text = mutate(payload, rng)
        expected = _reference_accepts(reference['scene_request'], text)
        if expected is None or len(text) > 1 << 20 or 'NaN' in text or 'Infinity' in text or '1e999' in text:
            continue  # not JSON, or refused before any schema: covered by the tests above
        try:
            messages.check('scene_request', json.loads(text))
            fast = True
        except messages.BadMessage:
            fast = False
        decided += 1
        agreed += fast == expected
        assert fast == expected, text[:300]
    assert decided > 250 and agreed == decided


def test_draft07_translation_refuses_unknown_keywords():
    with pytest.raises(ValueError, match='unevaluatedProperties'):
        messages.draft07({'type': 'object', 'unevaluatedProperties': False})
    assert messages.draft07({'prefixItems': [{'type': 'integer'}], 'items': False}) == \
        {'items': [{'type': 'integer'}], 'additionalItems': False}
    assert messages.draft07({'$ref': '#/a', 'minimum': 1}) == {'allOf': [{'$ref': '#/a'}, {'minimum': 1}]}


def test_inlined_references_resolve_across_files_and_refuse_recursion():
    from stars_ros.messages import SCHEMA_BASE, _inline_refs
    root = {'$id': SCHEMA_BASE + 'x.schema.json', 'type': 'object',
            'properties': {'graph': {'$ref': 'scene_graph.schema.json'}, 'point': {'$ref': '#/$defs/point'}},
            '$defs': {'point': {'type': 'number', 'minimum': 0}}}
    inlined = _inline_refs(root, root, root['$id'])
    assert inlined['properties']['point'] == {'type': 'number', 'minimum': 0}
    assert inlined['properties']['graph']['required'] == ['humans', 'room']
    assert '$ref' not in json.dumps(inlined)
    loop = {'$id': SCHEMA_BASE + 'loop.schema.json', '$defs': {'node': {'items': {'$ref': '#/$defs/node'}}},
            '$ref': '#/$defs/node'}
    with pytest.raises(ValueError, match='recursive'):
        _inline_refs(loop, loop, loop['$id'])
