"""Signed feedback without ROS: the key file, the signed form (a fixed vector), and a ranker
with ``feedback_key_file`` set refusing unsigned, wrongly signed, unknown-key, stale, future,
replayed and malformed feedback (kind auth, no model changed, nothing journaled) while
folding in signed feedback exactly as an unsigned ranker does; key rotation; a fuzz of the
signed message; replay across a restart; forged peer models under fleet sharing; the
signer command. test_feedback_auth_node.py checks signed feedback over DDS."""
import copy
import hashlib
import hmac
import json
import random
import subprocess
import sys

import numpy as np
import pytest

from mutations import mutate
from stars_ros import feedback_auth, messages, recording
from stars_ros.data.scene_source import scene_request
from stars_ros.errors import ConfigError, OutOfScaleError
from stars_ros.model.predictor import Predictor
from stars_ros.node.core import RankerCore
from stars_ros.node.parameters import PARAMETERS, TOPICS
from core_harness import Node, deliver, drain, published_models

USER = 'visitor'
SECRET_A, SECRET_B = bytes(range(32)), bytes(range(100, 132))
T0 = 1_700_000_000 * 10 ** 9  # the tests' ROS time (ns)
SECOND = 10 ** 9


class Clock:
    """ROS time as the tests set it."""

    def __init__(self, now=T0):
        self.now = now

    def __call__(self):
        return self.now


@pytest.fixture
def key_file(tmp_path):
    path = tmp_path / 'keys.txt'
    path.write_text(f'# tablet keys\nold:{SECRET_A.hex()}\n\nnew:{SECRET_B.hex()}\n')
    path.chmod(0o600)
    return path


def _robot(checkpoint, clock, name='ranker', **params):
    node = Node()
    values = {n: spec[0] for n, spec in PARAMETERS.items()}
    values.update({'checkpoint': str(checkpoint), 'record_folder': '', 'flush_interval': 0.01, **params})
    values = {k: str(v) if k in ('feedback_key_file', 'record_folder') else v for k, v in values.items()}
    core = RankerCore(values, {topic: f'/{name}/{topic}' for topic in TOPICS}, f'/{name}/ranker', node.publish,
                      node, clock)
    return node, core



def _rank(core, scene, user=USER):
    core.accept_scene(messages.dumps(scene_request(scene['identifier'], scene, user)), 0)
    drain(core)


def _feedback(scene, score=0.8, user=USER):
    return {'user_id': user, 'scene_id': scene['identifier'], 'action': 'navigate', 'score': score}


def _signed(fields, key_id='new', secret=SECRET_B, stamp=T0):
    return json.dumps(feedback_auth.sign(fields, key_id, secret, stamp))


def _errors(node, kind='auth'):
    return [e for e in node.on('stars/errors') if e['kind'] == kind]


def _served(core, user=USER):
    model = core.predictor.user_model(user)
    return None if model is None else np.append(model.p, model.b)


def test_the_signed_form_is_hmac_sha256_of_the_sorted_compact_fields_and_stamp():
    fields = {'user_id': 'alice', 'score': 0.9, 'scene_id': 's1', 'action': 'navigate'}
    canonical = b'{"action":"navigate","scene_id":"s1","score":0.9,"stamp":5,"user_id":"alice"}'
    assert feedback_auth.canonical({**fields, 'auth': {'ignored': 1}}, 5) == canonical
    signed = feedback_auth.sign(fields, 'tablet', SECRET_A, 5)
    assert signed['auth'] == {'key_id': 'tablet', 'stamp': 5,
                              'mac': hmac.new(SECRET_A, canonical, hashlib.sha256).hexdigest()}
    assert {k: v for k, v in signed.items() if k != 'auth'} == fields
    assert messages.parse_feedback(json.dumps(signed)).signed == signed
    docs_vector = {'user_id': 'alice', 'scene_id': 's1', 'action': 'navigate', 'score': 0.8}  # docs/security.md
    assert feedback_auth.mac(bytes(range(32)), docs_vector, 1_700_000_000_000_000_000) == (
        'f92ff2d26c8b0fcdd01ef546cb590251f34ac754ca1f931cd27a362ff2dce582')


