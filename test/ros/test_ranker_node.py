"""The ranker node, started for real and driven over loopback DDS.

One node for the module serves the ranking, error, fuzz, parameter, reload, publisher and
replay tests; each of them starts from the same node state (``ranker``: no latched user id,
whole rankings, the tiny checkpoint served, every answer to an earlier test in and forgotten
by the client, error totals read as differences), whatever the test before it changed or
where it failed, and names people and scene ids of its own. The shutdown, hard-kill,
unwritable-folder, flood and SocNav1 tests start their own: the process is their subject.
"""
import json
import random
import re
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import yaml

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Int32, String

from mutations import mutate
from ros_helpers import RosClient, domain_id, stored_feedback, ros_env, running_ranker, start_node, stop
from waiting import wait_for
from stars_ros import StarsRecommender, recording
from stars_ros.model.predictor import Predictor
from stars_ros.data.scene_source import read_scenes, scene_request
from stars_ros.resources import resolve_checkpoint
from stars_ros.model.training import split_rows

pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning:lark.*')  # rclpy's parameter client
KNOWN_USER = 'b'  # in the tiny checkpoint's training rows
START_TIMEOUT = 90


@pytest.fixture(scope='module')
def scenes(synthetic_scenes):
    return synthetic_scenes


@pytest.fixture(scope='module')
def predictor(tiny_checkpoint):
    return Predictor.load(tiny_checkpoint)


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


def _probe(scenes):
    return {'scene_id': f'probe-{time.monotonic_ns()}', 'graph': scenes[0]}


def _served_latched_user(client, scenes, user_id=KNOWN_USER, timeout: float = 20.0) -> dict | None:
    """Probe (each probe waiting for its ranking) until a request that names no user is
    ranked for ``user_id`` (the latched id; None: nobody); that ranking, None if none was."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        probe = _probe(scenes)
        client.scene(probe)
        if client.wait(lambda: client.ranking_for(probe['scene_id']) is not None, 5) and \
                client.ranking_for(probe['scene_id'])['user_id'] == user_id:
            return client.ranking_for(probe['scene_id'])
    return None


def _assert_same(reply, expected, key='action', tolerance=1e-5):
    assert [entry[key] for entry in reply['ranking']] == [r.name for r in expected]
    assert np.allclose([e['score'] for e in reply['ranking']], [r.score for r in expected], atol=tolerance)
    assert [e['rank'] for e in reply['ranking']] == list(range(1, len(expected) + 1))


SETTLED = 'settled-'  # the scene ids of _settle's markers


def _settle(client, scenes, attempts: int = 10):
    """Return once every answer to the requests sent so far has reached ``client``. The node
    takes stars/scene in order and each of its topics arrives in order: a request ranked
    after all of them (sent again while a full queue refuses it, once a ranking has come
    since, so the queue has had room made in it: a refusal comes back faster than a ranking
    is made), then, once that ranking is in, a request refused at once, whose error follows
    every earlier error."""
    for _ in range(attempts):
        scene_id = f'{SETTLED}{time.monotonic_ns()}'
        client.scene({'scene_id': scene_id, 'user_id': KNOWN_USER, 'graph': scenes[0]})
        if client.wait(lambda: client.ranking_for(scene_id) is not None or any(
                e['scene_id'] == scene_id for e in client.errors), 20) and client.ranking_for(scene_id):
            break
        rankings = len(client.snapshot(client.rankings))
        client.wait(lambda: len(client.snapshot(client.rankings)) > rankings, 20)
    else:
        pytest.fail(f'no request was ranked in {attempts} attempts')
    refused = f'{SETTLED}{time.monotonic_ns()}'
    client.scene({'scene_id': refused, 'graph': {}})
    assert client.wait(lambda: any(e['scene_id'] == refused for e in client.errors), 20), 'the refusal never came'


def _answers(client, prefix=None) -> tuple[set, list]:
    """(scene ids ranked, scene ids refused with an error, not a warning) of the answers
    ``client`` holds, _settle's markers left out; only ids starting with ``prefix`` if given."""
    def kept(scene_id):
        return not str(scene_id).startswith(SETTLED) and (prefix is None or str(scene_id).startswith(prefix))
    ranked = [r['scene_id'] for r in client.snapshot(client.rankings) if kept(r['scene_id'])]
    refused = [e['scene_id'] for e in client.snapshot(client.errors) if e['level'] == 'error' and kept(e['scene_id'])]
    return ranked, refused


