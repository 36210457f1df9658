"""Offline refit from MCAP logs or the node's state store: user mode equals the closed-form
fold-in, full mode trains, and bad logs give a report with counts instead of silent drops."""
import json
import shutil

import numpy as np
import pytest

from offline_training import refit
from stars_ros import recording
from stars_ros.model.checkpoint import load_checkpoint
from stars_ros.personalisation.foldin import FoldIn, Rating
from stars_ros.model.predictor import Predictor
from stars_ros.data.scene_source import read_scenes, scene_request
from stars_ros.state import PersonUpdate
from state_fill import fill_store

QOS = recording.qos_profile()


@pytest.fixture(scope='module')
def scenes(synthetic_root):
    return read_scenes(synthetic_root / 'raw' / 'f.jsonl')[:30]


def _write_session(folder, scenes, name='session', extra=()):
    """A bag as the node writes it: scene requests, then feedback on them (and ``extra``)."""
    expected = {'newbie': [], 'a': []}
    with recording.Recorder(folder, {}, name=name) as recorder:
        t = 10 ** 9
        for k, scene in enumerate(scenes[:12]):
            t += 10 ** 6
            recorder.write('/stars/scene', json.dumps({'scene_id': f's{k}', 'user_id': 'newbie', 'graph': scene}), t)
            t += 10 ** 6
            user = 'newbie' if k % 3 else 'a'
            score = scene['score'] / 100
            recorder.write('/stars/feedback', json.dumps({'user_id': user, 'scene_id': f's{k}', 'action': 'navigate',
                                                          'score': score}), t)
            expected[user].append(Rating(scene, 'navigate', score, f's{k}'))
        placements = scene_request('p0', scenes[20], user_id='newbie', placements=3)
        recorder.write('/stars/scene', json.dumps(placements), t + 1)
        label = placements['candidates'][1]['candidate']
        recorder.write('/stars/feedback', json.dumps({'user_id': 'newbie', 'scene_id': 'p0', 'candidate': label,
                                                      'score': 0.9}), t + 2)
        expected['newbie'].append(Rating(placements['candidates'][1]['graph'], 'navigate', 0.9, None))
        for topic, text in extra:
            t += 10 ** 6
            recorder.write(topic, text, t)
    return folder / name, expected


def test_user_mode_equals_the_closed_form_fold_in(tiny_checkpoint, scenes, tmp_path, capsys):
    bag, expected = _write_session(tmp_path, scenes)
    out = tmp_path / 'refit.pt'
    assert refit.main(['--checkpoint', str(tiny_checkpoint), '--logs', str(bag), '--out', str(out),
                       '--regularisation', '0.5']) == 0
    report = capsys.readouterr().out
    assert 'problems: none' in report and '13 usable ratings from 2 user(s)' in report
    parent, child = Predictor.load(tiny_checkpoint), Predictor.load(out)
    foldin = FoldIn(parent)
    assert child.knows_user('newbie') and not parent.knows_user('newbie')
    assert list(child.users[:len(parent.users)]) == list(parent.users)
    probe = [s for s in scenes[12:18]]
    for user in ('newbie', 'a'):
        online = foldin.fit(expected[user], user, 0.5)
        parent.set_user_model(user, online)  # what the node serves after folding in
        assert np.allclose(child.score(user, probe), parent.score(user, probe), atol=1e-5)
    assert not np.allclose(child.score('a', probe), Predictor.load(tiny_checkpoint).score('a', probe), atol=1e-4)
    assert np.array_equal(child.score('b', probe), parent.score('b', probe))  # other users untouched
    _, metadata = load_checkpoint(out)
    provenance = metadata['provenance']['refit']
    assert provenance['mode'] == 'user' and provenance['parent_fingerprint'] == parent.fingerprint
    assert provenance['ratings_per_user'] == {'newbie': 9, 'a': 4} and provenance['logs'] == [str(bag)]


