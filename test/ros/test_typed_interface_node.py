"""The ranker's typed interface (stars_ros_msgs), driven over loopback DDS against a real node:
the services rank typed scenes for a known and an unknown person with the scores of the JSON
path, typed feedback moves the person's next ranking, a malformed typed request gets the JSON
path's error kind (in the response and on stars/errors) and the node answers the next one."""
import json
import math

import pytest
from geometry_msgs import msg as geometry
from stars_ros_msgs import msg as typed
from stars_ros_msgs.srv import ChooseQuestion, RankActions, RankCandidates

from ros_helpers import RosClient, call_service as call, domain_id, running_ranker, start_node
from waiting import wait_for
from stars_ros.data.scene_source import placement_candidates, read_scenes, scene_request
from stars_ros.model.predictor import Predictor
from stars_ros.typed_messages import scene_message

pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning:lark.*')
KNOWN_USER = 'b'  # in the tiny checkpoint's training rows
FRAME = 'base_link'  # the ranker's default frame_id


def rank_actions(client, scene_id, scene, user_id='', frame=FRAME, **fields):
    request = RankActions.Request(scene_id=scene_id, user_id=user_id,
                                  scene=scene_message(scene, frame, typed, geometry), **fields)
    return call(client, RankActions, '/ranker/rank_actions', request)


def scores(entries) -> dict:
    return {entry.name: entry.score for entry in entries}


@pytest.fixture(scope='module')
def node(tiny_checkpoint, synthetic_scenes, tmp_path_factory):
    """The module's ranker; each test names people and scene ids of its own."""
    folder = tmp_path_factory.mktemp('typed_ranker')
    params = {'checkpoint': tiny_checkpoint, 'record_folder': folder / 'records'}
    with running_ranker(domain_id(15), params, folder / 'ranker.log', scene_request('probe', synthetic_scenes[0])) \
            as running:
        yield running


@pytest.fixture()
def ranker(node, request):
    """The module's node, and a client that holds nothing heard before the test: a refusal
    sent now comes after every earlier error on stars/errors, then all of it is forgotten."""
    process, client = node
    assert process.poll() is None, "the module's ranker died in an earlier test"
    marker = f'before-{request.node.name}'
    client.scene({'scene_id': marker, 'graph': {}})
    assert client.wait(lambda: any(e['scene_id'] == marker for e in client.errors), 30), 'the refusal never came'
    client.forget()
    return process, client


def test_a_typed_scene_is_ranked_for_a_known_and_an_unknown_person(ranker, tiny_checkpoint, synthetic_scenes):
    process, client = ranker
    predictor = Predictor.load(tiny_checkpoint)
    scene = synthetic_scenes[3]
    for user_id, known in ((KNOWN_USER, True), ('typed-stranger', False)):
        response = rank_actions(client, f'typed-{user_id}', scene, user_id)
        assert response.success and response.error_kind == '' and response.message == ''
        ranking = response.ranking
        assert (ranking.scene_id, ranking.user_id, ranking.known_user) == (f'typed-{user_id}', user_id, known)
        assert ranking.header.frame_id == FRAME and ranking.fingerprint == predictor.fingerprint
        assert [e.rank for e in ranking.entries] == list(range(1, len(predictor.actions) + 1))
        assert all(e.score_sd > 0 for e in ranking.entries) and 0 <= ranking.p_first_is_best <= 1
        assert ranking.processing_time > 0 and not any(e.has_why for e in ranking.entries)
        expected = predictor.rank(user_id, scene, scene_id=f'typed-{user_id}')
        assert scores(ranking.entries) == pytest.approx({r.name: r.score for r in expected}, abs=1e-9)
    explained = rank_actions(client, 'typed-why', scene, KNOWN_USER, explain=True).ranking.entries
    assert all(entry.has_why and entry.why.entities for entry in explained)


def test_typed_and_json_requests_get_the_same_scores(ranker, synthetic_scenes):
    process, client = ranker
    for k, scene in enumerate(synthetic_scenes[10:16]):
        client.scene(scene_request(f'json-{k}', scene, KNOWN_USER))
        typed_ranking = rank_actions(client, f'typed-twin-{k}', scene, KNOWN_USER).ranking
        assert client.wait(lambda: client.ranking_for(f'json-{k}') is not None, 30)
        json_ranking = client.ranking_for(f'json-{k}')
        assert scores(typed_ranking.entries) == pytest.approx(
            {e['action']: e['score'] for e in json_ranking['ranking']}, abs=1e-9)
    candidates = placement_candidates(synthetic_scenes[20], 4)
    client.scene({'scene_id': 'json-placements', 'user_id': KNOWN_USER, 'candidates': candidates})
    request = RankCandidates.Request(scene_id='typed-placements', user_id=KNOWN_USER, candidates=[
        typed.CandidateScene(label=c['candidate'], scene=scene_message(c['graph'], FRAME, typed, geometry))
        for c in candidates])
    response = call(client, RankCandidates, '/ranker/rank_candidates', request)
    assert response.success, response.message
    assert client.wait(lambda: client.ranking_for('json-placements') is not None, 30)
    twin = client.ranking_for('json-placements')
    assert response.ranking.action == twin['action']
    assert scores(response.ranking.entries) == pytest.approx(
        {e['candidate']: e['score'] for e in twin['ranking']}, abs=1e-9)