def test_key_files_take_comments_and_several_keys_and_name_a_bad_line_without_its_secret(key_file, tmp_path):
    assert feedback_auth.load_keys(key_file) == {'old': SECRET_A, 'new': SECRET_B}
    bad = {'no colon': 'justtext', 'bad id': f'a b:{SECRET_A.hex()}', 'not hex': 'k:' + 'zz' * 16,
           'short': 'k:' + 'ab' * 15, 'twice': f'k:{SECRET_A.hex()}\nk:{SECRET_B.hex()}', 'empty': '# none'}
    for case, text in bad.items():
        path = tmp_path / 'bad.txt'
        path.write_text(text + '\n')
        with pytest.raises(ConfigError) as raised:
            feedback_auth.load_keys(path)
        assert 'zz' * 16 not in str(raised.value) and SECRET_B.hex() not in str(raised.value), case
    with pytest.raises(ConfigError, match='cannot be read'):
        feedback_auth.load_keys(tmp_path / 'missing.txt')


def test_without_a_key_file_feedback_is_taken_as_today_with_one_warning(tiny_checkpoint, synthetic_scenes):
    node, core = _robot(tiny_checkpoint, Clock())
    assert [line for level, line in node.lines if level == 'warning' and 'feedback_key_file' in line] == [
        'feedback_key_file is empty: feedback is not authenticated, anyone who reaches the ROS domain can rate for '
        'any person (docs/security.md)']
    _rank(core, synthetic_scenes[0])
    assert core.accept_feedback(json.dumps(_feedback(synthetic_scenes[0]))) is True
    core.close()


def test_a_key_file_that_cannot_be_used_stops_the_node_and_an_open_one_is_warned_about(tiny_checkpoint, tmp_path,
                                                                                         key_file):
    (tmp_path / 'bad.txt').write_text('k:abc\n')
    with pytest.raises(ConfigError, match='line 1'):
        _robot(tiny_checkpoint, Clock(), feedback_key_file=tmp_path / 'bad.txt')
    key_file.chmod(0o644)
    node, core = _robot(tiny_checkpoint, Clock(), feedback_key_file=key_file)
    assert any('readable by its group or others' in line for level, line in node.lines if level == 'warning')
    assert not any('not authenticated' in line for _, line in node.lines)
    core.close()


def test_forged_feedback_is_refused_as_auth_journals_nothing_and_changes_no_model(tiny_checkpoint, synthetic_scenes,
                                                                                  key_file, tmp_path):
    clock = Clock()
    node, core = _robot(tiny_checkpoint, clock, feedback_key_file=key_file, record_folder=tmp_path / 'records')
    scene = synthetic_scenes[0]
    _rank(core, scene)
    fields = _feedback(scene)
    good = feedback_auth.sign(fields, 'new', SECRET_B, T0)
    forged = {
        'unsigned': json.dumps(fields),
        'wrong MAC': json.dumps({**good, 'auth': {**good['auth'], 'mac': '0' * 64}}),
        'changed score': json.dumps({**good, 'score': 0.1}),
        'another person': json.dumps({**good, 'user_id': 'someone-else'}),
        'unknown key': _signed(fields, 'stranger', SECRET_B),
        'wrong secret': _signed(fields, 'new', SECRET_A),
        'stale': _signed(fields, stamp=T0 - 61 * SECOND),
        'future': _signed(fields, stamp=T0 + 61 * SECOND),
        'malformed': json.dumps({**fields, 'auth': 'signed'}),
        'uppercase MAC': json.dumps({**good, 'auth': {**good['auth'], 'mac': good['auth']['mac'].upper()}}),
        'extra auth field': json.dumps({**good, 'auth': {**good['auth'], 'note': 1}}),
        'stamp as text': json.dumps({**good, 'auth': {**good['auth'], 'stamp': str(T0)}}),
    }
    for case, text in forged.items():
        assert core.accept_feedback(text) is False, case
        assert len(_errors(node)) == list(forged).index(case) + 1, case
    assert not core.personalisation.pending and core.personalisation.histories.ratings(USER) == []
    drain(core)
    assert _served(core) is None and not node.on('stars/user_model')
    reasons = [e['message'] for e in _errors(node)]
    assert all(e['topic'] == '/ranker/stars/feedback' and e['level'] == 'error' for e in _errors(node))
    for reason, expected in zip(reasons, ['not signed', 'wrong MAC', 'wrong MAC', 'wrong MAC', 'unknown key id',
                                          'wrong MAC', 's ago', 'in the future', 'malformed auth', 'malformed auth',
                                          'malformed auth', 'malformed auth']):
        assert expected in reason, reason
    assert core.diagnostics()[2]['errors.auth'] == len(forged)
    assert core.accept_feedback(json.dumps(good)) is True
    assert core.accept_feedback(json.dumps(good)) is False and 'a replay' in _errors(node)[-1]['message']
    core.close()
    recorded = [(topic, text) for topic, text, _ in recording.read_messages(core.recorder.path)]
    assert [text for topic, text in recorded if topic == '/ranker/stars/feedback'] == [json.dumps(good)]
    refusals = [text for topic, text in recorded if topic == '/ranker/stars/errors' and '"kind":"auth"' in text]
    assert len(refusals) == len(forged) + 1