def test_user_mode_from_the_state_store_solves_the_ratings_it_holds(tiny_checkpoint, scenes, tmp_path, capsys):
    """The store keeps a person's most recent ratings and how many older ones it dropped: the
    refit solves from those it holds, λ from the stored model, and says all of them were
    absorbed (a reload then keeps only newer feedback)."""
    _, expected = _write_session(tmp_path, scenes)
    parent = Predictor.load(tiny_checkpoint)
    foldin = FoldIn(parent)
    ratings = {user: [Rating(r.scene, r.action, r.score, r.scene_id, f'{user}-{k}', k, '/ranker')
                      for k, r in enumerate(held)] for user, held in expected.items()}
    models = {'newbie': foldin.fit(ratings['newbie'], 'newbie', 0.5), 'a': None}
    fill_store(tmp_path / 'records', parent.fingerprint, [
        PersonUpdate(user, models[user], parent.fingerprint, ratings[user], 3 if user == 'a' else 0, [], True)
        for user in ratings])
    out = tmp_path / 'refit.pt'
    assert refit.main(['--checkpoint', str(tiny_checkpoint), '--state', str(tmp_path / 'records'),
                       '--out', str(out)]) == 0
    assert 'read 1 state store, 13 messages; 13 usable ratings from 2 user(s)' in capsys.readouterr().out
    child = Predictor.load(out)
    probe = scenes[12:18]
    for user, regularisation in (('newbie', 0.5), ('a', 0.0)):
        parent.set_user_model(user, foldin.fit(ratings[user], user, regularisation))
        assert np.allclose(child.score(user, probe), parent.score(user, probe), atol=1e-5)
    provenance = load_checkpoint(out)[1]['provenance']['refit']
    assert provenance['ratings_per_user'] == {'newbie': 9, 'a': 4 + 3} and provenance['state'] == str(
        tmp_path / 'records')
    assert refit.main(['--checkpoint', str(tiny_checkpoint), '--state', str(tmp_path / 'none'),
                       '--out', str(out)]) == 2


def test_default_regularisation_is_the_one_the_node_logged(tiny_checkpoint, scenes, tmp_path):
    logged = {'user_id': 'newbie', 'p_u': [0.0] * 16, 'b_u': 0.0, 'n_ratings': 1, 'fingerprint': 'ab' * 32,
              'regularisation': 3.0}
    bag, expected = _write_session(tmp_path, scenes, extra=[('/stars/user_model', json.dumps(logged))])
    out = tmp_path / 'refit.pt'
    assert refit.main(['--checkpoint', str(tiny_checkpoint), '--logs', str(bag), '--out', str(out)]) == 0
    _, metadata = load_checkpoint(out)
    assert metadata['provenance']['refit']['regularisation'] == {'newbie': 3.0, 'a': 0.0}  # 0: the posterior
    assert metadata['user_prior']['covariance'] == 'ledoit-wolf'  # the parent's prior goes with its weights
    parent = Predictor.load(tiny_checkpoint)
    parent.set_user_model('newbie', FoldIn(parent).fit(expected['newbie'], 'newbie', 3.0))
    assert np.allclose(Predictor.load(out).score('newbie', scenes[:3]), parent.score('newbie', scenes[:3]), atol=1e-5)


