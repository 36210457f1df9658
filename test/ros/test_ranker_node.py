"""The ranker node, started for real and driven over loopback DDS.

One node for the module serves the ranking, error, fuzz, parameter, reload, publisher and
replay tests; each of them starts from the same node state (``ranker``: no latched user id,
whole rankings, the tiny checkpoint served, every answer to an earlier test in and forgotten
by the client, error totals read as differences), whatever the test before it changed or
where it failed, and names people and scene ids of its own. The tests that start a ranker of
their own (the process is their subject) are in ``test_ranker_process.py``.
"""
import json
import random
import threading
import time

import pytest

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Int32, String

from mutations import mutate
from ranker_harness import predictor, scenes  # noqa: F401 - the fixtures
from ranker_harness import KNOWN_USER, START_TIMEOUT, answers, assert_same, probe_request, served_latched_user, settle
from ros_helpers import domain_id, running_ranker, start_node
from stars_ros import StarsRecommender, recording
from stars_ros.model.predictor import Predictor
from stars_ros.data.scene_source import read_scenes, scene_request
from stars_ros.model.training import split_rows

pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning:lark.*')  # rclpy's parameter client


@pytest.fixture(scope='module')
def other_checkpoint(synthetic, tmp_path_factory):
    """A second small model (other seed and rows), for reload."""
    config = {'encoder': {'name': 'gcn', 'hidden': 16, 'layers': 1}, 'model': {'variant': 'stars', 'dim': 16},
              'training': {'pretrain_epochs': 1, 'joint_epochs': 1, 'lr': 3e-3, 'batch_size': 128, 'threads': 1,
                           'seed': 5}}
    train, _ = split_rows(synthetic, 0.2, 5)
    path = tmp_path_factory.mktemp('other') / 'other.pt'
    StarsRecommender(config).fit(synthetic, train[:300]).save(path)
    return path


@pytest.fixture(scope='module')
def node(tiny_checkpoint, scenes, tmp_path_factory):
    """The module's ranker on the tiny checkpoint (``ranker`` hands it to each test reset)."""
    folder = tmp_path_factory.mktemp('module_ranker')
    params = {'checkpoint': tiny_checkpoint, 'record_folder': folder / 'records', 'flush_interval': 0.2,
              'diagnostics_period': 0.3, 'log_throttle': 1.0}
    with running_ranker(domain_id(0), params, folder / 'ranker.log', probe_request(scenes), START_TIMEOUT) as running:
        yield running


def _ranker_values(client) -> dict:
    """The key-values of the ranker's latest /diagnostics status the client holds ({}: none yet)."""
    statuses = [s for d in client.snapshot(client.diagnostics) for s in d.status if s.name.endswith(': ranker')]
    return {v.key: v.value for v in statuses[-1].values} if statuses else {}


@pytest.fixture()
def ranker(node, scenes, predictor, tiny_checkpoint):
    """The module's node in its starting state, whatever an earlier test left: no latched
    user id, whole rankings, the tiny checkpoint served (reloaded if another one is), and a
    client that holds nothing heard before the test: every earlier answer is in and
    forgotten, and so are the /diagnostics periods that counted the earlier problems."""
    process, client = node
    assert process.poll() is None, "the module's ranker died in an earlier test"
    client.user_pub.publish(String(data=''))  # empty: nobody
    assert all(r.successful for r in client.set_parameters('/ranker', {'top_k': 0, 'checkpoint': str(tiny_checkpoint)}))
    served = served_latched_user(client, scenes, None)
    assert served is not None, 'the latched user id was never cleared'
    if served['fingerprint'] != predictor.fingerprint:
        assert client.call('/ranker/reload').success
    settle(client, scenes)
    client.forget()  # a period may still count settle's refusal: two more periods, then forget them too
    assert client.wait(lambda: len(client.diagnostics) >= 2, 20), 'no /diagnostics from the ranker'
    client.forget()
    return process, client


