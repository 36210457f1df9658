"""The typed interface's twins (stars_ros.typed_messages): a SocNav1 scene sent as a typed
SceneGraph (REP 103 metres, quaternions) comes back as the same scene; a scene in another
frame, a NaN pose or a NaN score is refused with its kind; signed typed feedback verifies as
its JSON twin; a ranking payload becomes a typed Ranking with its optional fields."""
import json
import math

import numpy as np
import pytest
from geometry_msgs import msg as geometry
from stars_ros_msgs import msg as typed
from stars_ros_msgs.srv import ChooseQuestion, RankActions, RankCandidates

from stars_ros import feedback_auth, messages, typed_messages
from stars_ros.typed_messages import scene_graph, scene_message


def _same_scene(ours: dict, theirs: dict):
    for kind in ('humans', 'objects'):
        assert [e['id'] for e in ours.get(kind, [])] == [e['id'] for e in theirs.get(kind, [])]
        for a, b in zip(ours.get(kind, []), theirs.get(kind, [])):
            assert (a['xPos'], a['yPos']) == pytest.approx((b['xPos'], b['yPos']), abs=1e-9)
            assert math.remainder(a['orientation'] - b['orientation'], 360.0) == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(ours['room'], theirs['room'], rtol=0, atol=1e-9)
    assert [link[:2] for link in ours['links']] == [link[:2] for link in theirs.get('links', [])]


def test_a_socnav1_scene_survives_the_typed_round_trip(synthetic_scenes):
    for scene in synthetic_scenes[:20]:
        message = scene_message(scene, 'base_link', typed, geometry)
        assert message.header.frame_id == 'base_link'
        back = scene_graph(message, 'base_link')
        messages.check('scene_graph', back)
        _same_scene(back, scene)


def test_a_scene_in_another_frame_is_refused_naming_the_transform_needed(synthetic_scenes):
    message = scene_message(synthetic_scenes[0], 'map', typed, geometry)
    with pytest.raises(messages.BadMessage, match=r"TF base_link <- map") as refused:
        scene_graph(message, 'base_link', 's1')
    assert (refused.value.kind, refused.value.scene_id) == ('frame', 's1')
    message.header.frame_id = ''
    with pytest.raises(messages.BadMessage, match='header.frame_id is empty'):
        scene_graph(message, 'base_link')


def test_a_typed_requests_schema_errors_name_its_own_fields_and_an_empty_one_is_schema(synthetic_scenes):
    scene = next(s for s in synthetic_scenes if s['humans'])
    request = RankActions.Request(scene_id='s', scene=scene_message(scene, 'base_link', typed, geometry))
    request.scene.room = request.scene.room[:2]
    with pytest.raises(messages.BadMessage, match=r"'scene\.room' must contain at least 3 items") as refused:
        messages.parse_scene_request(typed_messages.rank_actions_twin(request, 'base_link'))
    assert refused.value.kind == 'schema'
    with pytest.raises(messages.BadMessage, match=r"'graph\.room' must"):  # the JSON twin, as it was
        messages.parse_scene_request(typed_messages.rank_actions_twin(request, 'base_link').text)
    empty = RankActions.Request()  # frame_id empty too: an empty scene is the schema's, as its JSON twin
    with pytest.raises(messages.BadMessage) as refused:
        messages.parse_scene_request(typed_messages.rank_actions_twin(empty, 'base_link'))
    assert refused.value.kind == 'schema'


def test_non_finite_poses_room_points_and_scores_are_refused(synthetic_scenes):
    scene = next(s for s in synthetic_scenes if s['humans'])
    message = scene_message(scene, 'base_link', typed, geometry)
    message.humans[0].pose.orientation.z = math.inf
    with pytest.raises(messages.BadMessage) as refused:
        scene_graph(message, 'base_link')
    assert refused.value.kind == 'non_finite'
    assert str(refused.value).startswith('scene.humans[0].pose.orientation.z is inf')  # the typed field's path
    message = scene_message(scene, 'base_link', typed, geometry)
    message.room[1].y = math.nan
    with pytest.raises(messages.BadMessage, match=r'candidates\[2\]\.scene\.room\[1\]\.y is nan'):
        scene_graph(message, 'base_link', where='candidates[2].scene')
    with pytest.raises(messages.BadMessage, match='not a finite number'):
        typed_messages.feedback_twin(typed.Feedback(user_id='u', scene_id='s', action='a', score=math.nan))