def test_the_window_is_feedback_max_age_either_side_and_a_replay_within_it_is_refused(tiny_checkpoint,
                                                                                    synthetic_scenes, key_file):
    clock = Clock()
    node, core = _robot(tiny_checkpoint, clock, feedback_key_file=key_file, feedback_max_age=5.0)
    scenes = synthetic_scenes[:4]
    for scene in scenes:
        _rank(core, scene)
    assert core.accept_feedback(_signed(_feedback(scenes[0]), stamp=T0 - 5 * SECOND)) is True  # at the edge
    assert core.accept_feedback(_signed(_feedback(scenes[1]), stamp=T0 + 5 * SECOND)) is True
    assert core.accept_feedback(_signed(_feedback(scenes[2]), stamp=T0 - 5 * SECOND - 1)) is False
    replayed = _signed(_feedback(scenes[3]), stamp=T0)
    assert core.accept_feedback(replayed) is True
    clock.now += 4 * SECOND
    assert core.accept_feedback(replayed) is False and 'a replay' in _errors(node)[-1]['message']
    clock.now += 2 * SECOND  # past the window: the replay is now stale
    assert core.accept_feedback(replayed) is False and 's ago' in _errors(node)[-1]['message']
    core.params['feedback_max_age'] = 60.0  # widened while running: the MAC is still remembered
    assert core.accept_feedback(replayed) is False and 'a replay' in _errors(node)[-1]['message']
    first = _signed(_feedback(scenes[0]), stamp=T0 - 5 * SECOND)  # its MAC was let go under the narrow window
    assert core.accept_feedback(first) is False and 'widened' in _errors(node)[-1]['message']
    drain(core)
    assert core.predictor.user_model(USER).n_ratings == 3
    core.close()


def test_signed_feedback_is_folded_in_exactly_as_unsigned_feedback_and_both_keys_of_a_rotation_sign(
        tiny_checkpoint, synthetic_scenes, key_file):
    scenes, scores = synthetic_scenes[:3], (1.0, 0.2, 0.7)
    _, plain = _robot(tiny_checkpoint, Clock())
    node, signed = _robot(tiny_checkpoint, Clock(), feedback_key_file=key_file)
    for k, (scene, score) in enumerate(zip(scenes, scores)):
        _rank(plain, scene)
        _rank(signed, scene)
        assert plain.accept_feedback(json.dumps(_feedback(scene, score))) is True
        key_id, secret = ('old', SECRET_A) if k % 2 else ('new', SECRET_B)
        assert signed.accept_feedback(_signed(_feedback(scene, score), key_id, secret)) is True
        drain(plain)
        drain(signed)
    assert not _errors(node)
    assert np.array_equal(_served(signed), _served(plain))
    ratings = signed.personalisation.histories.ratings(USER)
    assert [r.rating_id for r in ratings] == [r.feedback['auth']['mac'] for r in ratings]
    assert [r.feedback['auth']['key_id'] for r in ratings] == ['new', 'old', 'new']
    plain.close()
    signed.close()


def test_a_fuzz_of_the_signed_message_never_crashes_and_takes_nothing_but_the_original(tiny_checkpoint,
                                                                                       synthetic_scenes, key_file):
    node, core = _robot(tiny_checkpoint, Clock(), feedback_key_file=key_file)
    scene = synthetic_scenes[0]
    _rank(core, scene)
    good = feedback_auth.sign(_feedback(scene), 'new', SECRET_B, T0)
    assert core.accept_feedback(json.dumps(good)) is True
    rng = random.Random(27)
    wrong = (None, True, False, -1, 0, 2 ** 64, 1.5, '', 'x' * 300, [], {}, [1], {'a': {}}, T0)
    texts = [mutate(good, rng) for _ in range(300)]
    for _ in range(300):  # the auth object itself: each field wrong, missing or doubled
        auth = copy.deepcopy(good['auth'])
        key = rng.choice(['key_id', 'stamp', 'mac', 'other'])
        choice = rng.randrange(3)
        if choice == 0:
            auth[key] = rng.choice(wrong)
        elif choice == 1:
            auth.pop(key, None)
        else:
            auth = rng.choice(wrong)
        texts.append(json.dumps({**good, 'auth': auth}))
    for text in texts:
        assert core.accept_feedback(text) is False, text[:200]
    kinds = {e['kind'] for e in node.on('stars/errors')}
    assert 'internal' not in kinds and 'auth' in kinds
    drain(core)
    assert core.predictor.user_model(USER).n_ratings == 1
    core.close()