def _on_disk(bag, topic) -> list:
    """The ``topic`` messages the bag's MCAP files hold on disk now, read as a hard kill
    would leave them (complete records only)."""
    return [json.loads(text) for path in recording.bag_files(bag)
            for found, text, _ in recording.salvage_messages(path)[0] if found == topic]


@pytest.fixture(scope='module')
def node(tiny_checkpoint, scenes, tmp_path_factory):
    """The module's ranker on the tiny checkpoint (``ranker`` hands it to each test reset)."""
    folder = tmp_path_factory.mktemp('module_ranker')
    params = {'checkpoint': tiny_checkpoint, 'record_folder': folder / 'records', 'flush_interval': 0.2,
              'diagnostics_period': 0.3, 'log_throttle': 1.0}
    with running_ranker(domain_id(0), params, folder / 'ranker.log', _probe(scenes), START_TIMEOUT) as running:
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
    served = _served_latched_user(client, scenes, None)
    assert served is not None, 'the latched user id was never cleared'
    if served['fingerprint'] != predictor.fingerprint:
        assert client.call('/ranker/reload').success
    _settle(client, scenes)
    client.forget()  # a period may still count _settle's refusal: two more periods, then forget them too
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
        _assert_same(reply, predictor.rank(KNOWN_USER, scene, scene_id=scene['identifier']))


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
        _assert_same(reply, expected, key='candidate')


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
    _assert_same(stranger, predictor.rank('nobody-knows-me', scenes[5], scene_id='stranger'))
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
    before = [len(part) for part in _answers(client)]

    def answered():
        return sum(len(part) for part in _answers(client)) - sum(before)
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
    _settle(client, scenes)
    assert answered() == sent, 'some messages got no answer, or more than one'
    assert process.poll() is None
    for scene_id, scene in valid.items():
        _assert_same(client.ranking_for(scene_id), predictor.rank(KNOWN_USER, scene, scene_id=scene_id))


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
        ranked, _ = _answers(client, 'load-')
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
        _assert_same(reply, models[reply['fingerprint']].rank(KNOWN_USER, scene, scene_id=scene_id))
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


@pytest.mark.slow
@pytest.mark.socnav1
def test_demo_runs_to_its_summary_and_a_second_run_prints_the_same_rankings(socnav1_root, tmp_path):
    """Each run records into a new temporary folder of its own (under TMPDIR here), so the
    second restores none of the first run's folded-in users, and sends its feedback once
    every ranking is in: the two runs print the same rankings, digit for digit; each draws
    its first scene for both people into that folder."""
    printed = []
    for _ in range(2):
        demo = subprocess.run([sys.executable, '-m', 'stars_ros.examples.demo',  # the packaged model, as a user runs it
                               '--data-root', str(socnav1_root), '--scenes', '3', '--placements', '3', '--rate', '10',
                               '--domain-id', str(domain_id(5))], env=dict(ros_env(domain_id(5)), TMPDIR=str(tmp_path)),
                              capture_output=True, text=True, timeout=240)
        assert demo.returncode == 0, demo.stdout + demo.stderr
        assert re.search(r"People: '[a-l]' and '[a-l]'", demo.stdout)
        assert demo.stdout.count('scene ') == 3 and 'Summary: 6 rankings' in demo.stdout
        assert '7 rankings (the typed one included) and 6 feedback ratings read back from MCAP. Ranker exit code 0.' \
            in demo.stdout
        gap = re.search(r'^Typed service /ranker/rank_candidates .*\(largest difference from the JSON ranking above: '
                        r'(\S+)\)$', demo.stdout, re.MULTILINE)
        assert gap and float(gap.group(1)) < 1e-6  # the JSON one may share a float32 batch with others: 1e-8 seen
        picture = re.search(r'Picture \(both people, [^)]+\): (\S+\.png)$', demo.stdout, re.MULTILINE)
        assert picture and open(picture.group(1), 'rb').read(8) == b'\x89PNG\r\n\x1a\n'
        printed.append([line for line in demo.stdout.splitlines() if line.startswith(('scene ', '  '))])
    assert len(printed[0]) == 9 and printed[0] == printed[1]
    people_lines = [line for k, line in enumerate(printed[0]) if k % 3]
    assert all(re.fullmatch(r'  +[a-l]: (\w+ -?\d\.\d{3,5}( > )?){3}', line) for line in people_lines), people_lines
    assert len(list(tmp_path.glob('stars_demo_*/records/stars_*'))) == 2