@pytest.fixture()
def error_totals_before(ranker) -> dict:
    """The ranker's errors.* totals (/diagnostics) before the test sends anything: a test on
    the module's node checks what its own requests added."""
    _, client = ranker
    assert client.wait(lambda: bool(_ranker_values(client)), 20), 'no /diagnostics from the ranker'
    return {key: int(value) for key, value in _ranker_values(client).items() if key.startswith('errors.')}


def test_ranking_equals_predictor_rank(ranker, scenes, predictor):
    _, client = ranker
    for scene in scenes[:20]:
        client.scene({'scene_id': scene['identifier'], 'user_id': KNOWN_USER, 'graph': scene})
    assert client.wait(lambda: all(client.ranking_for(s['identifier']) for s in scenes[:20]), 30)
    for scene in scenes[:20]:
        reply = client.ranking_for(scene['identifier'])
        assert reply['user_id'] == KNOWN_USER and reply['known_user'] is True
        assert reply['fingerprint'] == predictor.fingerprint
        assert reply['processing_ms'] >= 0  # what it measures: test_ranker_core.py, on a stepped clock
        assert_same(reply, predictor.rank(KNOWN_USER, scene, scene_id=scene['identifier']))


def test_candidate_scenes_equal_rank_scenes_and_users_differ(ranker, scenes, predictor):
    _, client = ranker
    for user in ('a', 'c'):
        client.scene(scene_request(f'placements-{user}', scenes[3], user_id=user, placements=5))
    assert client.wait(lambda: client.ranking_for('placements-a') and client.ranking_for('placements-c'), 30)
    for user in ('a', 'c'):
        request = scene_request('x', scenes[3], placements=5)
        expected = predictor.rank_scenes(user, [c['graph'] for c in request['candidates']],
                                         labels=[c['candidate'] for c in request['candidates']])
        reply = client.ranking_for(f'placements-{user}')
        assert reply['action'] == 'navigate'
        assert_same(reply, expected, key='candidate')


def test_user_id_topic_and_message_precedence(ranker, scenes, predictor):
    _, client = ranker
    client.user_pub.publish(String(data='c'))
    for attempt in range(200):  # a request without a user id is ranked for the latched one once it arrived
        probe = f'user-probe-{attempt}'
        client.scene({'scene_id': probe, 'graph': scenes[5]})
        assert client.wait(lambda: client.ranking_for(probe) is not None, 10)
        if client.ranking_for(probe)['user_id'] == 'c':
            break
    else:
        pytest.fail('the latched user id never reached the ranker')
    client.scene({'scene_id': 'from-topic', 'graph': scenes[5]})
    client.scene({'scene_id': 'from-message', 'user_id': 'a', 'graph': scenes[5]})
    client.scene({'scene_id': 'stranger', 'user_id': 'nobody-knows-me', 'graph': scenes[5]})
    assert client.wait(lambda: all(client.ranking_for(s) for s in ('from-topic', 'from-message', 'stranger')), 30)
    assert client.ranking_for('from-topic')['user_id'] == 'c'
    assert client.ranking_for('from-message')['user_id'] == 'a'
    stranger = client.ranking_for('stranger')
    assert stranger['known_user'] is False
    assert_same(stranger, predictor.rank('nobody-knows-me', scenes[5], scene_id='stranger'))
    assert client.wait(lambda: any(e['kind'] == 'unknown_user' and e['scene_id'] == 'stranger'
                                   for e in client.errors), 10)


BAD_INPUTS = {
    'malformed_json': '{"scene_id": "bad", "graph": ',
    'non_finite': '{"scene_id": "bad", "graph": {"humans": [], "room": [[0, 0], [1, NaN], [2, 3]]}}',
    'oversized': '{"scene_id": "bad", "pad": "' + 'x' * 300000 + '"}',
    'schema': '{"scene_id": "bad", "graph": {"humans": [], "room": []}}',
}