def test_typed_feedback_moves_that_persons_next_ranking(ranker, synthetic_scenes):
    process, client = ranker
    scene, user_id = synthetic_scenes[7], 'typed-newcomer'
    before = rank_actions(client, 'rated', scene, user_id).ranking
    assert before.personalised_from == 0
    action = before.entries[0].name
    feedback = client.node.create_publisher(typed.Feedback, '/stars/typed/feedback', 10)
    assert wait_for(lambda: feedback.get_subscription_count() > 0, 30)
    feedback.publish(typed.Feedback(user_id=user_id, scene_id='rated', action='fly_away', score=0.5))
    assert client.wait(lambda: any(e['kind'] == 'unknown_action' and e['scene_id'] == 'rated'
                                   and e['topic'] == '/stars/typed/feedback' for e in client.errors), 30)
    feedback.publish(typed.Feedback(user_id=user_id, scene_id='rated', action=action, score=0.0))

    def personalised():  # the fold-in runs once the feedback is taken in: ask until it is served
        return rank_actions(client, 'after', scene, user_id).ranking.personalised_from == 1
    assert wait_for(personalised, 60), 'typed feedback was not folded in'
    client.node.destroy_publisher(feedback)  # taken in: the module's later tests meet no extra publisher
    after = rank_actions(client, 'after', scene, user_id).ranking
    assert scores(after.entries)[action] < scores(before.entries)[action]


def _nan_pose(request):
    request.scene.humans[0].pose.position.x = math.nan


def _unknown_action(request):
    request.actions = ['fly_away']


def _empty_scene(request):
    request.scene.humans, request.scene.objects, request.scene.room, request.scene.interactions = [], [], [], []


def _other_frame(request):
    request.scene.header.frame_id = 'map'


def _json_twin(scene_id: str, scene: dict, **fields) -> str:
    return json.dumps({'scene_id': scene_id, 'graph': scene, **fields})


@pytest.mark.parametrize('spoil, kind, json_twin', [
    (_nan_pose, 'non_finite', lambda i, scene: _json_twin(i, scene).replace('"xPos": ', '"xPos": NaN, "was": ', 1)),
    (_unknown_action, 'unknown_action', lambda i, scene: _json_twin(i, scene, candidates=['fly_away'])),
    (_empty_scene, 'schema', lambda i, scene: _json_twin(i, {'humans': [], 'objects': [], 'links': [], 'room': []})),
    (_other_frame, 'frame', None)])
def test_a_malformed_typed_request_gets_its_error_and_the_node_answers_the_next(ranker, synthetic_scenes, spoil,
                                                                              kind, json_twin):
    process, client = ranker
    scene_id, scene = f'bad-{kind}', next(s for s in synthetic_scenes if s['humans'])
    request = RankActions.Request(scene_id=scene_id, scene=scene_message(scene, FRAME, typed, geometry))
    spoil(request)
    response = call(client, RankActions, '/ranker/rank_actions', request)
    assert not response.success and response.error_kind == kind and response.message
    typed_field = {'non_finite': 'scene.humans[0].pose.position.x', 'schema': "'scene.room'"}.get(kind)
    assert typed_field is None or typed_field in response.message  # the typed field, not the JSON twin's
    assert client.wait(lambda: any(e['kind'] == kind and e['scene_id'] == scene_id for e in client.errors), 30)
    assert {e['topic'] for e in client.errors if e['scene_id'] == scene_id} == {'/ranker/rank_actions'}  # its service
    if json_twin is not None:  # the same mistake on the JSON path gets the same kind
        seen = len(client.errors)
        client.scene(json_twin(f'json-{scene_id}', scene))
        assert client.wait(lambda: len(client.errors) > seen, 30)
        assert client.errors[seen]['kind'] == kind and client.errors[seen]['topic'] == '/stars/scene'
    assert rank_actions(client, f'next-{kind}', scene).success and process.poll() is None


def test_the_typed_question_service_asks_about_a_given_scene(ranker, synthetic_scenes):
    process, client = ranker
    request = ChooseQuestion.Request(user_id='typed-asked', scene_ids=['ask-0', 'ask-1'], scenes=[
        scene_message(scene, FRAME, typed, geometry) for scene in synthetic_scenes[30:32]])
    response = call(client, ChooseQuestion, '/ranker/choose_question', request)
    assert response.success, response.message
    assert response.question.scene_id in {'ask-0', 'ask-1'} and response.question.candidates >= 2
    request.scene_ids = ['ask-0']
    refused = call(client, ChooseQuestion, '/ranker/choose_question', request)
    assert not refused.success and refused.error_kind == 'schema'


@pytest.mark.slow
@pytest.mark.socnav1
def test_typed_and_json_paths_score_50_socnav1_scenes_alike(socnav1_root, tmp_path):
    """The packaged model on 50 real SocNav1 scenes, for an annotator and a stranger: the
    typed request (REP 103 metres and quaternions, converted back) scores as its JSON twin."""
    scenes = read_scenes(socnav1_root / 'raw' / 'g.jsonl')[:50]
    domain = domain_id(1)
    client = RosClient(domain)
    process = start_node('stars_ros.ros.ranker', domain, {'record_folder': tmp_path}, tmp_path / 'ranker.log')
    try:
        client.wait_ready(process, 90, scene_request('probe', scenes[0]))
        for k, scene in enumerate(scenes):
            user_id = 'g' if k % 2 else 'stranger'
            client.scene({'scene_id': scene['identifier'], 'user_id': user_id, 'graph': scene})
            served = rank_actions(client, scene['identifier'], scene, user_id).ranking
            assert client.wait(lambda: client.ranking_for(scene['identifier']) is not None, 30)
            twin = client.ranking_for(scene['identifier'])
            assert served.known_user is twin['known_user']
            assert scores(served.entries) == pytest.approx({e['action']: e['score'] for e in twin['ranking']},
                                                           abs=1e-9)
    finally:
        process.kill()
        process.wait()
        client.close()
