"""End to end over loopback DDS: a stranger's feedback personalises their next ranking, the
MCAP log refits offline to a checkpoint that ranks the same through ~/reload, and a restart
restores the folded-in user.

Tolerance: the refit checkpoint and the online overlay hold the same float32 (p_u, b_u), so
their scores agree to float rounding; the test allows 1e-5 on the [0, 1] scale.
"""
import json
import signal

import pytest

from offline_training import refit
from ros_helpers import RELIABLE, RosClient, domain_id, stored_feedback, start_node, stop
from waiting import wait_for
from stars_ros import recording, state
from stars_ros.personalisation.foldin import FoldIn, Rating
from stars_ros.model.predictor import Predictor
from stars_ros.data.scene_source import read_scenes, scene_request

pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning:lark.*')
USER = 'newcomer'
LAMBDA = 0.05
TOLERANCE = 1e-5
START_TIMEOUT = 90


@pytest.fixture(scope='module')
def scenes(synthetic_root):
    return read_scenes(synthetic_root / 'raw' / 'h.jsonl')[:20]


def _start(domain, checkpoint, folder, log):
    return start_node('stars_ros.ros.ranker', domain, {
        'checkpoint': checkpoint, 'record_folder': folder, 'flush_interval': 0.2,
        'fold_in_regularisation': LAMBDA}, log)


def _latest(client, scene_id):
    return next((r for r in reversed(client.snapshot(client.rankings)) if r['scene_id'] == scene_id), None)


def _rank(client, scenes, tag):
    """Rank scenes 0..5 for USER (scene ids are the data set's identifiers, so q_i applies);
    returns {identifier: reply}."""
    before = len(client.rankings)
    for scene in scenes[:6]:
        client.scene({'scene_id': scene['identifier'], 'user_id': USER, 'graph': scene})
    assert client.wait(lambda: len(client.rankings) >= before + 6, 30), f'no rankings ({tag})'
    return {s['identifier']: _latest(client, s['identifier']) for s in scenes[:6]}


def _score(reply):
    return reply['ranking'][0]['score']


def _ranker_values(diagnostics) -> dict:
    """The key-values of the ranker's status in one /diagnostics message ({} if it has none)."""
    return next(({v.key: v.value for v in s.values} for s in diagnostics.status if s.name.endswith(': ranker')), {})