def test_a_replay_after_a_restart_is_still_refused(tiny_checkpoint, synthetic_scenes, key_file, tmp_path):
    clock = Clock()
    node, core = _robot(tiny_checkpoint, clock, feedback_key_file=key_file, record_folder=tmp_path)
    scene = synthetic_scenes[0]
    _rank(core, scene)
    text = _signed(_feedback(scene))
    assert core.accept_feedback(text) is True
    drain(core)
    core.close()
    clock.now += 10 * SECOND
    node, again = _robot(tiny_checkpoint, clock, feedback_key_file=key_file, record_folder=tmp_path)
    _rank(again, scene)
    assert again.predictor.user_model(USER).n_ratings == 1  # restored
    assert again.accept_feedback(text) is False and 'a replay' in _errors(node)[-1]['message']
    again.close()


def _fleet(checkpoint, key_file, clock, *names, **params):
    return [_robot(checkpoint, clock, name, fleet_sharing=True, feedback_key_file=key_file, **params)
            for name in names]




def test_signed_ratings_travel_the_fleet_and_forged_peer_models_are_refused(tiny_checkpoint, synthetic_scenes,
                                                                           key_file):
    clock = Clock()
    (node_a, robot_a), (node_b, robot_b) = _fleet(tiny_checkpoint, key_file, clock, 'robot_a', 'robot_b')
    scenes = synthetic_scenes[:2]
    for scene, score in zip(scenes, (0.9, 0.3)):
        _rank(robot_a, scene)
        assert robot_a.accept_feedback(_signed(_feedback(scene, score))) is True
        drain(robot_a)
    genuine = json.loads(published_models(node_a)[-1])
    assert all(r['id'] == r['feedback']['auth']['mac'] for r in genuine['ratings'])

    def forged(change):
        payload = copy.deepcopy(genuine)
        change(payload, payload['ratings'][-1])
        return json.dumps(payload)

    other_fields = _feedback(scenes[1], 0.3, user='someone-else')
    other = json.loads(_signed(other_fields))
    cases = {
        'no signed originals': forged(lambda p, r: r.pop('feedback')),
        'score changed': forged(lambda p, r: r.update(score=0.0)),
        'signed score changed too': forged(lambda p, r: (r.update(score=0.0), r['feedback'].update(score=0.0))),
        'another person': forged(lambda p, r: p.update(user_id='someone-else')),
        'a rating of one person as another': forged(lambda p, r: r.update(feedback=other, id=other['auth']['mac'])),
        'one signature, a second rating': forged(lambda p, r: p['ratings'].append({**r, 'id': 'f' * 64})),
        'id not the MAC': forged(lambda p, r: r.update(id='e' * 64)),
        'unknown key': forged(lambda p, r: r.update(feedback=json.loads(_signed(_feedback(scenes[1], 0.3),
                                                                                'stranger', SECRET_A)))),
        'received long after signing': forged(lambda p, r: r.update(stamp=r['stamp'] + 61 * SECOND)),
        'no ratings at all': forged(lambda p, r: (p.pop('ratings'), p.pop('origin'))),
        'malformed auth': forged(lambda p, r: r['feedback'].update(auth={'key_id': 'new'})),
    }
    for case, text in cases.items():
        assert deliver([text], robot_b) == [False], case
        assert len(_errors(node_b)) == list(cases).index(case) + 1, (case, node_b.on('stars/errors'))
        assert robot_b.predictor.user_model(USER) is None and robot_b.predictor.user_model('someone-else') is None
    assert not robot_b.personalisation.peers.snapshot()
    assert all(e['topic'] == '/robot_b/stars/user_model' for e in _errors(node_b))
    assert deliver(published_models(node_a), robot_b) == [True, True]  # the genuine ones are taken
    assert np.array_equal(_served(robot_b), _served(robot_a))
    robot_a.close()
    robot_b.close()


