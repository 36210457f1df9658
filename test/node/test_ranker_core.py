"""The ranker's work without ROS (what test_ranker_node.py checks over DDS, here in one
process): rankings carry the checkpoint's fingerprint, problems are reported by kind and
summed up in the diagnostics, feedback is folded in once the queue is empty, a reload that
fails keeps serving, and a clean close leaves the feedback and the people in the store."""
import json
import sqlite3

import pytest

from stars_ros import messages
from stars_ros import recording, state
from core_harness import Node, SteppedClock, drain, make_core, woken_and_drained
from waiting import wait_for
from stars_ros.node.parameters import PARAMETERS, TOPICS, topic_qos
from stars_ros.data.scene_source import read_scenes, scene_request


@pytest.fixture(scope='module')
def scenes(synthetic_root):
    return read_scenes(synthetic_root / 'raw' / 'h.jsonl')[:4]


def _scene(core, scene, user_id=None, scene_id=None):
    core.accept_scene(messages.dumps(scene_request(scene_id or scene['identifier'], scene, user_id)), 0)


def test_rankings_carry_the_fingerprint_and_a_stranger_is_warned_once(tiny_checkpoint, scenes):
    node = Node()
    core = make_core(node, tiny_checkpoint)
    for scene in scenes[:2]:
        _scene(core, scene, 'stranger')
    assert core.work() is False
    rankings = node.on('stars/ranking')
    assert [r['scene_id'] for r in rankings] == [s['identifier'] for s in scenes[:2]]
    assert {r['fingerprint'] for r in rankings} == {core.predictor.fingerprint}
    assert all(r['known_user'] is False and r['user_id'] == 'stranger' for r in rankings)
    [warning] = node.on('stars/errors')
    assert (warning['kind'], warning['level'], warning['topic']) == ('unknown_user', 'warning', '/stars/scene')
    core.close()


def test_processing_time_runs_from_the_middlewares_reception_to_the_reply(tiny_checkpoint, scenes):
    node, clock = Node(), SteppedClock()
    core = make_core(node, tiny_checkpoint, clock=clock)
    core.accept_scene(messages.dumps(scene_request('waited', scenes[0], 'a')), clock.ns - 5_000_000)
    clock.ns += 2_000_000  # the executor was busy elsewhere meanwhile
    assert core.work() is False
    [ranking] = node.on('stars/ranking')
    assert ranking['processing_ms'] == 7.0
    core.close()


def test_a_ranking_that_waited_behind_fold_in_is_counted_with_that_wait(tiny_checkpoint, scenes):
    """A request received before feedback is folded in and served after it: the fold-in's
    span lies inside its wait, and the next diagnostics count it (``period.*``)."""
    node, clock = Node(), SteppedClock(step=1_000_000)  # 1 ms at every read
    core = make_core(node, tiny_checkpoint, clock=clock)
    core.accept_scene(messages.dumps(scene_request(scenes[0]['identifier'], scenes[0], 'newcomer')), clock())
    assert core.work() is False
    core.diagnostics()  # a new period
    core.accept_scene(messages.dumps(scene_request('waits', scenes[1], 'other')), clock())
    feedback = {'user_id': 'newcomer', 'scene_id': scenes[0]['identifier'], 'action': 'navigate', 'score': 1.0}
    assert core.accept_feedback(messages.dumps(feedback)) is True
    while core.work():
        pass
    values = core.diagnostics()[2]
    assert values['period.rankings'] == 1 and values['period.rankings_delayed_by_fold_in'] == 1
    assert values['period.fold_in_updates'] == 1
    assert 0 < values['period.fold_in_delay_ms.max'] <= values['period.delayed_processing_ms.max']
    assert values['period.delayed_processing_ms.max'] <= values['period.processing_ms.max']
    core.accept_scene(messages.dumps(scene_request('on time', scenes[1], 'other')), clock())
    assert core.work() is False
    assert core.diagnostics()[2]['period.rankings_delayed_by_fold_in'] == 0
    core.close()