# -- nodes of their own ------------------------------------------------------------------------
@pytest.mark.socnav1
def test_the_packaged_model_ranks_socnav1_scenes_as_its_predictor_does(socnav1, socnav1_root, tmp_path):
    """Real data end to end: the ranker with its default checkpoint (the packaged model,
    trained on these SocNav1 files) ranks SocNav1 scenes, and placements of one, for an
    annotator and a stranger, as a Predictor on the same file does."""
    predictor = Predictor.load(resolve_checkpoint(''))
    assert predictor.metadata['data']['fingerprint'] == socnav1.fingerprint
    scenes = read_scenes(socnav1_root / 'raw' / 'g.jsonl')[:10]
    domain = domain_id(7)
    client = RosClient(domain)
    process = start_node('stars_ros.ros.ranker', domain, {'record_folder': tmp_path}, tmp_path / 'ranker.log')

    def reply(scene_id, user):
        return next((r for r in client.snapshot(client.rankings) if r['scene_id'] == scene_id and r['user_id'] == user),
                    None)
    try:
        client.wait_ready(process, START_TIMEOUT, _probe(scenes))
        placements = scene_request('placements', scenes[0], placements=4)
        for user in ('g', 'stranger'):  # scene ids are the identifiers: the scenes' q_i and b_i apply
            for scene in scenes:
                client.scene({'scene_id': scene['identifier'], 'user_id': user, 'graph': scene})
            client.scene({**placements, 'user_id': user})
        wanted = [(identifier, user) for user in ('g', 'stranger')
                  for identifier in [s['identifier'] for s in scenes] + ['placements']]
        assert client.wait(lambda: all(reply(*pair) for pair in wanted), 60)
        for user in ('g', 'stranger'):
            for scene in scenes:
                served = reply(scene['identifier'], user)
                assert served['fingerprint'] == predictor.fingerprint and served['known_user'] is (user == 'g')
                _assert_same(served, predictor.rank(user, scene, scene_id=scene['identifier']))
            _assert_same(reply('placements', user), predictor.rank_scenes(
                user, [c['graph'] for c in placements['candidates']],
                labels=[c['candidate'] for c in placements['candidates']]), key='candidate')
        assert stop(process, signal.SIGINT) == 0
    finally:
        if process.poll() is None:
            process.kill()
        client.close()