def test_bad_input_is_reported_on_both_topics_and_serving_goes_on(ranker, scenes, error_totals_before):
    process, client = ranker
    for text in BAD_INPUTS.values():
        client.scene(text)
    crowd = dict(scenes[0], humans=[{'id': k, 'xPos': 10, 'yPos': 20, 'orientation': 0} for k in range(1, 2500)])
    client.scene(json.dumps({'scene_id': 'crowd', 'graph': crowd}))
    client.scene({'scene_id': 'fly', 'graph': scenes[0], 'candidates': ['fly']})
    client.scene({'scene_id': 'twin-ids', 'graph': dict(scenes[0], objects=[dict(scenes[0]['humans'][0])])})
    client.scene({'scene_id': 'after-the-bad-ones', 'graph': scenes[1]})
    client.feedback({'user_id': KNOWN_USER, 'scene_id': 'no-action', 'score': 0.5})
    kinds = set(BAD_INPUTS) | {'unknown_action', 'scene_graph'}
    assert client.wait(lambda: kinds <= {e['kind'] for e in client.errors}, 20)
    assert client.wait(lambda: client.ranking_for('after-the-bad-ones') is not None, 20)
    assert client.wait(lambda: 'no-action' in {e['scene_id'] for e in client.errors}, 20)
    by_scene = {e['scene_id']: e for e in client.errors}
    assert by_scene['fly']['kind'] == 'unknown_action' and 'fly' in by_scene['fly']['message']
    assert by_scene['twin-ids']['kind'] == 'scene_graph'
    assert by_scene['crowd']['kind'] == 'schema' and 'humans' in by_scene['crowd']['message']
    assert by_scene['no-action']['kind'] == 'schema' and by_scene['no-action']['topic'] == '/stars/feedback'
    assert "feedback needs either 'action'" in by_scene['no-action']['message']

    def reported(kind):
        return any(s.name.endswith(': ' + kind) and s.level == b'\x02' for d in client.diagnostics for s in d.status)
    assert client.wait(lambda: all(reported(k) for k in kinds), 10)
    values = _ranker_values(client)
    assert int(values['errors.malformed_json']) >= error_totals_before.get('errors.malformed_json', 0) + 1
    assert values['fingerprint']
    assert process.poll() is None


def test_endpoints_that_can_never_match_are_reported_once_and_the_node_serves_on(ranker, scenes):
    """The ranker keeps no QoS event handlers of its own (qos_watch): it finds a subscriber
    that wants what stars/ranking does not offer, and a publisher of another type on
    stars/question_request, by asking the graph each diagnostics period."""
    process, client = ranker
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    wanting = client.node.create_subscription(String, '/stars/ranking', lambda _: None, latched)  # it is volatile
    other_type = client.node.create_publisher(Int32, '/stars/question_request', 10)
    problems = lambda: [e for e in client.snapshot(client.errors) if e['kind'] == 'qos']  # noqa: E731
    try:
        assert client.wait(lambda: len(problems()) >= 2, 20)
        by_topic = {e['topic']: e for e in problems()}
        assert 'transient local' in by_topic['/stars/ranking']['message'].lower()
        assert 'std_msgs/msg/Int32' in by_topic['/stars/question_request']['message']
        assert all(e['level'] == 'warning' for e in problems())
        client.diagnostics.clear()
        assert client.wait(lambda: len(client.snapshot(client.diagnostics)) >= 3, 20)  # three more periods
        assert len(problems()) == 2  # each reported once
    finally:  # the module's later tests meet no endpoint that cannot match
        client.node.destroy_subscription(wanting)
        client.node.destroy_publisher(other_type)
    client.scene({'scene_id': 'after-qos', 'graph': scenes[0]})
    assert client.wait(lambda: client.ranking_for('after-qos') is not None, 20)
    assert process.poll() is None


