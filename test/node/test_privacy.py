"""Issue 49's fleet forget, replay memory, consent and retention without ROS: a forget told to
a peer in a message that does not hold the id, signed, which the peer applies to its memory,
store and bags and whose tombstone refuses a later model (also of a person it never met, and
after a restart); the authenticator's replay memory lets the forgotten person's MACs go;
store_policy consented keeps nobody else; retention_days erases old ratings on an injected
clock. test/ros/test_privacy_node.py runs the fleet forget over DDS."""
import itertools
import json

import pytest

from stars_ros import feedback_auth, messages, recording, state
from stars_ros.data.scene_source import read_scenes, scene_request
from stars_ros.errors import ConfigError
from stars_ros.node.core import RankerCore
from stars_ros.node.parameters import PARAMETERS, TOPICS
from core_harness import Node, deliver, drain, published_models, woken_and_drained
from forget_search import bag_records, holds, store_bytes
from waiting import wait_for

SECRET = bytes(range(32))
T0 = 1_700_000_000 * 10 ** 9
DAY = 86400 * 10 ** 9
RATED = itertools.count()


class Clock:
    """ROS time as a test sets it."""

    def __init__(self, now=T0):
        self.now = now

    def __call__(self):
        return self.now


@pytest.fixture(scope='module')
def scenes(synthetic_root):
    return read_scenes(synthetic_root / 'raw' / 'h.jsonl')[:4]


@pytest.fixture
def key_file(tmp_path):
    path = tmp_path / 'keys.txt'
    path.write_text(f'fleet:{SECRET.hex()}\n')
    path.chmod(0o600)
    return str(path)


def robot(checkpoint, folder, name, clock, **params):
    node = Node()
    values = {n: spec[0] for n, spec in PARAMETERS.items()}
    values.update({'checkpoint': str(checkpoint), 'record_folder': str(folder) if folder else '',
                   'flush_interval': 60.0, **params})
    core = RankerCore(values, {topic: f'/{name}/{topic}' for topic in TOPICS}, f'/{name}/ranker', node.publish, node,
                      clock, wake=node.woken.set)
    return node, core


def rate(core, scene, user, score, signed=False):
    """Rank ``scene`` for ``user`` and give feedback on it (signed by the fleet key)."""
    scene_id = f"{scene['identifier']}-{next(RATED)}"  # not named after the person: a search finds them only
    core.accept_scene(messages.dumps(scene_request(scene_id, scene, user)), 0)
    drain(core)
    fields = {'user_id': user, 'scene_id': scene_id, 'action': 'navigate', 'score': score}
    if signed:
        fields = feedback_auth.sign(fields, 'fleet', SECRET, core._now())
    accepted = core.accept_feedback(json.dumps(fields))
    drain(core)
    return accepted


def models_out(node, core, want: dict) -> list:
    """The stars/user_model texts ``node`` published, once they hold {user: n_ratings} (a
    model goes out when the store has committed its ratings: the store's thread wakes the
    executor, which sends it)."""
    assert wait_for(lambda: (woken_and_drained(node, core) or True) and want.items() <= {
        (m['user_id'], m['n_ratings']) for m in node.on('stars/user_model')}, 30), 'models not published'
    return published_models(node)


def recorded(folder) -> list:
    """(topic, payload) of every JSON message the bags of ``folder`` hold."""
    found = []
    for bag in (p for p in folder.iterdir() if p.is_dir() and list(p.glob('*.mcap'))):
        for topic, decoded, _ in recording.read_decoded(bag):
            data = getattr(decoded, 'data', None)
            if isinstance(data, str) and data.startswith('{'):
                found.append((topic.rsplit('/', 1)[-1], json.loads(data)))
    return found


def errors(node, kind):
    return [e for e in node.on('stars/errors') if e['kind'] == kind]


def folder_holds(folder, user_id, others=()) -> bool:
    return any(holds(data, user_id, others) for data in [*store_bytes(folder).values(), *bag_records(folder)])