def test_requests_become_the_json_twins_the_schemas_take(synthetic_scenes):
    request = RankActions.Request(scene_id='s', user_id='u', actions=['a', 'b'], explain=True,
                                  scene=scene_message(synthetic_scenes[0], 'base_link', typed, geometry))
    twin_message = typed_messages.rank_actions_twin(request, 'base_link')
    text = twin_message.text
    assert json.loads(text) == twin_message.payload and len(text) <= twin_message.size_bound
    twin = messages.parse_scene_request(twin_message)
    assert twin == messages.parse_scene_request(text)
    with pytest.raises(messages.BadMessage, match=f'message of {len(text)} bytes exceeds the limit of 100 bytes'):
        messages.parse_scene_request(twin_message, 100)  # the size still counts, measured once over the bound
    with pytest.raises(messages.BadMessage, match="'scene_id'"):  # and the schema
        messages.parse_scene_request(messages.Twin({**twin_message.payload, 'scene_id': ''}, 0))
    assert (twin.scene_id, twin.user_id, twin.actions, twin.explain) == ('s', 'u', ('a', 'b'), True)
    request.user_id, request.actions, request.explain = '', [], False
    twin = messages.parse_scene_request(typed_messages.rank_actions_twin(request, 'base_link'))
    assert (twin.user_id, twin.actions, twin.explain) == (None, None, False)
    question = ChooseQuestion.Request(user_id='u', scene_ids=['x'], scenes=[request.scene])
    parsed = messages.parse_question_request(typed_messages.question_request_text(question, 'base_link'))
    assert [request.scene_id for request, _ in parsed.candidates] == ['x']
    question.scene_ids = []
    with pytest.raises(messages.BadMessage, match='1 scenes but 0 scene_ids'):
        typed_messages.question_request_text(question, 'base_link')


def test_a_twins_size_bound_holds_for_the_longest_numbers_and_strings(synthetic_scenes):
    """The bound a typed request's twin is size-checked by (without writing it) is never
    below its text: ids of 20 characters, floats of 24, strings that escape to 12 bytes a
    character, for actions and candidates alike."""
    longest = -2.2250738585072014e-306  # 24 characters in metres, as many in centimetres
    scene = scene_message(synthetic_scenes[0], 'base_link', typed, geometry)
    for k, human in enumerate(scene.humans):
        human.id = -2 ** 63 + k
        human.pose.position.x, human.pose.position.y = -1.2345678901234567e-7, longest
        human.pose.orientation.z, human.pose.orientation.w = 0.12345678901234567, 0.9876543210987654
    for point in scene.room:
        point.x, point.y = -1.2345678901234567e-7, -9.876543210987654e-7
    name = '\U0001F916\u00e9"\n'  # a surrogate pair, a BMP character, two escapes
    actions = RankActions.Request(scene_id=name * 3, user_id=name, actions=[name, name * 2], explain=True, scene=scene)
    candidates = RankCandidates.Request(scene_id=name, user_id=name * 5, action=name, candidates=[
        typed.CandidateScene(label=name * k, scene=scene) for k in range(1, 4)])
    for twin in (typed_messages.rank_actions_twin(actions, 'base_link'),
                 typed_messages.rank_candidates_twin(candidates, 'base_link')):
        text = twin.text
        assert len(text.encode()) <= twin.size_bound < 4 * len(text)


def test_signed_typed_feedback_verifies_as_its_json_twin():
    secret = bytes(range(32))
    feedback = typed.Feedback(user_id='ann', scene_id='s1', action='approach', score=0.25, auth_key_id='robot',
                              auth_stamp=1_000_000_000)
    feedback.auth_mac = feedback_auth.mac(secret, typed_messages.feedback_fields(feedback), feedback.auth_stamp)
    twin = typed_messages.feedback_twin(feedback)
    parsed = messages.parse_feedback(twin)  # taken as a value: its text is written for the log only
    assert parsed == messages.parse_feedback(twin.text)
    assert len(twin.text.encode()) <= twin.size_bound
    assert (parsed.user_id, parsed.action, parsed.candidate, parsed.score) == ('ann', 'approach', None, 0.25)
    authenticator = feedback_auth.FeedbackAuthenticator({'robot': secret}, lambda: 60.0)
    assert authenticator.check(parsed.signed, 1_000_000_000) is None
    unsigned = json.loads(typed_messages.feedback_twin(typed.Feedback(user_id='ann', scene_id='s1', candidate='c2',
                                                                      score=1.0)).text)
    assert unsigned == {'user_id': 'ann', 'scene_id': 's1', 'candidate': 'c2', 'score': 1.0}


def test_a_ranking_payload_becomes_a_typed_ranking():
    payload = {'scene_id': 's', 'user_id': None, 'known_user': False, 'fingerprint': 'f' * 64, 'processing_ms': 2.5,
               'ranking': [{'action': 'wait', 'score': 0.75, 'rank': 1, 'score_sd': 0.1,
                            'why': {'content': 0.5, 'personal': 0.2, 'scene': 0.05,
                                    'entities': [{'id': 3, 'kind': 'human', 'effect': -0.1},
                                                 {'id': 'wall-0', 'kind': 'wall', 'effect': 0.01}]}},
                           {'action': 'go', 'score': 0.5, 'rank': 2}]}
    ranking = typed_messages.ranking_message(payload, typed)
    assert (ranking.user_id, ranking.known_user, ranking.personalised_from, ranking.action) == ('', False, 0, '')
    assert ranking.processing_time == pytest.approx(0.0025) and math.isnan(ranking.p_first_is_best)
    first, second = ranking.entries
    assert (first.name, first.rank, first.has_why, first.why.personal) == ('wait', 1, True, 0.2)
    assert [(e.id, e.kind) for e in first.why.entities] == [('3', 'human'), ('wall-0', 'wall')]
    assert not second.has_why and math.isnan(second.score_sd)
