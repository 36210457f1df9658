"""The ranker's state file (user_models.json): round trip, the files earlier versions wrote,
another checkpoint's users and corrupted files refused with a reason, the writer thread."""
import dataclasses
import json
import re

import numpy as np
import pytest

from stars_ros.personalisation import user_state
from stars_ros.personalisation.foldin import Rating, UserModel
from stars_ros.personalisation.user_state import STATE_FILE, StateWriter, UserStateError
from waiting import wait_for

SCENE = {'identifier': 's1', 'humans': [{'id': 1, 'xPos': 0.5, 'yPos': -1.0, 'orientation': 90}]}
FINGERPRINT = 'ab' * 32


def _users():
    models = {'ann': UserModel(np.array([0.25, -1.5]), 0.125, 2, 1.0), 'bob': UserModel(np.zeros(2), -0.5, 1, 0.05)}
    histories = {'ann': ([Rating(SCENE, 'navigate', 0.75, 's1', 'r1', 10, '/ranker'),
                          Rating(SCENE, 'navigate', 0.5, None, 'r2', 20, '/ranker')], 3),
                 'bob': ([Rating([0.0, 1.5], 'wait', 1.0, None, 'r3', 30, '/ranker')], 0)}
    return models, histories


def _without_ids(histories: dict) -> dict:
    return {u: ([dataclasses.replace(r, rating_id='', stamp=0, origin='') for r in ratings], dropped)
            for u, (ratings, dropped) in histories.items()}


def _same_models(loaded: dict, expected: dict):
    assert list(loaded) == list(expected)
    for user_id, model in expected.items():
        got = loaded[user_id]
        assert np.array_equal(got.p, model.p) and got.p.dtype == np.float64
        assert (got.b, got.n_ratings, got.regularisation) == (model.b, model.n_ratings, model.regularisation)


def test_round_trip_keeps_models_histories_and_dropped_counts(tmp_path):
    models, histories = _users()
    path = tmp_path / 'records' / STATE_FILE  # the folder is created
    peers = {'ann': [Rating(SCENE, 'navigate', 0.25, 's1', 'p1', 15, '/robot2/ranker')]}
    user_state.save(path, user_state.to_dict(FINGERPRINT, models, histories, peers))
    loaded = user_state.load(path, FINGERPRINT)
    assert loaded.fingerprint == FINGERPRINT
    _same_models(loaded.models, models)
    assert loaded.histories == histories and loaded.peers == peers
    assert [p.name for p in path.parent.iterdir()] == [STATE_FILE]  # no temporary left


def test_a_user_without_history_is_saved_with_an_empty_one(tmp_path):
    models, histories = _users()
    del histories['bob']
    state = user_state.to_dict(FINGERPRINT, models, histories)
    assert state['users']['bob']['ratings'] == [] and state['users']['bob']['ratings_dropped'] == 0
    assert set(state) == {'format', 'version', 'fingerprint', 'users'} and state['format'] == user_state.FORMAT