def test_fuzz_never_kills_the_node_and_valid_messages_stay_correct(ranker, scenes, predictor):
    """1,000 mutated messages with 250 valid ones interleaved: every message gets exactly
    one answer (a ranking or an error), and the valid ones the right ranking."""
    process, client = ranker
    rng = random.Random(11)
    before = [len(part) for part in answers(client)]

    def answered():
        return sum(len(part) for part in answers(client)) - sum(before)
    valid = {}
    sent = 0
    for k in range(1000):
        base = scene_request(f'fuzz-{k}', scenes[k % 150], user_id=rng.choice('abc'), placements=2 if k % 4 == 0 else 0)
        client.scene(mutate(base, rng))
        sent += 1
        if k % 4 == 3:
            scene = scenes[150 + k // 4 % 100]
            valid[f'valid-{k}'] = scene
            client.scene({'scene_id': f'valid-{k}', 'user_id': KNOWN_USER, 'graph': scene})
            sent += 1
        if k % 50 == 49:  # at most ~100 unanswered: the node's stars/scene history never overflows
            assert client.wait(lambda: answered() >= sent - 50, 60), 'the node stopped answering'
    settle(client, scenes)
    assert answered() == sent, 'some messages got no answer, or more than one'
    assert process.poll() is None
    for scene_id, scene in valid.items():
        assert_same(client.ranking_for(scene_id), predictor.rank(KNOWN_USER, scene, scene_id=scene_id))


def test_parameters_are_checked_and_top_k_applies(ranker, scenes):
    _, client = ranker
    refused = client.set_parameters('/ranker', {'top_k': -1})
    assert not refused[0].successful and 'top_k' in refused[0].reason
    assert not client.set_parameters('/ranker', {'max_batch': 'many'})[0].successful
    assert not client.set_parameters('/ranker', {'record_folder': '/elsewhere'})[0].successful  # read-only
    assert client.set_parameters('/ranker', {'top_k': 2})[0].successful
    client.scene(scene_request('top2', scenes[7], user_id='a', placements=5))
    assert client.wait(lambda: client.ranking_for('top2') is not None, 20)
    assert [e['rank'] for e in client.ranking_for('top2')['ranking']] == [1, 2]


def test_reload_under_load_swaps_models_without_losing_or_misscoring(ranker, scenes, predictor, other_checkpoint,
                                                                     tmp_path):
    _, client = ranker
    other = Predictor.load(other_checkpoint)
    assert other.fingerprint != predictor.fingerprint
    sent = []
    stop_sending = threading.Event()

    def send():
        k = 0
        while not stop_sending.is_set() and k < 2000:
            scene_id = f'load-{k}'
            client.scene({'scene_id': scene_id, 'user_id': KNOWN_USER, 'graph': scenes[k % len(scenes)]})
            sent.append((scene_id, scenes[k % len(scenes)]))
            k += 1
            time.sleep(0.01)  # the load itself: a steady ~100 requests a second, not a wait for anything

    def ranked_by(fingerprint, count=1):
        ranked, _ = answers(client, 'load-')
        return sum(client.ranking_for(s)['fingerprint'] == fingerprint for s in ranked) >= count

    sender = threading.Thread(target=send)
    sender.start()
    try:
        assert client.wait(lambda: ranked_by(predictor.fingerprint, 20), 30), 'no load served before the reload'
        assert client.set_parameters('/ranker', {'checkpoint': str(tmp_path / 'missing.pt')})[0].successful
        failed = client.call('/ranker/reload')
        assert not failed.success and 'missing.pt' in failed.message
        assert client.set_parameters('/ranker', {'checkpoint': str(other_checkpoint)})[0].successful
        response = client.call('/ranker/reload')
        assert response.success and other.fingerprint in response.message
        assert client.wait(lambda: ranked_by(other.fingerprint, 20), 30), 'no load served after the reload'
    finally:
        stop_sending.set()
        sender.join()
    assert client.wait(lambda: all(client.ranking_for(s) for s, _ in sent), 60), 'rankings were lost'
    models = {predictor.fingerprint: predictor, other.fingerprint: other}
    seen = []
    for scene_id, scene in sent:
        reply = client.ranking_for(scene_id)
        seen.append(reply['fingerprint'])
        assert_same(reply, models[reply['fingerprint']].rank(KNOWN_USER, scene, scene_id=scene_id))
    switch = seen.index(other.fingerprint)
    assert switch > 0 and set(seen[:switch]) == {predictor.fingerprint} and set(seen[switch:]) == {other.fingerprint}
    assert any(e['kind'] == 'checkpoint' for e in client.errors)


@pytest.mark.slow
def test_scene_publisher_feeds_the_ranker(ranker, synthetic_root, tmp_path):
    process, client = ranker
    runs = [({'source': synthetic_root / 'raw' / 'a.jsonl', 'user_id': 'a', 'count': 4, 'placements': 3,
              'scene_id_prefix': 'pub-', 'rate': 20.0}, 'pub-'),
            ({'count': 3, 'seed': 4, 'user_id': KNOWN_USER, 'scene_id_prefix': 'rnd-', 'rate': 20.0}, 'rnd-')]
    for params, prefix in runs:
        publisher = start_node('stars_ros.ros.scene_publisher', domain_id(0), params, tmp_path / f'{prefix}.log')
        log = tmp_path / f'{prefix}.log'
        assert publisher.wait(timeout=60) == 0, log.read_text()
        assert f"published {prefix}0 for user {params['user_id']} on /stars/scene (1 in all)" in log.read_text()
    assert client.wait(lambda: all(client.ranking_for(f'pub-{k}') for k in range(4))
                       and all(client.ranking_for(f'rnd-{k}') for k in range(3)), 30)
    assert all(client.ranking_for(f'pub-{k}')['user_id'] == 'a' for k in range(4))
    assert [len(client.ranking_for(f'pub-{k}')['ranking']) for k in range(4)] == [3] * 4
    assert client.ranking_for('rnd-0')['ranking'][0]['action'] == 'navigate'
    assert not [e for e in client.errors if str(e['scene_id']).startswith(('pub-', 'rnd-'))]
    own = tmp_path / 'own-ids.log'  # the file's own identifiers, which feedback can name
    publisher = start_node('stars_ros.ros.scene_publisher', domain_id(0), {
        'source': synthetic_root / 'raw' / 'b.jsonl', 'user_id': 'b', 'count': 2, 'keep_identifiers': True,
        'rate': 20.0}, own)
    assert publisher.wait(timeout=60) == 0, own.read_text()
    identifiers = [scene['identifier'] for scene in read_scenes(synthetic_root / 'raw' / 'b.jsonl')[:2]]
    assert client.wait(lambda: all(client.ranking_for(i) for i in identifiers), 30)


def test_replay_reruns_a_recorded_session(ranker, scenes, tmp_path):
    _, client = ranker
    qos = {'/stars/scene': recording.qos_profile(), '/stars/user_id': recording.qos_profile(1, transient_local=True),
           '/stars/ranking': recording.qos_profile()}
    with recording.Recorder(tmp_path, qos, name='session') as recorder:
        recorder.write('/stars/user_id', 'only-in-the-bag', 10 ** 9)  # nobody is latched before the replay
        for k in range(5):
            recorder.write('/stars/scene', json.dumps({'scene_id': f'replayed-{k}', 'graph': scenes[k]}),
                           10 ** 9 + (k + 2) * 10 ** 8)
        recorder.write('/stars/ranking', '{"not": "played by default"}', 2 * 10 ** 9)
    replay = start_node('stars_ros.ros.replay', domain_id(0), {'bag': tmp_path / 'session', 'rate': 1.0},
                        tmp_path / 'replay.log')
    assert replay.wait(timeout=60) == 0, (tmp_path / 'replay.log').read_text()
    assert 'played a message on /stars/user_id (1 in all)' in (tmp_path / 'replay.log').read_text()
    assert 'replayed 6 messages' in (tmp_path / 'replay.log').read_text()
    assert client.wait(lambda: all(client.ranking_for(f'replayed-{k}') for k in range(5)), 30)
    assert {client.ranking_for(f'replayed-{k}')['user_id'] for k in range(5)} == {'only-in-the-bag'}
    assert not any(r.get('not') for r in client.rankings)