def test_problems_are_reported_throttled_and_summed_up_in_the_diagnostics(tiny_checkpoint, scenes):
    node = Node()
    core = make_core(node, tiny_checkpoint, queue_depth=1)
    assert core.diagnostics()[0] == 'ok'
    core.accept_scene('{"scene_id": "x"', 0)
    core.accept_scene('[]', 0)
    _scene(core, scenes[0], 'a')
    _scene(core, scenes[1], 'a')  # the queue holds one
    kinds = [e['kind'] for e in node.on('stars/errors')]
    assert len(kinds) == 3 and kinds[-1] == 'overload'
    assert [level for level, _ in node.lines if level == 'error'] == ['error'] * len(set(kinds))  # one line per kind
    assert core.work() is False and len(node.on('stars/ranking')) == 1
    level, summary, values, per_kind = core.diagnostics()
    assert level == 'error' and summary.startswith('serving; problems since last report: ')
    assert values['rankings'] == 1 and values['errors.overload'] == 1 and values['queued'] == 0
    assert values['recording'] == 'off' and values['period.rankings'] == 1
    assert ('overload', 'error', 1) in [entry[:3] for entry in per_kind]
    assert core.diagnostics()[:2] == ('ok', 'serving')  # a new period
    core.close()


def test_feedback_is_folded_in_once_no_scene_waits(tiny_checkpoint, scenes):
    node = Node()
    core = make_core(node, tiny_checkpoint)
    _scene(core, scenes[0], 'newcomer')
    core.work()
    feedback = {'user_id': 'newcomer', 'scene_id': scenes[0]['identifier'], 'action': 'navigate', 'score': 1.0}
    assert core.accept_feedback(messages.dumps(feedback)) is True
    _scene(core, scenes[1], 'newcomer')
    assert core.work() is True and not node.on('stars/user_model')  # the scene first
    assert core.work() is False
    [model] = node.on('stars/user_model')
    assert model['user_id'] == 'newcomer' and model['n_ratings'] == 1
    assert model['fingerprint'] == core.predictor.fingerprint
    _scene(core, scenes[2], 'newcomer')
    core.work()
    assert node.on('stars/ranking')[-1]['personalised_from'] == 1
    assert core.accept_feedback(messages.dumps({**feedback, 'scene_id': 'gone'})) is False
    assert node.on('stars/errors')[-1]['kind'] == 'unknown_scene'
    core.params['fold_in'] = False
    assert core.accept_feedback(messages.dumps(feedback)) is False and not core.personalisation.pending
    core.close()


def test_a_failed_reload_keeps_serving_the_checkpoint(tiny_checkpoint, tmp_path):
    node = Node()
    core = make_core(node, tiny_checkpoint)
    fingerprint = core.predictor.fingerprint
    core.params['checkpoint'] = str(tmp_path / 'missing.pt')
    succeeded, message = core.reload()
    assert not succeeded and core.predictor.fingerprint == fingerprint
    assert node.on('stars/errors')[-1]['kind'] == 'checkpoint'
    core.params['checkpoint'] = str(tiny_checkpoint)
    assert core.reload() == (True, f'serving {tiny_checkpoint} (fingerprint {fingerprint})')
    core.close()


def test_a_clean_close_leaves_feedback_rankings_and_users_on_disk(tiny_checkpoint, scenes, tmp_path):
    node = Node()
    core = make_core(node, tiny_checkpoint, record_folder=str(tmp_path), flush_interval=60.0)
    _scene(core, scenes[0], 'newcomer')
    core.work()
    core.accept_feedback(messages.dumps({'user_id': 'newcomer', 'scene_id': scenes[0]['identifier'],
                                         'action': 'navigate', 'score': 0.5}))
    core.work()
    _scene(core, scenes[1], 'newcomer')  # never scored: still recorded
    core.close()
    recorded = [topic for topic, _, _ in recording.read_messages(core.recorder.path)]
    for topic in ('/stars/scene', '/stars/ranking', '/stars/feedback', '/stars/user_model', '/stars/errors'):
        assert topic in recorded, topic
    assert recorded.count('/stars/scene') == 2
    with state.open_reader(tmp_path) as store:
        assert [p['person'] for p in store.summary()] == ['newcomer']
        assert [json.loads(e['data'])['user_id'] for e in store.feedback(core.recorder.name)] == ['newcomer']
    offered = recording.bag_topics(core.recorder.path)
    depths = topic_qos(core.params)
    for topic in set(recorded):  # the bag offers what the node subscribed and published with
        depth, latched = depths[topic[1:]]
        assert offered[topic]['depth'] == depth
        assert offered[topic]['durability'] == ('transient_local' if latched else 'volatile')