def test_a_forget_reaches_a_peer_without_the_id_and_a_later_model_is_refused(tiny_checkpoint, scenes, tmp_path,
                                                                              key_file):
    clock = Clock()
    node_a, robot_a = robot(tiny_checkpoint, tmp_path / 'a', 'robot_a', clock, fleet_sharing=True,
                            feedback_key_file=key_file)
    node_b, robot_b = robot(tiny_checkpoint, tmp_path / 'b', 'robot_b', clock, fleet_sharing=True,
                            feedback_key_file=key_file)
    for n, scene in enumerate(scenes[:3]):
        assert rate(robot_a, scene, 'walker', 0.2 + 0.3 * n, signed=True)
        assert rate(robot_a, scene, 'runner', 0.9 - 0.3 * n, signed=True)
    models = models_out(node_a, robot_a, {'walker': 3, 'runner': 3})
    deliver(models, robot_b)
    assert robot_b.predictor.user_model('walker') is not None
    assert wait_for(lambda: any(holds(data, 'walker') for data in store_bytes(tmp_path / 'b').values()), 30)
    runner_before = robot_b.predictor.user_model('runner').p.copy()

    removed = robot_a.forget_person('walker')
    assert removed['memory']['replay_memory'] == 3  # the MACs of their feedback, let go
    [forget] = node_a.on('stars/forget_person')
    text = json.dumps(forget)
    assert 'walker' not in text and forget['auth']['key_id'] == 'fleet'

    unsigned = json.dumps({k: v for k, v in forget.items() if k != 'auth'})
    assert robot_b.accept_forget_message(unsigned) == 0  # with keys set, an unsigned forget is refused
    assert errors(node_b, 'auth') and robot_b.predictor.user_model('walker') is not None

    assert robot_b.accept_forget_message(text) == 1
    assert robot_b.predictor.user_model('walker') is None
    assert (robot_b.predictor.user_model('runner').p == runner_before).all()  # everyone else as they were

    assert robot_a.accept_forget_message(text) == 0  # its own message changes nothing
    deliver(models, robot_b)  # the models a late message brings again: the forgotten one refused
    assert errors(node_b, 'forgotten') and robot_b.predictor.user_model('walker') is None
    assert not any('walker' in e['message'] for e in node_b.on('stars/errors'))
    robot_b.close()
    assert not folder_holds(tmp_path / 'b', 'walker')
    assert folder_holds(tmp_path / 'b', 'runner')
    node_b, robot_b = robot(tiny_checkpoint, tmp_path / 'b', 'robot_b', clock, fleet_sharing=True,
                            feedback_key_file=key_file)
    deliver(models, robot_b)  # after a restart too
    assert errors(node_b, 'forgotten') and robot_b.predictor.user_model('walker') is None
    assert robot_b.predictor.user_model('runner') is not None
    robot_a.close()
    robot_b.close()


def test_a_peer_that_never_met_the_person_keeps_the_tombstone(tiny_checkpoint, scenes, tmp_path):
    """Without keys the forget goes unsigned (a salted hash of the id); a peer that never
    met the person refuses their model once told, and after a restart."""
    clock = Clock()
    node_a, robot_a = robot(tiny_checkpoint, tmp_path / 'a', 'robot_a', clock, fleet_sharing=True)
    node_c, robot_c = robot(tiny_checkpoint, tmp_path / 'c', 'robot_c', clock, fleet_sharing=True)
    assert rate(robot_a, scenes[0], 'walker', 0.9)
    models = models_out(node_a, robot_a, {'walker': 1})
    robot_a.forget_person('walker')
    [forget] = node_a.on('stars/forget_person')
    assert 'auth' not in forget and 'walker' not in json.dumps(forget)
    assert robot_c.accept_forget_message(json.dumps(forget)) == 0  # nobody held, the tombstone kept
    robot_c.close()
    node_c, robot_c = robot(tiny_checkpoint, tmp_path / 'c', 'robot_c', clock, fleet_sharing=True)
    deliver(models, robot_c)
    assert errors(node_c, 'forgotten') and robot_c.predictor.user_model('walker') is None
    assert not rate(robot_c, scenes[1], 'walker', 0.5)  # their feedback too
    robot_a.close()
    robot_c.close()


def test_a_malformed_forget_is_reported_and_changes_nothing(tiny_checkpoint, scenes, tmp_path):
    node, core = robot(tiny_checkpoint, tmp_path / 'a', 'robot_a', Clock(), fleet_sharing=True)
    assert rate(core, scenes[0], 'walker', 0.9)
    for text in ('{', json.dumps({'tag': 'walker', 'salt': '00' * 16, 'origin': '/x'}),
                 json.dumps({'tag': '0' * 64, 'salt': '00' * 16, 'origin': '/x', 'user_id': 'walker'})):
        assert core.accept_forget_message(text) == 0
    assert len(errors(node, 'schema')) == 2 and errors(node, 'malformed_json')
    assert core.predictor.user_model('walker') is not None
    core.close()


