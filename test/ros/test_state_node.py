"""The ranker's state store with the node running for real: SIGKILLed at random moments of
a feedback stream, round after round on one record folder, it keeps every feedback message
it had stored (what it counts as accepted), each once, serves every person the model of all
their stored ratings after the restart, and every person whose model it had published on
stars/user_model comes back with at least the ratings that model was solved from; the bags
hold the stored feedback, each once; a second ranker on a folder another holds is refused at
start, naming the holder."""
import json
import random
import signal
import time

import pytest

import ros_helpers
from ros_helpers import RosClient, domain_id, start_node, stop, stored_feedback
from waiting import wait_for
from stars_ros import recording, state

pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning:lark.*')  # rclpy's parameter handling
START_TIMEOUT = 90
PEOPLE = [f'person-{k}' for k in range(6)]
ROUNDS = 3


@pytest.fixture(scope='module')
def scenes(synthetic_scenes):
    return synthetic_scenes


def _start(domain, checkpoint, folder, log):
    return start_node('stars_ros.ros.ranker', domain, {'checkpoint': checkpoint, 'record_folder': folder,
                                                      'flush_interval': 0.2}, log)


def _stored(folder) -> list:
    """Every feedback message the store in ``folder`` has committed, as text, in commit order."""
    with state.open_reader(folder) as store:
        return [entry['data'] for entry in store.feedback()]


def _rank_all(client, scenes, tag):
    for person in PEOPLE:
        client.scene({'scene_id': f'{tag}-{person}', 'user_id': person, 'graph': scenes[0]})
    assert client.wait(lambda: all(client.ranking_for(f'{tag}-{p}') for p in PEOPLE), 30)
    return {p: client.ranking_for(f'{tag}-{p}').get('personalised_from', 0) for p in PEOPLE}


@pytest.mark.slow
def test_sigkill_during_feedback_keeps_every_stored_message_once(tiny_checkpoint, scenes, tmp_path):
    domain = domain_id(16)
    rng = random.Random(25)
    client = RosClient(domain)
    published = client.collect('/stars/user_model', ros_helpers.RELIABLE)  # what anybody could see
    acknowledged = []  # stored before a kill: the node had counted them as accepted
    sent = 0
    process = None
    try:
        for round_ in range(ROUNDS + 1):
            process = _start(domain, tiny_checkpoint, tmp_path, tmp_path / f'ranker-{round_}.log')
            client.wait_ready(process, START_TIMEOUT, {'scene_id': f'probe-{round_}', 'graph': scenes[0]})
            stored = _stored(tmp_path)
            assert set(acknowledged) <= set(stored), 'feedback the node had stored is gone'
            assert len(stored) == len(set(stored)), 'feedback stored twice'
            expected = {p: sum(json.loads(text)['user_id'] == p for text in stored) for p in PEOPLE}
            seen = {m['user_id']: max(n['n_ratings'] for n in published if n['user_id'] == m['user_id'])
                    for m in list(published)}
            assert all(expected[person] >= n for person, n in seen.items()), (seen, expected)
            # each person's model is solved from every stored rating (restored, or solved again)
            assert wait_for(lambda: _rank_all(client, scenes, f'check-{round_}-{time.monotonic_ns()}') == expected,
                            60), (expected, _rank_all(client, scenes, f'last-{round_}'))
            if round_ == ROUNDS:
                break
            rated = [f'r{round_}-s{k}' for k in range(8)]  # feedback names scenes this run ranked
            for k, scene_id in enumerate(rated):
                client.scene({'scene_id': scene_id, 'graph': scenes[k + 1]})
            assert client.wait(lambda: all(client.ranking_for(s) for s in rated), 30)
            for _ in range(rng.randint(20, 150)):  # then SIGKILL, with some of them still on their way
                sent += 1
                client.feedback({'user_id': rng.choice(PEOPLE), 'scene_id': rng.choice(rated), 'action': 'navigate',
                                 'score': sent / 1000})
            bag = next(b for b in tmp_path.glob('stars_*') if (b / recording.PID_FILE).exists())
            if rng.random() < 0.5:  # sometimes after a first message is stored, sometimes at once
                wait_for(lambda: bool(stored_feedback(bag)), 20)
            acknowledged = _stored(tmp_path)
            process.kill()
            process.wait()
        assert stop(process, signal.SIGINT) == 0
    finally:
        if process is not None and process.poll() is None:
            process.kill()
        client.close()
    stored = _stored(tmp_path)
    assert 0 < len(stored) <= sent
    assert published, 'no model was published: nothing seen to check'
    in_bags = [text for bag in sorted(tmp_path.glob('stars_*'))
               for topic, text, _ in recording.read_messages(bag) if topic == '/stars/feedback']
    assert sorted(in_bags) == sorted(stored)  # the log of record: every stored message, once


@pytest.mark.slow
def test_a_second_ranker_on_a_held_folder_is_refused_naming_the_holder(tiny_checkpoint, scenes, tmp_path):
    domain = domain_id(17)
    client = RosClient(domain)
    first = _start(domain, tiny_checkpoint, tmp_path, tmp_path / 'first.log')
    second = None
    try:
        client.wait_ready(first, START_TIMEOUT, {'scene_id': 'probe', 'graph': scenes[0]})
        second = start_node('stars_ros.ros.ranker', domain, {'checkpoint': tiny_checkpoint, 'record_folder': tmp_path},
                            tmp_path / 'second.log', ros_args=['-r', '__ns:=/robot2'])
        assert second.wait(timeout=START_TIMEOUT) == 1
        log = (tmp_path / 'second.log').read_text()
        assert f'the state store in {tmp_path} is held by /ranker (pid {first.pid} on ' in log, log
        assert len(list(tmp_path.glob('stars_*'))) == 1  # the refused node recorded nothing
        assert stop(first, signal.SIGINT) == 0
    finally:
        for process in (first, second):
            if process is not None and process.poll() is None:
                process.kill()
        client.close()