@pytest.mark.slow
def test_feedback_personalises_refits_reloads_and_survives_a_restart(tiny_checkpoint, scenes, tmp_path):
    domain = domain_id(7)
    records = tmp_path / 'records'
    client = RosClient(domain)
    models = client.collect('/stars/user_model', RELIABLE)
    process = _start(domain, tiny_checkpoint, records, tmp_path / 'ranker-1.log')
    probe = {'scene_id': 'probe', 'graph': scenes[19]}
    try:
        client.wait_ready(process, START_TIMEOUT, probe)
        before = _rank(client, scenes, 'stranger')
        assert all(r['known_user'] is False and 'personalised_from' not in r for r in before.values())

        # feedback: the stranger likes scenes 0-3 a lot, and one candidate placement
        placements = scene_request('placements', scenes[10], user_id=USER, placements=3)
        client.scene(placements)
        assert client.wait(lambda: client.ranking_for('placements') is not None, 20)
        label = placements['candidates'][2]['candidate']
        ratings = []
        for scene in scenes[:4]:
            client.feedback({'user_id': USER, 'scene_id': scene['identifier'], 'action': 'navigate', 'score': 1.0})
            ratings.append(Rating(scene, 'navigate', 1.0, scene['identifier']))
        client.feedback({'user_id': USER, 'scene_id': 'placements', 'candidate': label, 'score': 1.0})
        ratings.append(Rating(placements['candidates'][2]['graph'], 'navigate', 1.0, None))
        client.feedback({'user_id': USER, 'scene_id': 'never-ranked', 'action': 'navigate', 'score': 0.0})
        assert client.wait(lambda: any(m['n_ratings'] == 5 for m in models), 20), models
        assert client.wait(lambda: any(e['kind'] == 'unknown_scene' and e['level'] == 'warning'
                                       and e['scene_id'] == 'never-ranked' for e in client.errors), 10)
        model = [m for m in models if m['n_ratings'] == 5][-1]
        assert model['user_id'] == USER and model['regularisation'] == LAMBDA and len(model['p_u']) == 16

        after = _rank(client, scenes, 'folded in')
        for scene in scenes[:4]:  # towards the feedback (1.0 is above every prediction)
            assert _score(after[scene['identifier']]) > _score(before[scene['identifier']])
        assert all(r['personalised_from'] == 5 and r['known_user'] is False for r in after.values())
        reference = Predictor.load(tiny_checkpoint)
        reference.set_user_model(USER, FoldIn(reference).fit(ratings, USER, LAMBDA))
        for scene in scenes[:6]:
            expected = reference.rank(USER, scene, scene_id=scene['identifier'])[0].score
            assert abs(_score(after[scene['identifier']]) - expected) < TOLERANCE
        assert stop(process, signal.SIGINT) == 0
        with state.open_reader(records) as store:
            assert [(p['person'], p['ratings'], p['solved']) for p in store.summary()] == [(USER, 5, True)]

        # offline refit of the log, user mode
        bag = next(records.glob('stars_*'))
        recorded = [json.loads(text) for topic, text, _ in recording.read_messages(bag) if topic == '/stars/user_model']
        assert recorded[-1]['n_ratings'] == 5
        assert any(topic == '/stars/feedback' and 'never-ranked' in text
                   for topic, text, _ in recording.read_messages(bag))  # recorded, though not folded in
        refitted = tmp_path / 'refit.pt'
        assert refit.main(['--checkpoint', str(tiny_checkpoint), '--logs', str(bag), '--out', str(refitted)]) == 0

        # restart: the folded-in user is restored from the state store
        process = _start(domain, tiny_checkpoint, records, tmp_path / 'ranker-2.log')
        client.wait_ready(process, START_TIMEOUT, {'scene_id': 'probe-2', 'graph': scenes[19]})
        restored = _rank(client, scenes, 'restored')
        for identifier, reply in restored.items():
            assert reply['personalised_from'] == 5
            assert abs(_score(reply) - _score(after[identifier])) < TOLERANCE

        # ~/reload to the refit checkpoint ranks as the online fold-in did
        assert client.set_parameters('/ranker', {'checkpoint': str(refitted)})[0].successful
        assert client.call('/ranker/reload').success
        reloaded = _rank(client, scenes, 'reloaded')
        fingerprint = Predictor.load(refitted).fingerprint
        for identifier, reply in reloaded.items():
            assert reply['fingerprint'] == fingerprint and reply['known_user'] is True
            assert 'personalised_from' not in reply  # the checkpoint absorbed the feedback
            assert abs(_score(reply) - _score(after[identifier])) < TOLERANCE
        client.feedback({'user_id': USER, 'scene_id': scenes[0]['identifier'], 'action': 'navigate', 'score': 0.0})
        assert client.wait(lambda: any(m['fingerprint'] == fingerprint for m in models), 20)
        assert stop(process, signal.SIGINT) == 0
        with state.open_reader(records) as store:  # only the feedback the refit did not absorb
            assert store.fingerprint == fingerprint and [(p['person'], p['ratings']) for p in store.summary()] == [
                (USER, 1)]

        # a store solved against another checkpoint is not restored, with a warning
        process = _start(domain, tiny_checkpoint, records, tmp_path / 'ranker-3.log')
        client.wait_ready(process, START_TIMEOUT, {'scene_id': 'probe-3', 'graph': scenes[19]})
        assert stop(process, signal.SIGINT) == 0
        assert 'folded-in users are not restored' in (tmp_path / 'ranker-3.log').read_text()
    finally:
        if process.poll() is None:
            process.kill()
        client.close()


def test_fold_in_off_records_feedback_without_personalising(tiny_checkpoint, scenes, tmp_path):
    """The feedback is taken (stored) and still nothing is folded in: no user model is
    published, the rankings after it are the stranger's, and the diagnostics that follow
    them count no folded-in user."""
    domain = domain_id(8)
    client = RosClient(domain)
    models = client.collect('/stars/user_model', RELIABLE)
    process = start_node('stars_ros.ros.ranker', domain, {'checkpoint': tiny_checkpoint, 'record_folder': tmp_path,
                                                      'fold_in': False, 'diagnostics_period': 0.2},
                         tmp_path / 'ranker.log')
    try:
        client.wait_ready(process, START_TIMEOUT, {'scene_id': 'probe', 'graph': scenes[19]})
        before = _rank(client, scenes, 'stranger')
        feedback = {'user_id': USER, 'scene_id': scenes[0]['identifier'], 'action': 'navigate', 'score': 1.0}
        client.feedback(feedback)
        bag = next(tmp_path.glob('stars_*'))
        assert wait_for(lambda: feedback in stored_feedback(bag), 20), 'the feedback was never taken in'
        after = _rank(client, scenes, 'still a stranger')
        assert all('personalised_from' not in r for r in after.values())
        assert all(abs(_score(after[k]) - _score(before[k])) < 1e-6 for k in before)  # batching may round
        reports = len(client.diagnostics)
        assert client.wait(lambda: len(client.diagnostics) >= reports + 2, 10)  # periods after those rankings
        assert _ranker_values(client.diagnostics[-1])['folded_in_users'] == '0' and not models
        assert client.set_parameters('/ranker', {'fold_in_min_ratings': 0})[0].successful is False
        assert stop(process, signal.SIGINT) == 0
    finally:
        if process.poll() is None:
            process.kill()
        client.close()
    with state.open_reader(tmp_path) as store:
        assert store.summary() == [] and len(store.feedback()) == 1