def test_store_policy_consented_keeps_nobody_else(tiny_checkpoint, scenes, tmp_path):
    consent = tmp_path / 'consent.txt'
    consent.write_text('# agreed on the tablet\nann\n')
    folder = tmp_path / 'robot'
    node, core = robot(tiny_checkpoint, folder, 'robot', Clock(), store_policy='consented',
                       consent_file=str(consent), fleet_sharing=True)
    assert rate(core, scenes[0], 'ann', 0.9)
    assert not rate(core, scenes[1], 'bob', 0.1)  # not on the list: refused, not stored
    assert errors(node, 'consent') and not any('bob' in e['message'] for e in errors(node, 'consent'))
    assert core.predictor.user_model('bob') is None
    ranking = core.rank_now(messages.dumps(scene_request('later', scenes[2], 'bob')), 0)[0]
    drain(core)  # recorded now
    assert ranking['user_id'] == 'bob' and 'personalised_from' not in ranking  # served as a stranger
    core.accept_user_id('bob')
    peer = dict(json.loads(models_out(node, core, {'ann': 1})[0]), user_id='carl', origin='/peer/ranker')
    assert not core.accept_user_model(json.dumps(peer))  # a peer's model of someone without consent
    assert len(errors(node, 'consent')) == 2
    core.accept_consent(json.dumps({'consented': ['bob']}))  # the consent flow adds bob
    assert rate(core, scenes[3], 'bob', 0.2)
    core.accept_consent('{"consented": "bob"}')
    assert errors(node, 'schema') and core.consent.allows('bob')  # a bad list changes nothing
    core.close()
    with state.open_reader(folder) as reader:
        assert {p['person'] for p in reader.summary()} == {'ann', 'bob'}
        assert [json.loads(e['data'])['user_id'] for e in reader.feedback()] == ['ann', 'bob']
    kept = recorded(folder)
    named = {(topic, payload.get('scene_id')) for topic, payload in kept if payload.get('user_id') == 'bob'}
    assert ('scene', 'later') not in named and ('ranking', 'later') not in named
    assert any(payload.get('scene_id') == 'later' for _, payload in kept)  # recorded, without his id
    assert {topic for topic, _ in named} >= {'scene', 'ranking', 'feedback'}  # once he agreed
    assert not any(holds(data, 'carl') for data in [*store_bytes(folder).values(), *bag_records(folder)])
    assert not any(holds(data, 'bob') for data in bag_records(folder) if b'"user_id":"bob"' not in data
                   and b'later' in data)


def test_a_bad_store_policy_or_consent_file_stops_the_start(tiny_checkpoint, tmp_path):
    with pytest.raises(ConfigError, match='store_policy'):
        robot(tiny_checkpoint, None, 'robot', Clock(), store_policy='some')
    with pytest.raises(ConfigError, match='consent_file'):
        robot(tiny_checkpoint, None, 'robot', Clock(), store_policy='consented', consent_file=str(tmp_path / 'no'))


def test_retention_erases_old_ratings_everywhere(tiny_checkpoint, scenes, tmp_path):
    clock, folder = Clock(), tmp_path / 'robot'
    node, core = robot(tiny_checkpoint, folder, 'robot', clock)
    assert rate(core, scenes[0], 'old-only', 0.9)
    assert rate(core, scenes[0], 'both', 0.1)
    models_out(node, core, {'old-only': 1, 'both': 1})  # their models are logged at T0 too
    clock.now += 3 * DAY
    assert rate(core, scenes[1], 'both', 0.8)
    assert rate(core, scenes[2], 'recent', 0.4)
    assert core.apply_retention() == {}  # retention_days 0: nothing goes
    core.params['retention_days'] = 2.0
    removed = core.apply_retention()
    assert removed['memory'] == {'ratings': 2, 'peer_ratings': 0, 'people': 1}
    assert removed['state_store']['journal'] == 2  # their rows went with the people written just before
    assert sum(removed['bags'].values()) > 0
    drain(core)
    assert core.predictor.user_model('old-only') is None
    assert core.predictor.user_model('both').n_ratings == 1 and core.predictor.user_model('recent') is not None
    core.close()
    with state.open_reader(folder) as reader:
        assert {p['person']: p['ratings'] for p in reader.summary()} == {'both': 1, 'recent': 1}
        assert all(e['log_time'] >= T0 + 3 * DAY for e in reader.feedback())
    assert not folder_holds(folder, 'old-only')
    for bag in (p for p in folder.iterdir() if p.is_dir() and list(p.glob('*.mcap'))):
        assert all(log_time >= T0 + DAY for _, _, log_time in recording.read_decoded(bag))
    _, core = robot(tiny_checkpoint, folder, 'robot', clock, retention_days=2.0)  # a restart runs a pass
    assert core.predictor.user_model('both') is not None and core.predictor.user_model('old-only') is None
    core.close()