def test_a_fuzz_of_a_peer_model_never_crashes_and_takes_nothing_forged(tiny_checkpoint, synthetic_scenes, key_file):
    clock = Clock()
    (node_a, robot_a), (node_b, robot_b) = _fleet(tiny_checkpoint, key_file, clock, 'robot_a', 'robot_b')
    _rank(robot_a, synthetic_scenes[0])
    robot_a.accept_feedback(_signed(_feedback(synthetic_scenes[0])))
    drain(robot_a)
    [genuine] = node_a.on('stars/user_model')
    rng = random.Random(2727)
    for _ in range(300):
        text = mutate(genuine, rng)
        try:
            payload = json.loads(text)
        except (ValueError, RecursionError):
            payload = None
        robot_b.accept_user_model(text)
        drain(robot_b)
        model = robot_b.predictor.user_model(USER)
        if model is not None:  # taken: then what the signature binds is the genuine rating's (docs/security.md
            # says what it does not bind: the scene content, the accepting robot, the stamp within the window)
            [rating] = robot_b.personalisation.ratings(USER)
            bound = ('id', 'feedback', 'score', 'action', 'scene_id')
            assert {k: rating.to_json().get(k) for k in bound} == {k: genuine['ratings'][0].get(k) for k in bound}
            assert payload['user_id'] == USER, text[:300]
            robot_b.personalisation.peers.drop(USER)
            robot_b.predictor.set_user_model(USER, None)
    huge = copy.deepcopy(genuine)
    huge['ratings'][0]['score'] = 10 ** 400  # JSON takes the integer, no float holds it
    assert robot_b.accept_user_model(json.dumps(huge)) is False
    assert node_b.on('stars/errors')[-1]['kind'] == 'non_finite'
    assert 'internal' not in {e['kind'] for e in node_b.on('stars/errors')}
    robot_a.close()
    robot_b.close()


def test_a_peer_without_a_key_file_is_refused_by_one_with_it(tiny_checkpoint, synthetic_scenes, key_file):
    clock = Clock()
    [(node_open, unsigned)] = _fleet(tiny_checkpoint, '', clock, 'open')
    [(node_b, robot_b)] = _fleet(tiny_checkpoint, key_file, clock, 'robot_b')
    _rank(unsigned, synthetic_scenes[0])
    unsigned.accept_feedback(json.dumps(_feedback(synthetic_scenes[0])))
    drain(unsigned)
    assert deliver(published_models(node_open), robot_b) == [False]
    assert 'carries no signed feedback' in _errors(node_b)[-1]['message']
    assert robot_b.predictor.user_model(USER) is None
    unsigned.close()
    robot_b.close()


def test_the_signer_prints_what_the_ranker_takes(tiny_checkpoint, synthetic_scenes, key_file, tmp_path):
    scene = synthetic_scenes[0]
    command = [sys.executable, '-m', 'stars_ros.sign_feedback', '--key-file', str(key_file)]
    fields = json.dumps(_feedback(scene))
    refused = subprocess.run(command + [fields], capture_output=True, text=True)
    assert refused.returncode == 2 and 'say which with --key-id' in refused.stderr
    invalid = subprocess.run(command + ['--key-id', 'old', '{"user_id": "x"}'], capture_output=True, text=True)
    assert invalid.returncode == 2 and "feedback needs either 'action'" in invalid.stderr
    served = ['--checkpoint', str(tiny_checkpoint)]
    signed = subprocess.run(command + served + ['--key-id', 'old', '--stamp', str(T0), fields], capture_output=True,
                            text=True, check=True).stdout
    assert json.loads(signed)['auth']['key_id'] == 'old'
    low, high = Predictor.load(tiny_checkpoint).rating_scale
    off_scale = json.dumps({**_feedback(scene), 'score': high + 79})  # a raw 0-100 score on a smaller scale
    unsigned = subprocess.run(command + served + ['--key-id', 'old', off_scale], capture_output=True, text=True)
    assert unsigned.returncode == 2 and unsigned.stdout == ''
    assert f'outside the rating scale [{low:g}, {high:g}]' in unsigned.stderr
    with pytest.raises(OutOfScaleError, match='outside the rating scale'):
        feedback_auth.sign({**_feedback(scene), 'score': high + 79}, 'old', b'k' * 32, T0, (low, high))
    node, core = _robot(tiny_checkpoint, Clock(), feedback_key_file=key_file)
    _rank(core, scene)
    assert core.accept_feedback(signed.strip()) is True
    core.close()