def test_every_topic_has_its_qos_and_shared_models_keep_every_user():
    params = {name: spec[0] for name, spec in PARAMETERS.items()}
    alone = topic_qos({**params, 'fleet_sharing': False})
    assert set(alone) == set(TOPICS)
    shared = topic_qos({**params, 'fleet_sharing': True, 'fold_in_max_users': 50})
    assert shared['stars/user_model'] == (alone['stars/user_model'][0] + 50, True)


def _sums_to_the_score(entry, scale):
    why = entry['why']
    total = why['content'] + why['personal'] + why['scene']
    return abs(min(max(total, scale[0]), scale[1]) - entry['score']) < 1e-5


def test_a_request_that_asks_gets_why_on_every_entry_and_the_others_do_not(tiny_checkpoint, scenes):
    node = Node()
    core = make_core(node, tiny_checkpoint, explain_entities=3)
    user = core.predictor.served.user_vocabulary.keys[0]
    explained = {**scene_request('asks', scenes[0], user), 'explain': True}
    placements = {**scene_request('placements', scenes[1], user, placements=3), 'explain': True}
    for request in (explained, scene_request('plain', scenes[0], user), placements):
        core.accept_scene(messages.dumps(request), 0)
    assert core.work() is False
    rankings = {r['scene_id']: r for r in node.on('stars/ranking')}
    for ranking in rankings.values():
        messages.check('ranking', ranking)
    assert not any('why' in entry for entry in rankings['plain']['ranking'])
    assert [e['score'] for e in rankings['plain']['ranking']] == [e['score'] for e in rankings['asks']['ranking']]
    scale = core.predictor.rating_scale
    for scene_id in ('asks', 'placements'):
        for entry in rankings[scene_id]['ranking']:
            assert _sums_to_the_score(entry, scale), entry
            effects = [abs(e['effect']) for e in entry['why']['entities']]
            assert len(effects) == 3 and effects == sorted(effects, reverse=True)
    core.close()


def test_the_explain_parameter_explains_every_request(tiny_checkpoint, scenes):
    node = Node()
    core = make_core(node, tiny_checkpoint, explain=True, explain_entities=0)
    _scene(core, scenes[2], 'stranger')
    assert core.work() is False
    [ranking] = node.on('stars/ranking')
    kinds = {e['kind'] for entry in ranking['ranking'] for e in entry['why']['entities']}
    assert 'human' in kinds and 'wall' in kinds and 'room' in kinds
    assert all(_sums_to_the_score(entry, core.predictor.rating_scale) for entry in ranking['ranking'])
    core.close()


@pytest.mark.slow
def test_a_full_disk_keeps_serving_reports_recording_and_stores_the_feedback_once_it_has_room(
        tiny_checkpoint, scenes, tmp_path, monkeypatch):
    """SQLite's own 'database or disk is full' (max_page_count stands in for the disk)."""
    from stars_ros.state import store as state_store
    connections, connect = [], sqlite3.connect
    monkeypatch.setattr(state_store.sqlite3, 'connect',
                        lambda *args, **kwargs: connections.append(connect(*args, **kwargs)) or connections[-1])
    node = Node()
    core = make_core(node, tiny_checkpoint, record_folder=str(tmp_path), flush_interval=0.01)
    writer = connections[0]
    writer.execute(f"PRAGMA max_page_count = {writer.execute('PRAGMA page_count').fetchone()[0]}")
    for scene in scenes:
        _scene(core, scene, 'newcomer')
    core.work()
    sent = []

    def disk_full() -> bool:
        return any(e['kind'] == 'recording' for e in node.on('stars/errors'))
    for k in range(40):  # until the pages the store has are full
        sent.append(messages.dumps({'user_id': f'person-{k}', 'scene_id': scenes[k % len(scenes)]['identifier'],
                                    'action': 'navigate', 'score': 0.5}))
        assert core.accept_feedback(sent[-1])
        assert wait_for(lambda: disk_full() or core.diagnostics()[2]['feedback_not_on_disk'] == 0, 30)
        if disk_full():  # else it was committed: there was room for it
            break
    assert 'database or disk is full' in node.on('stars/errors')[-1]['message']
    assert core.diagnostics()[2]['feedback_not_on_disk'] >= 1
    while core.work():  # the fold-in goes on: the models are served to their own people
        pass
    _scene(core, scenes[1], f'person-{len(sent) - 1}')
    core.work()
    assert node.on('stars/ranking')[-1]['personalised_from'] == 1
    with state.open_reader(tmp_path) as store:  # nobody else sees a model solved from feedback not stored
        stored = {p.user_id for p in store.people()}
    assert {m['user_id'] for m in node.on('stars/user_model')} <= stored
    writer.execute('PRAGMA max_page_count = 1000000')  # room again
    assert wait_for(lambda: core.diagnostics()[2]['feedback_not_on_disk'] == 0, 30)
    assert wait_for(lambda: woken_and_drained(node, core) and {m['user_id'] for m in node.on('stars/user_model')} == {
        f'person-{k}' for k in range(len(sent))}, 30), 'the models were not published once stored'
    core.close()
    assert [text for topic, text,
            _ in recording.read_messages(core.recorder.path) if topic == '/stars/feedback'] == sent
    with state.open_reader(tmp_path) as store:
        people = store.people()
    assert [p.user_id for p in people] == [f'person-{k}' for k in range(len(sent))]
    assert all(len(p.ratings) == 1 and p.solved for p in people)


