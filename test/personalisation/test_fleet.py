"""Fleet sharing without ROS: rankers that pass each other's stars/user_model messages solve
each user from the union of their ratings, so they serve the same model to the last bit;
duplicates and their own messages change nothing, another checkpoint's models are ignored
with one warning, garbage is reported and changes nothing, and a restart keeps the peers'
ratings. test_fleet_node.py checks the same over DDS between ranker processes."""
import json

import numpy as np
import pytest

from stars_ros import messages
from stars_ros.personalisation.fleet import PeerRatings, solve_set
from stars_ros.personalisation.foldin import Rating
from stars_ros.node.core import RankerCore
from stars_ros.node.parameters import PARAMETERS, TOPICS
from stars_ros.data.scene_source import read_scenes, scene_request
from stars_ros import state
from core_harness import Node, deliver, drain, published_models

USER = 'visitor'


@pytest.fixture(scope='module')
def scenes(synthetic_root):
    return read_scenes(synthetic_root / 'raw' / 'h.jsonl')[:8]


def _robot(name, checkpoint, folder='', **params):
    node = Node()
    values = {name: spec[0] for name, spec in PARAMETERS.items()}
    values.update({'checkpoint': str(checkpoint), 'record_folder': str(folder), 'fleet_sharing': True,
                   'flush_interval': 0.01, **params})
    core = RankerCore(values, {topic: f'/{name}/{topic}' for topic in TOPICS}, f'/{name}/ranker', node.publish,
                      node, lambda: next(node.clock))
    return node, core



def _rate(node, core, scene, score, user=USER):
    """Rank ``scene`` for ``user`` at this robot, then give feedback on it there."""
    core.accept_scene(messages.dumps(scene_request(scene['identifier'], scene, user)), 0)
    drain(core)
    core.accept_feedback(json.dumps({'user_id': user, 'scene_id': scene['identifier'], 'action': 'navigate',
                                     'score': score}))
    drain(core)




def _served(core, user=USER):
    model = core.predictor.user_model(user)
    return np.append(model.p, model.b)


def _ranking(node, core, scene, user=USER):
    core.accept_scene(messages.dumps(scene_request('probe', scene, user)), 0)
    drain(core)
    return node.on('stars/ranking')[-1]['ranking']


def test_solve_set_is_the_union_by_id_in_stamp_order_cut_to_the_most_recent():
    def rating(rid, stamp):
        return Rating({}, 'navigate', 0.5, None, rid, stamp, 'x')
    a, b, c, d = rating('a', 3), rating('b', 1), rating('c', 2), rating('d', 2)
    assert [r.rating_id for r in solve_set([a, b], [c, b, d], 10)] == ['b', 'c', 'd', 'a']
    assert [r.rating_id for r in solve_set([a, b], [d, c], 2)] == ['d', 'a']  # ties: by id
    assert solve_set([a], [], 10) == solve_set([], [a], 10)
    peers = PeerRatings(max_ratings=2, max_users=1)
    assert peers.add('u', [a, b, c]) == []
    assert {r.rating_id for r in peers.ratings('u')} == {'c', 'a'}  # the most recent two
    assert peers.add('v', [d]) == ['u']


def test_feedback_at_one_robot_gives_its_peer_the_same_model_and_ranking(tiny_checkpoint, scenes):
    node_a, robot_a = _robot('robot_a', tiny_checkpoint)
    node_b, robot_b = _robot('robot_b', tiny_checkpoint)
    for scene, score in zip(scenes[:3], (1.0, 0.9, 0.2)):
        _rate(node_a, robot_a, scene, score)
    sent = published_models(node_a)
    assert len(sent) == 3 and [len(json.loads(t)['ratings']) for t in sent] == [1, 2, 3]
    assert json.loads(sent[-1])['origin'] == '/robot_a/ranker'
    assert robot_b.predictor.user_model(USER) is None
    assert deliver(sent, robot_b) == [True, True, True]
    assert np.array_equal(_served(robot_b), _served(robot_a))  # bit for bit
    assert _ranking(node_b, robot_b, scenes[5]) == _ranking(node_a, robot_a, scenes[5])
    assert [json.loads(t)['n_ratings'] for t in published_models(node_b)] == [3]  # three arrived, one solve
    # duplicates and a robot's own messages change nothing and start no exchange
    published = len(node_b.published)
    assert deliver(sent, robot_b) == [False] * 3 and deliver(published_models(node_b), robot_b) == [False]
    assert len(node_b.published) == published
    assert deliver(published_models(node_b), robot_a) == [False]  # A's ratings coming back


