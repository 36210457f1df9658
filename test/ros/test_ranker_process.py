"""The ranker as a process: the demo and the packaged model end to end, a clean shutdown on
SIGINT/SIGTERM, a hard kill and recovery, an unwritable record folder and a flood beyond the
queue. Each test starts a ranker of its own: the process is its subject."""
import json
import re
import signal
import subprocess
import sys

import pytest
import yaml

from std_msgs.msg import String

from ranker_harness import predictor, scenes  # noqa: F401 - the fixtures
from ranker_harness import KNOWN_USER, START_TIMEOUT, answers, assert_same, probe_request, served_latched_user, settle
from ros_helpers import RosClient, domain_id, stored_feedback, ros_env, start_node, stop
from waiting import wait_for
from stars_ros import recording
from stars_ros.model.predictor import Predictor
from stars_ros.data.scene_source import read_scenes, scene_request
from stars_ros.resources import resolve_checkpoint

pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning:lark.*')  # rclpy's parameter client


def _on_disk(bag, topic) -> list:
    """The ``topic`` messages the bag's MCAP files hold on disk now, read as a hard kill
    would leave them (complete records only)."""
    return [json.loads(text) for path in recording.bag_files(bag)
            for found, text, _ in recording.salvage_messages(path)[0] if found == topic]


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
        client.wait_ready(process, START_TIMEOUT, probe_request(scenes))
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
                assert_same(served, predictor.rank(user, scene, scene_id=scene['identifier']))
            assert_same(reply('placements', user), predictor.rank_scenes(
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
        client.wait_ready(process, START_TIMEOUT, probe_request(scenes))
        # the latched id comes over its own topic, whose endpoints may match after stars/scene's
        assert served_latched_user(client, scenes), 'the user id latched before the node started never arrived'
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
        client.wait_ready(process, START_TIMEOUT, probe_request(scenes))
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
        client.wait_ready(process, START_TIMEOUT, probe_request(scenes))
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
        client.wait_ready(process, START_TIMEOUT, probe_request(scenes))
        for k in range(1000):
            client.scene(json.dumps({'scene_id': f'flood-{k}', 'user_id': KNOWN_USER,
                                     'graph': scenes[k % len(scenes)]}))

        settle(client, scenes)  # ranked once the queue has room again: the node served on
        ranked, refused = answers(client, 'flood-')
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