def test_fold_in_bounds_ratings_per_user_and_users(tiny_checkpoint, scenes, tmp_path):
    """fold_in_max_ratings solves from the most recent ratings; fold_in_max_users sends the
    user who rated least recently back to the checkpoint, with a warning."""
    domain = domain_id(9)
    client = RosClient(domain)
    models = client.collect('/stars/user_model', RELIABLE)
    process = start_node('stars_ros.ros.ranker', domain, {
        'checkpoint': tiny_checkpoint, 'record_folder': tmp_path, 'flush_interval': 0.2,
        'fold_in_max_ratings': 2, 'fold_in_max_users': 1}, tmp_path / 'ranker.log')
    try:
        client.wait_ready(process, START_TIMEOUT, {'scene_id': 'probe', 'graph': scenes[19]})
        _rank(client, scenes, 'stranger')
        for scene in scenes[:3]:
            client.feedback({'user_id': USER, 'scene_id': scene['identifier'], 'action': 'navigate', 'score': 1.0})
        assert client.wait(lambda: all(r.get('personalised_from') == 2
                                       for r in _rank(client, scenes, 'window').values()), 20)
        client.feedback({'user_id': 'other', 'scene_id': scenes[0]['identifier'], 'action': 'navigate', 'score': 0.0})
        assert client.wait(lambda: any(e['kind'] == 'user_models' and USER in e['message'] for e in client.errors), 20)
        assert all('personalised_from' not in r for r in _rank(client, scenes, 'evicted').values())
        # the executor solves 'other' once no scene waits: stopping before that would race it
        assert client.wait(lambda: any(m['user_id'] == 'other' for m in models), 20)
        assert stop(process, signal.SIGINT) == 0
    finally:
        if process.poll() is None:
            process.kill()
        client.close()
    with state.open_reader(tmp_path) as store:
        assert [(p['person'], p['ratings'], p['dropped']) for p in store.summary()] == [('other', 1, 0)]


def test_diagnostics_report_the_fold_in_work_and_the_waits_behind_it(tiny_checkpoint, scenes, tmp_path):
    """A burst of feedback, then at once another user's scene requests: /diagnostics counts
    the fold-in updates and reports any ranking that waited for them consistently. Whether
    one did wait depends on the timing, so that a ranking that waited is counted, with its
    wait, is checked on the core with a stepped clock (test/node/test_ranker_core.py)."""
    domain = domain_id(10)
    client = RosClient(domain)
    process = start_node('stars_ros.ros.ranker', domain, {
        'checkpoint': tiny_checkpoint, 'record_folder': tmp_path, 'diagnostics_period': 0.2}, tmp_path / 'ranker.log')
    try:
        client.wait_ready(process, START_TIMEOUT, {'scene_id': 'probe', 'graph': scenes[19]})
        _rank(client, scenes, 'rated scenes')
        for k in range(60):
            client.feedback({'user_id': f'rater-{k % 3}', 'scene_id': scenes[k % 6]['identifier'],
                             'action': 'navigate', 'score': float(k % 2)})
        for k in range(20):
            client.scene({'scene_id': f'other-{k}', 'user_id': 'other', 'graph': scenes[6 + k % 10]})
        assert client.wait(lambda: all(client.ranking_for(f'other-{k}') for k in range(20)), 30)
        assert all(client.ranking_for(f'other-{k}')['processing_ms'] > 0 for k in range(20))

        def periods():
            return [_ranker_values(d) for d in client.snapshot(client.diagnostics) if _ranker_values(d)]

        def burst_reported():  # the three raters solved
            return sum(int(p['period.fold_in_updates']) for p in periods()) >= 3
        assert client.wait(burst_reported, 30), periods()
        delayed = [p for p in periods() if int(p['period.rankings_delayed_by_fold_in'])]
        for p in delayed:
            assert 0 < float(p['period.fold_in_delay_ms.max']) <= float(p['period.delayed_processing_ms.max'])
            assert float(p['period.delayed_processing_ms.max']) <= float(p['period.processing_ms.max'])
        assert stop(process, signal.SIGINT) == 0
    finally:
        if process.poll() is None:
            process.kill()
        client.close()