def test_bad_logs_are_reported_with_counts(tiny_checkpoint, scenes, tmp_path, capsys):
    extra = [('/chatter', 'hello'), ('/chatter', 'again'), ('/stars/feedback', json.dumps(
        {'user_id': 'newbie', 'scene_id': 'never-seen', 'action': 'navigate', 'score': 0.3})),
        ('/stars/feedback', json.dumps({'user_id': 'newbie', 'scene_id': 's1', 'action': 'fly', 'score': 0.3})),
        ('/stars/feedback', json.dumps({'user_id': 'newbie', 'scene_id': 'p0', 'candidate': 'nowhere', 'score': 0.3})),
        ('/stars/feedback', '{"user_id": "newbie", "scene_id": '),
        ('/stars/ranking', '{"not": "needed"}')]
    bag, _ = _write_session(tmp_path, scenes, extra=extra)
    damaged, _ = _write_session(tmp_path, scenes, name='damaged')
    mcap = next(damaged.glob('*.mcap'))
    data = mcap.read_bytes()
    mcap.write_bytes(data[:len(data) // 2])  # a hard kill before the recorder's repair
    out = tmp_path / 'refit.pt'
    assert refit.main(['--checkpoint', str(tiny_checkpoint), '--logs', str(bag), str(damaged), str(tmp_path / 'gone'),
                       '--out', str(out)]) == 0
    report = capsys.readouterr().out
    assert 'foreign topic: 2' in report and '/chatter' in report
    assert 'feedback for a scene never recorded: 1' in report and 'never-seen' in report
    assert 'unknown action: 1' in report and "'fly'" in report
    assert 'feedback that does not match its scene: 1' in report and 'nowhere' in report
    assert 'unusable feedback message: 1' in report
    assert 'truncated or damaged file: 1' in report and 'no MCAP files: 1' in report
    assert 'not needed for a refit: stars/ranking 1' in report
    assert out.exists()


def test_nothing_usable_exits_non_zero_without_writing(tiny_checkpoint, tmp_path, capsys):
    with recording.Recorder(tmp_path, {}, name='empty') as recorder:
        recorder.write('/chatter', 'hello', 10 ** 9)
        recorder.write('/stars/feedback', json.dumps({'user_id': 'x', 'scene_id': 'nope', 'action': 'navigate',
                                                      'score': 0.1}), 2 * 10 ** 9)
    out = tmp_path / 'refit.pt'
    assert refit.main(['--checkpoint', str(tiny_checkpoint), '--logs', str(tmp_path / 'empty'),
                       '--out', str(out)]) == 1
    captured = capsys.readouterr()
    assert 'no usable feedback' in captured.err and 'feedback for a scene never recorded: 1' in captured.out
    assert not out.exists()
    assert refit.main(['--checkpoint', str(tmp_path / 'missing.pt'), '--logs', str(tmp_path), '--out', str(out)]) == 2


def test_full_mode_fine_tunes_from_the_user_solution(tiny_checkpoint, scenes, tmp_path, capsys):
    bag, _ = _write_session(tmp_path, scenes)
    user_out, full_out = tmp_path / 'user.pt', tmp_path / 'full.pt'
    assert refit.main(['--checkpoint', str(tiny_checkpoint), '--logs', str(bag), '--out', str(user_out)]) == 0
    assert refit.main(['--checkpoint', str(tiny_checkpoint), '--logs', str(bag), '--out', str(full_out),
                       '--mode', 'full', '--epochs', '2']) == 0
    assert 'full fine-tune: 2 joint epochs on 13 ratings' in capsys.readouterr().out
    full, user = Predictor.load(full_out), Predictor.load(user_out)
    assert full.knows_user('newbie')
    assert not np.allclose(full.score('newbie', scenes[:3]), user.score('newbie', scenes[:3]), atol=1e-6)
    _, metadata = load_checkpoint(full_out)
    assert metadata['provenance']['refit']['mode'] == 'full'
    assert len(metadata['provenance']['refit']['fine_tune_losses']) == 2
    shutil.rmtree(bag)


def test_a_score_off_the_rating_scale_in_a_bag_is_refused_naming_the_scale(tiny_checkpoint, scenes, tmp_path,
                                                                           capsys):
    low, high = Predictor.load(tiny_checkpoint).rating_scale
    raw = json.dumps({'user_id': 'a', 'scene_id': 's3', 'action': 'navigate', 'score': high + 79})
    bag, _ = _write_session(tmp_path, scenes, extra=[('/stars/feedback', raw)])
    out = tmp_path / 'refit.pt'
    assert refit.main(['--checkpoint', str(tiny_checkpoint), '--logs', str(bag), '--out', str(out)]) == 0
    report = capsys.readouterr().out
    assert 'out_of_scale' in report and f'outside the rating scale [{low:g}, {high:g}]' in report
    assert '13 usable ratings from 2 user(s)' in report  # the session's own, without it
    _, metadata = load_checkpoint(out)
    assert metadata['provenance']['refit']['ratings_per_user'] == {'newbie': 9, 'a': 4}