def test_files_written_by_earlier_versions_load(tmp_path):
    """The exact text the node wrote before the state file had a module of its own (users
    spliced in one by one), and a version-1 file from before ratings_dropped existed."""
    path = tmp_path / STATE_FILE
    path.write_text(
        '{"format":"stars_ros.user_models","version":1,"fingerprint":"' + FINGERPRINT + '","users":{"ann":'
        '{"p_u":[0.25,-1.5],"b_u":0.125,"n_ratings":2,"regularisation":1.0,"ratings_dropped":3,"ratings":['
        '{"scene":' + json.dumps(SCENE, separators=(',', ':')) + ',"action":"navigate","score":0.75,"scene_id":"s1"},'
        '{"scene":' + json.dumps(SCENE, separators=(',', ':')) + ',"action":"navigate","score":0.5,"scene_id":null}]},'
        '"bob":{"p_u":[0.0,0.0],"b_u":-0.5,"n_ratings":1,"regularisation":0.05,"ratings_dropped":0,"ratings":['
        '{"scene":[0.0,1.5],"action":"wait","score":1.0,"scene_id":null}]}}}')
    models, histories = _users()
    loaded = user_state.load(path, FINGERPRINT)
    _same_models(loaded.models, models)
    assert _without_ids(loaded.histories) == _without_ids(histories) and loaded.peers == {}
    ids = [r.rating_id for ratings, _ in loaded.histories.values() for r in ratings]
    assert len(set(ids)) == 3 and all(ids)  # named, each differently, and the same at every load
    assert ids == [r.rating_id for ratings, _ in user_state.load(path, FINGERPRINT).histories.values() for r in ratings]
    older = {'format': user_state.FORMAT, 'version': 1, 'fingerprint': FINGERPRINT,
             'users': {'ann': {**models['ann'].to_json(), 'ratings': [{'scene': SCENE, 'action': 'navigate',
                                                                       'score': 1, 'scene_id': 's1'}]}}}
    path.write_text(json.dumps(older))
    assert _without_ids(user_state.load(path, FINGERPRINT).histories) == {
        'ann': ([Rating(SCENE, 'navigate', 1.0, 's1')], 0)}


def test_users_of_another_checkpoint_are_refused_naming_both(tmp_path):
    path = tmp_path / STATE_FILE
    user_state.save(path, user_state.to_dict(FINGERPRINT, *_users()))
    with pytest.raises(UserStateError, match=f'solved against checkpoint {FINGERPRINT[:12]}, not the served '
                                             f'cdcdcdcdcdcd: folded-in users are not restored'):
        user_state.load(path, 'cd' * 32)


@pytest.mark.parametrize('text', [
    '{"format":"stars_ros.user_models","version":1,"fingerprint":"abab',  # truncated
    '[]', '{"format":"something else","users":{}}', '{"format":"stars_ros.user_models","users":{}}',
    '{"format":"stars_ros.user_models","fingerprint":"x","users":{"ann":{"p_u":[0],"b_u":0}}}',
    '{"format":"stars_ros.user_models","fingerprint":"x","users":{"ann":{"p_u":[0],"b_u":0,"n_ratings":1,'
    '"regularisation":1,"ratings":[{"scene":{},"action":"a","score":"high"}]}}}',
    '{"format":"stars_ros.user_models","fingerprint":"x","users":[]}',
])
def test_a_corrupted_file_is_refused_with_a_reason(tmp_path, text):
    path = tmp_path / STATE_FILE
    path.write_text(text)
    reason = f'cannot read {re.escape(str(path))}: .+; folded-in users are not restored'
    with pytest.raises(UserStateError, match=reason):
        user_state.load(path, 'x')


def test_no_file_is_no_users(tmp_path):
    assert user_state.load(tmp_path / STATE_FILE, FINGERPRINT) is None


def test_the_writer_saves_when_asked_and_once_more_on_close(tmp_path):
    models, histories = _users()
    states = iter([user_state.to_dict(FINGERPRINT, models, {}), user_state.to_dict(FINGERPRINT, models, histories)])
    path = tmp_path / STATE_FILE
    writer = StateWriter(path, lambda: next(states), interval=60.0, on_error=pytest.fail)
    writer.request()
    assert wait_for(path.exists, 30), 'the first request was never written'
    assert user_state.load(path, FINGERPRINT).histories == {'ann': ([], 0), 'bob': ([], 0)}
    writer.request()  # within the interval: written at its end, or at close
    writer.close()
    assert user_state.load(path, FINGERPRINT).histories == histories


def test_the_writer_reports_a_disk_that_refuses(tmp_path):
    (tmp_path / 'file').write_text('')
    errors = []
    writer = StateWriter(tmp_path / 'file' / STATE_FILE, lambda: user_state.to_dict(FINGERPRINT, {}, {}), 0.01,
                         errors.append)
    writer.request()
    writer.close()
    assert errors and errors[0].startswith(f"could not write {tmp_path / 'file' / STATE_FILE}: ")