def test_simultaneous_feedback_converges_to_one_model_whatever_the_order(tiny_checkpoint, scenes):
    robots = [_robot(name, tiny_checkpoint) for name in ('robot_a', 'robot_b', 'robot_c')]
    (node_a, robot_a), (node_b, robot_b), (node_c, robot_c) = robots
    _rate(node_a, robot_a, scenes[0], 1.0)
    _rate(node_b, robot_b, scenes[1], 0.1)  # at the same time: neither has heard the other
    _rate(node_b, robot_b, scenes[2], 0.3)
    from_a, from_b = published_models(node_a), published_models(node_b)
    deliver(from_b, robot_a)
    deliver(from_a[::-1], robot_b)
    deliver(from_b[::-1] + from_a, robot_c)  # a third robot hears both, in another order
    assert np.array_equal(_served(robot_a), _served(robot_b))
    assert np.array_equal(_served(robot_a), _served(robot_c))
    assert robot_a.predictor.user_model(USER).n_ratings == 3
    # each re-published the union once; passing those round changes nothing more
    last = {name: published_models(node)[-1] for name, (node, _) in zip('abc', robots)}
    assert all(len(json.loads(text)['ratings']) == 3 for text in last.values())
    counts = [len(node.published) for node, _ in robots]
    for (_, core) in robots:
        deliver(list(last.values()), core)
    assert [len(node.published) for node, _ in robots] == counts


def test_a_late_robot_gets_every_user_when_it_joins(tiny_checkpoint, scenes):
    node_a, robot_a = _robot('robot_a', tiny_checkpoint)
    for k, user in enumerate(('ann', 'bob')):
        _rate(node_a, robot_a, scenes[k], 0.8, user)
    before = len(node_a.published)
    assert robot_a.announce() is True
    drain(robot_a)
    announced = published_models(node_a)[-2:]
    assert len(node_a.published) == before + 2 and {json.loads(t)['user_id'] for t in announced} == {'ann', 'bob'}
    node_c, robot_c = _robot('robot_c', tiny_checkpoint)
    deliver(announced, robot_c)
    for user in ('ann', 'bob'):
        assert np.array_equal(_served(robot_c, user), _served(robot_a, user))


def test_models_of_another_checkpoint_are_ignored_with_one_warning(tiny_checkpoint, scenes):
    node_a, robot_a = _robot('robot_a', tiny_checkpoint)
    node_b, robot_b = _robot('robot_b', tiny_checkpoint)
    _rate(node_a, robot_a, scenes[0], 1.0)
    other = json.loads(published_models(node_a)[-1])
    other['fingerprint'] = 'f' * 64
    assert deliver([json.dumps(other)] * 2, robot_b) == [False, False]
    assert robot_b.predictor.user_model(USER) is None
    warnings = [e for e in node_b.on('stars/errors') if e['kind'] == 'fleet']
    assert len(warnings) == 1 and warnings[0]['level'] == 'warning'
    assert 'ffffffffffff' in warnings[0]['message'] and '/robot_a/ranker' in warnings[0]['message']
    assert warnings[0]['topic'] == '/robot_b/stars/user_model'


def test_garbage_from_a_peer_is_reported_and_changes_nothing(tiny_checkpoint, scenes):
    node_a, robot_a = _robot('robot_a', tiny_checkpoint)
    node_b, robot_b = _robot('robot_b', tiny_checkpoint)
    _rate(node_a, robot_a, scenes[0], 1.0)
    _rate(node_a, robot_a, scenes[1], 0.5)
    good = json.loads(published_models(node_a)[-1])

    def variant(change):
        payload = json.loads(json.dumps(good))
        change(payload)
        return json.dumps(payload)
    bad = {
        'malformed_json': '{"user_id": ',
        'schema': variant(lambda p: p['ratings'][0].pop('score')),
        'unknown_action': variant(lambda p: p['ratings'][1].update(action='dance')),
        'scene_graph': variant(lambda p: p['ratings'][1]['scene'].update(humans=[{'id': 1}])),
    }
    for kind, text in bad.items():
        deliver([text], robot_b)
        error = node_b.on('stars/errors')[-1]
        assert error['kind'] in (kind, 'schema') and error['level'] == 'error', (kind, error)
        assert error['topic'] == '/robot_b/stars/user_model'
    assert not robot_b.personalisation.intake and robot_b.personalisation.peers.snapshot() == {}
    assert robot_b.predictor.user_model(USER) is None
    assert deliver([json.dumps(good)], robot_b) == [True]  # the good one still goes in whole
    assert np.array_equal(_served(robot_b), _served(robot_a))