@pytest.mark.parametrize('signal_number', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
def test_clean_shutdown_closes_the_bag_with_feedback_and_latched_user(signal_number, tiny_checkpoint, scenes,
                                                                       tmp_path):
    domain = domain_id(1 if signal_number == signal.SIGINT else 2)
    client = RosClient(domain)
    client.user_pub.publish(String(data=KNOWN_USER))
    process = start_node('stars_ros.ros.ranker', domain, {'checkpoint': tiny_checkpoint, 'record_folder': tmp_path},
                         tmp_path / 'ranker.log')  # starts after the user id was published
    try:
        client.wait_ready(process, START_TIMEOUT, _probe(scenes))
        # the latched id comes over its own topic, whose endpoints may match after stars/scene's
        assert _served_latched_user(client, scenes), 'the user id latched before the node started never arrived'
        for k in range(5):
            client.scene({'scene_id': f's{k}', 'graph': scenes[k]})
        feedback = {'user_id': KNOWN_USER, 'scene_id': 's1', 'action': 'navigate', 'score': 0.75}
        client.feedback(feedback)
        assert client.wait(lambda: all(client.ranking_for(f's{k}') for k in range(5)), 30)
        assert client.ranking_for('s0')['user_id'] == KNOWN_USER  # latched before the node existed
        bag = next(tmp_path.glob('stars_*'))
        assert wait_for(lambda: stored_feedback(bag) == [feedback], 10), 'the feedback was never stored'
        assert stop(process, signal_number) == 0
    finally:
        if process.poll() is None:
            process.kill()
        client.close()
    assert 'Failed to publish log message' not in (tmp_path / 'ranker.log').read_text()  # a clean stop logs no error
    assert not (bag / recording.PID_FILE).exists()
    assert all(recording.is_finished(f) for f in bag.glob('*.mcap'))
    messages = list(recording.read_messages(bag))
    topics = {t for t, _, _ in messages}
    assert {'/stars/scene', '/stars/ranking', '/stars/user_id', '/stars/feedback'} <= topics
    assert [json.loads(m) for t, m, _ in messages if t == '/stars/feedback'] == [feedback]
    recorded = {json.loads(m)['scene_id']: json.loads(m) for t, m, _ in messages if t == '/stars/ranking'}
    assert recorded['s3'] == client.ranking_for('s3')

    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    with Reader(bag) as reader:
        read = [(c.topic, store.deserialize_cdr(raw, c.msgtype)) for c, _, raw in reader.messages()]
        qos = {c.topic: c.ext.offered_qos_profiles for c in reader.connections}
    texts = [(topic, message.data) for topic, message in read if topic != '/stars/markers']
    assert ('/stars/feedback', json.dumps(feedback)) in texts and len(texts) == len(messages)
    markers = [message for topic, message in read if topic == '/stars/markers']  # one MarkerArray a ranking (a
    rankings = [m for t, m, _ in messages if t == '/stars/ranking']  # probe sent again is ranked again, same id)
    assert len(markers) == len(rankings) and all(m.markers[0].action == 3 for m in markers)  # DELETEALL first
    assert qos['/stars/user_id'][0].durability.name == 'TRANSIENT_LOCAL'
    info = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert info['message_count'] == len(messages) + len(markers)


@pytest.mark.slow
def test_hard_kill_then_recovery_keeps_everything_before_the_last_flush(tiny_checkpoint, scenes, tmp_path):
    domain = domain_id(3)
    client = RosClient(domain)
    process = start_node('stars_ros.ros.ranker', domain, {'checkpoint': tiny_checkpoint, 'record_folder': tmp_path,
                                                      'flush_interval': 0.2}, tmp_path / 'ranker.log')
    try:
        client.wait_ready(process, START_TIMEOUT, _probe(scenes))
        for k in range(20):
            client.scene({'scene_id': f's{k}', 'user_id': KNOWN_USER, 'graph': scenes[k]})
        assert client.wait(lambda: all(client.ranking_for(f's{k}') for k in range(20)), 30)
        bag = next(tmp_path.glob('stars_*'))
        assert wait_for(lambda: {f's{k}' for k in range(20)} <= {r['scene_id'] for r in _on_disk(
            bag, '/stars/ranking')}, 10), 'the rankings were never flushed'
        client.feedback({'user_id': KNOWN_USER, 'scene_id': 's2', 'candidate': 'left', 'score': 0.1})
        assert wait_for(lambda: stored_feedback(bag), 10), 'the feedback was never stored'
        process.kill()  # SIGKILL, right after the feedback was stored
        process.wait()
    finally:
        if process.poll() is None:
            process.kill()
        client.close()
    assert recording.abandoned_bags(tmp_path) == [bag]
    recording.recover(bag)
    messages = list(recording.read_messages(bag))
    rankings = {json.loads(m)['scene_id'] for t, m, _ in messages if t == '/stars/ranking'}
    assert {f's{k}' for k in range(20)} <= rankings
    assert [json.loads(m)['score'] for t, m, _ in messages if t == '/stars/feedback'] == [0.1]


def test_unwritable_record_folder_is_reported_and_ranking_goes_on(tiny_checkpoint, scenes, tmp_path):
    blocker = tmp_path / 'a-file'
    blocker.write_text('not a folder')
    domain = domain_id(4)
    client = RosClient(domain)
    process = start_node('stars_ros.ros.ranker', domain, {'checkpoint': tiny_checkpoint,
                                                      'record_folder': blocker / 'records', 'diagnostics_period': 0.3},
                         tmp_path / 'ranker.log')
    try:
        client.wait_ready(process, START_TIMEOUT, _probe(scenes))
        client.feedback({'user_id': KNOWN_USER, 'scene_id': 's', 'action': 'navigate', 'score': 0.5})
        assert client.wait(lambda: any(e['kind'] == 'recording' and e['topic'] == '/stars/feedback'
                                       for e in client.errors), 20)

        def recording_error():
            statuses = [s for d in client.diagnostics for s in d.status if s.name.endswith(': ranker')]
            values = statuses and {v.key: v.value for v in statuses[-1].values}
            return bool(values) and 'a-file' in values['recording'] and values['feedback_not_on_disk'] == '1'
        assert client.wait(recording_error, 10)
        client.scene({'scene_id': 'still-served', 'graph': scenes[2]})
        assert client.wait(lambda: client.ranking_for('still-served') is not None, 20)
        assert stop(process, signal.SIGTERM) == 0
    finally:
        if process.poll() is None:
            process.kill()
        client.close()
    assert "feedback that could not be stored: {'topic': '/stars/feedback'" in (tmp_path / 'ranker.log').read_text()


@pytest.mark.slow
def test_a_flood_beyond_queue_depth_is_refused_as_overload_and_serving_goes_on(tiny_checkpoint, scenes, tmp_path):
    """The scene callback drains what waits on stars/scene into a queue of at most
    queue_depth requests; beyond that a request is refused with an overload error, never
    both refused and ranked, and the node serves on."""
    domain = domain_id(6)
    client = RosClient(domain)
    process = start_node('stars_ros.ros.ranker', domain, {'checkpoint': tiny_checkpoint, 'record_folder': tmp_path,
                                                      'queue_depth': 20, 'max_batch': 1}, tmp_path / 'ranker.log')
    try:
        client.wait_ready(process, START_TIMEOUT, _probe(scenes))
        for k in range(1000):
            client.scene(json.dumps({'scene_id': f'flood-{k}', 'user_id': KNOWN_USER,
                                     'graph': scenes[k % len(scenes)]}))

        _settle(client, scenes)  # ranked once the queue has room again: the node served on
        ranked, refused = _answers(client, 'flood-')
        overloaded = [e['scene_id'] for e in client.errors if e['kind'] == 'overload']
        assert ranked and refused and refused == [s for s in overloaded if s.startswith('flood-')], (
            len(ranked), len(refused))
        assert len(set(ranked)) == len(ranked) and len(set(refused)) == len(refused)
        assert not set(ranked) & set(refused)
        assert process.poll() is None
    finally:
        if process.poll() is None:
            process.kill()
        client.close()