def _feedback(scene, user_id, score=0.5):
    return messages.dumps({'user_id': user_id, 'scene_id': scene['identifier'], 'action': 'navigate', 'score': score})


def test_a_model_is_seen_by_nobody_else_before_the_feedback_it_was_solved_from_is_committed(
        tiny_checkpoint, scenes, tmp_path):
    """The store's writer held between the solve and its commit (another connection holds
    the database's write lock): a kill then would lose the feedback, and nothing of that
    person has gone out; their own rankings already use it."""
    node = Node()
    core = make_core(node, tiny_checkpoint, record_folder=str(tmp_path), flush_interval=60.0)
    _scene(core, scenes[0], 'ann')
    core.work()
    blocker = sqlite3.connect(tmp_path / state.DATABASE, isolation_level=None)
    blocker.execute('BEGIN IMMEDIATE')
    assert core.accept_feedback(_feedback(scenes[0], 'ann'))
    drain(core)  # solved
    _scene(core, scenes[1], 'ann')
    core.work()
    assert node.on('stars/ranking')[-1]['personalised_from'] == 1  # her own next ranking uses it
    with state.open_reader(tmp_path) as store:  # what a kill now would leave
        assert store.summary() == [] and store.feedback() == []
    assert node.on('stars/user_model') == []
    blocker.execute('ROLLBACK')  # the commit goes through: the store's thread wakes the executor, which sends it
    assert wait_for(lambda: woken_and_drained(node, core) and node.on('stars/user_model'), 30)
    assert node.on('stars/user_model')[0]['user_id'] == 'ann'
    blocker.close()
    core.close()
    assert [json.loads(text)['user_id'] for topic, text, _ in recording.read_messages(core.recorder.path)
            if topic == '/stars/user_model'] == ['ann']


def test_a_score_off_the_rating_scale_is_refused_and_leaves_the_store_as_it_was(tiny_checkpoint, scenes, tmp_path):
    node = Node()
    core = make_core(node, tiny_checkpoint, record_folder=str(tmp_path))
    low, high = core.predictor.rating_scale
    _scene(core, scenes[0], 'ann')
    core.work()
    assert core.accept_feedback(_feedback(scenes[0], 'ann', high + 79)) is False  # a raw 0-100 score
    assert core.accept_feedback(_feedback(scenes[0], 'ann', low - 0.5)) is False
    refusals = [e for e in node.on('stars/errors') if e['kind'] == 'out_of_scale']
    assert len(refusals) == 2 and f'rating scale [{low:g}, {high:g}]' in refusals[0]['message']
    assert refusals[0]['topic'] == '/stars/feedback'
    drain(core)
    assert not core.personalisation.pending and core.predictor.user_model('ann') is None
    core.close()
    with state.open_reader(tmp_path) as store:
        assert store.summary() == [] and store.feedback() == []
    assert '/stars/feedback' not in {topic for topic, _, _ in recording.read_messages(core.recorder.path)}