def test_a_peer_score_off_the_rating_scale_is_refused_and_leaves_the_store_as_it_was(tiny_checkpoint, scenes,
                                                                                     tmp_path):
    node_a, robot_a = _robot('robot_a', tiny_checkpoint)
    node_b, robot_b = _robot('robot_b', tiny_checkpoint, tmp_path / 'b')
    _rate(node_a, robot_a, scenes[0], 1.0)
    _rate(node_a, robot_a, scenes[1], 0.5)
    low, high = robot_b.predictor.rating_scale
    payload = json.loads(published_models(node_a)[-1])
    payload['ratings'][1]['score'] = high + 79  # a raw 0-100 score: a peer that took it unchecked
    assert deliver([json.dumps(payload)], robot_b) == [False]
    [error] = node_b.on('stars/errors')
    assert error['kind'] == 'out_of_scale' and f'rating scale [{low:g}, {high:g}]' in error['message']
    assert robot_b.predictor.user_model(USER) is None and node_b.on('stars/user_model') == []  # not passed on
    robot_b.close()
    with state.open_reader(tmp_path / 'b') as store:
        assert store.summary() == []


def test_a_restarted_robot_keeps_its_peers_ratings(tiny_checkpoint, scenes, tmp_path):
    node_a, robot_a = _robot('robot_a', tiny_checkpoint)
    node_b, robot_b = _robot('robot_b', tiny_checkpoint, tmp_path / 'b')
    _rate(node_a, robot_a, scenes[0], 1.0)
    _rate(node_b, robot_b, scenes[1], 0.2)
    deliver(published_models(node_a), robot_b)
    served = _served(robot_b)
    robot_b.close()
    with state.open_reader(tmp_path / 'b') as store:
        [person] = store.people()
    assert (len(person.ratings), len(person.peer_ratings), person.solved) == (1, 1, True)
    node_b2, robot_b2 = _robot('robot_b', tiny_checkpoint, tmp_path / 'b')
    assert not robot_b2.personalisation.pending  # served as stored: solved from the ratings stored with it
    assert np.array_equal(_served(robot_b2), served)
    assert np.array_equal(state.loaded(robot_b2.predictor.user_model(USER).covariance),
                          robot_b.predictor.user_model(USER).covariance)  # read when first used
    assert [r.rating_id for r in robot_b2.personalisation.ratings(USER)] == [
        r.rating_id for r in robot_b.personalisation.ratings(USER)]
    assert deliver(published_models(node_a), robot_b2) == [False]  # known already: nothing was lost
    robot_b2.close()


def test_a_peer_message_is_taken_in_one_rated_scene_per_turn(tiny_checkpoint, scenes):
    """Rankings wait behind at most one encoding: a message of three new ratings takes three
    turns of ``work``, and a ranking queued meanwhile goes first."""
    node_a, robot_a = _robot('robot_a', tiny_checkpoint)
    node_b, robot_b = _robot('robot_b', tiny_checkpoint)
    for scene in scenes[:3]:
        _rate(node_a, robot_a, scene, 0.7)
    assert robot_b.accept_user_model(published_models(node_a)[-1]) is True
    for turn in (1, 2):
        assert robot_b.work() is True and robot_b.personalisation.intake[0].encoded == turn
        assert robot_b.personalisation.peers.snapshot() == {}  # nothing kept before all have passed
    robot_b.accept_scene(messages.dumps(scene_request('meanwhile', scenes[6], 'other')), 0)
    robot_b.work()
    assert node_b.on('stars/ranking')[-1]['scene_id'] == 'meanwhile' and robot_b.personalisation.intake
    robot_b.work()  # the third scene: the ratings are kept and the user waits for a solve
    assert not robot_b.personalisation.intake and list(robot_b.personalisation.pending) == [USER]
    drain(robot_b)
    assert np.array_equal(_served(robot_b), _served(robot_a))
