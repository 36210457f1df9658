"""The node's state store (state.db): people round trip with their posteriors, only the
changed rows written, scenes kept once, another checkpoint's people not restored, the import
of user_models.json and feedback.jsonl (once, the files kept), a store another process holds
refused naming it, a full disk retried without losing committed or waiting feedback, and
the inspection command."""
import json
import os
import sqlite3
import subprocess
import sys
import textwrap
import threading

import numpy as np
import pytest

from stars_ros.personalisation.foldin import Rating, UserModel
from stars_ros.errors import StoreError
from stars_ros.recording import __main__ as inspect_cli
from stars_ros.state import migration, schema, store as state_store
from stars_ros.state import Deferred, loaded
from stars_ros.errors import StoreLockedError
from stars_ros.state import PersonUpdate, StateStore, open_reader

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SCENE = {'identifier': 's1', 'humans': [{'id': 1, 'xPos': 0.5, 'yPos': -1.0, 'orientation': 90}]}
OTHER_SCENE = {'identifier': 's2', 'humans': [{'id': 1, 'xPos': 1.5, 'yPos': 2.0, 'orientation': 0}]}
FINGERPRINT = 'ab' * 32
SIGNED = {'user_id': 'ann', 'auth': {'key': 'k1', 'mac': 'r1'}}


def _model(dim=2, covariance=True):
    p = np.array([0.25, -1.5][:dim])
    return UserModel(p, 0.125, 2, 0.0, np.eye(dim + 1) * 0.5 if covariance else None)


def _ann():
    return [Rating(SCENE, 'navigate', 0.75, 's1', 'r1', 10, '/ranker', SIGNED),
            Rating(SCENE, 'navigate', 0.5, None, 'r2', 20, '/ranker')]


def _open(folder, errors=None):
    return StateStore(folder, '/ranker', on_error=(errors.append if errors is not None else pytest.fail),
                      retry_interval=0.01)


def _committed(store, entry, person=None):
    done = threading.Event()
    store.when_committed(store.write_person(person, [(entry, 'bag')]), done.set)
    assert done.wait(30), 'never committed'


def test_people_round_trip_with_posterior_ratings_and_peers(tmp_path):
    store = _open(tmp_path / 'records')  # the folder is created
    assert store.load(FINGERPRINT) == ([], None)
    peers = [Rating(SCENE, 'navigate', 0.25, 's1', 'p1', 15, '/robot2/ranker')]
    store.write_person(PersonUpdate('ann', _model(), FINGERPRINT, _ann(), 3, peers, True))
    store.write_person(PersonUpdate('bob', None, FINGERPRINT, [Rating([0.0, 1.5], 'wait', 1.0, None, 'r3', 30, '/r')],
                                   0, [], False))
    assert store.close() == []
    store = _open(tmp_path / 'records')
    people, problem = store.load(FINGERPRINT)
    assert problem is None and [p.user_id for p in people] == ['ann', 'bob']
    assert people[0].ratings.load() == _ann() and people[1].peer_ratings == []  # read when first used
    store.close()
    with open_reader(tmp_path / 'records') as reader:
        ann, bob = reader.people()
    assert np.array_equal(ann.model.p, _model().p) and np.array_equal(ann.model.covariance, _model().covariance)
    assert (ann.model.b, ann.model.n_ratings, ann.fingerprint, ann.dropped, ann.solved) == (0.125, 2, FINGERPRINT, 3,
                                                                                            True)
    assert ann.ratings == _ann() and ann.peer_ratings == peers
    assert ann.ratings[0].scene is ann.ratings[1].scene  # one scene content, one object
    assert bob.model is None and not bob.solved and bob.ratings[0].scene == [0.0, 1.5]


def test_an_update_writes_the_rows_it_changes_and_scenes_once(tmp_path):
    store = _open(tmp_path)
    store.load(FINGERPRINT)
    ratings = _ann()
    store.write_person(PersonUpdate('ann', None, FINGERPRINT, ratings, 0, [], False))
    newer = Rating(OTHER_SCENE, 'navigate', 0.1, None, 'r4', 40, '/ranker')
    store.write_person(PersonUpdate('ann', _model(), FINGERPRINT, ratings[1:] + [newer], 1, [], True))
    store.write_person(PersonUpdate('cat', None, FINGERPRINT, [newer], 0, [], False))
    store.close()
    database = sqlite3.connect(tmp_path / schema.DATABASE)
    assert database.execute('SELECT person, id FROM ratings ORDER BY position').fetchall() == [
        ('ann', 'r2'), ('ann', 'r4'), ('cat', 'r4')]
    assert sorted(database.execute('SELECT refs FROM scenes')) == [(1,), (2,)]
    assert database.execute("SELECT dropped, solved FROM people WHERE person = 'ann'").fetchone() == (1, 1)
    database.close()
    store = _open(tmp_path)
    store.load(FINGERPRINT)
    store.forget_person('ann')
    store.forget_person('cat')
    store.close()
    with open_reader(tmp_path) as reader:
        assert reader.people() == [] and reader.summary() == []
    database = sqlite3.connect(tmp_path / schema.DATABASE)
    assert database.execute('SELECT COUNT(*) FROM scenes').fetchone() == (0,)  # no rating names them
    database.close()


def test_the_h_of_rated_scenes_is_kept_per_checkpoint_until_no_rating_names_the_scene(tmp_path):
    store = _open(tmp_path)
    store.load(FINGERPRINT)
    ratings = _ann()  # both of SCENE
    newer = Rating(OTHER_SCENE, 'navigate', 0.1, None, 'r4', 40, '/ranker')
    h = np.array([0.5, -0.25, 1.0])
    store.write_person(PersonUpdate('ann', None, FINGERPRINT, ratings, 0, [], False, {id(SCENE): h}))
    store.write_person(PersonUpdate('ann', None, FINGERPRINT, ratings + [newer], 0, [], False,
                                    {id(SCENE): h + 1.0, id(OTHER_SCENE): -h}))  # SCENE's first h stays
    store.close()
    store = _open(tmp_path)
    [ann] = store.load(FINGERPRINT)[0]
    restored = loaded(ann.ratings)
    found = store.encodings([r.scene for r in restored], FINGERPRINT)
    assert set(found) == {id(restored[0].scene), id(restored[2].scene)} and restored[0].scene is restored[1].scene
    np.testing.assert_array_equal(found[id(restored[0].scene)], h)
    np.testing.assert_array_equal(found[id(restored[2].scene)], -h)
    assert store.encodings([r.scene for r in restored], 'cd' * 32) == {}  # another checkpoint's h differ
    assert store.encodings([dict(SCENE)], FINGERPRINT) == {}  # a scene the store did not give
    store.write_person(PersonUpdate('ann', None, FINGERPRINT, ratings, 0, [], False))
    store.close()
    database = sqlite3.connect(tmp_path / schema.DATABASE)
    assert database.execute('SELECT COUNT(*) FROM encodings').fetchone() == (1,)  # OTHER_SCENE's went with it
    database.close()


def test_people_of_another_checkpoint_are_not_restored_and_replaced_by_the_first_update(tmp_path):
    store = _open(tmp_path)
    store.load(FINGERPRINT)
    store.write_person(PersonUpdate('ann', _model(), FINGERPRINT, _ann(), 0, [], True))
    store.close()
    store = _open(tmp_path)
    people, problem = store.load('cd' * 32)
    assert people == [] and problem == (f'{tmp_path / "state.db"} holds people solved against checkpoint '
                                        f'{FINGERPRINT[:12]}, not the served cdcdcdcdcdcd: folded-in users are not '
                                        'restored')
    store.close()
    with open_reader(tmp_path) as reader:  # nothing written yet: a restart with the right checkpoint has them
        assert [p['person'] for p in reader.summary()] == ['ann']
    store = _open(tmp_path)
    store.load('cd' * 32)
    store.write_person(PersonUpdate('bob', None, 'cd' * 32, [Rating(SCENE, 'navigate', 1.0, None, 'b1', 5, '/r')], 0,
                                   [], False))
    store.close()
    with open_reader(tmp_path) as reader:
        assert reader.fingerprint == 'cd' * 32 and [p['person'] for p in reader.summary()] == ['bob']


def test_feedback_is_reported_committed_with_the_rating_it_gave(tmp_path):
    entry = {'topic': '/stars/feedback', 'log_time': 7, 'data': '{"score": 1}'}
    seen_in_store = []

    def on_commit(committed):  # runs once the transaction is: a reader sees feedback and rating
        with open_reader(tmp_path) as reader:
            seen_in_store.append((reader.feedback(), [len(p.ratings) for p in reader.people()]))
    store = StateStore(tmp_path, '/ranker', on_error=pytest.fail, on_feedback_committed=on_commit)
    store.load(FINGERPRINT)
    store.write_person(PersonUpdate('ann', None, FINGERPRINT, _ann(), 0, [], False), [(entry, 'bag')])
    assert store.close() == []
    assert seen_in_store == [([{**entry, 'bag': 'bag'}], [2])]
    assert store.uncommitted_feedback == 0


def test_a_full_disk_is_reported_and_everything_waits_in_order_until_it_has_room(tmp_path, monkeypatch):
    """SQLite's own 'database or disk is full' (max_page_count stands in for the disk)."""
    connections = []
    connect = sqlite3.connect

    def keep(*args, **kwargs):
        connection = connect(*args, **kwargs)
        connections.append(connection)
        return connection
    monkeypatch.setattr(state_store.sqlite3, 'connect', keep)
    errors, recovered, committed = [], threading.Event(), []
    store = StateStore(tmp_path, '/ranker', errors.append, lambda text: recovered.set(), retry_interval=0.01,
                       on_feedback_committed=committed.append)
    store.load(FINGERPRINT)
    writer = connections[0]
    pages = writer.execute('PRAGMA page_count').fetchone()[0]
    writer.execute(f'PRAGMA max_page_count = {pages}')
    for k in range(3):
        store.write_person(None, [({'topic': '/stars/feedback', 'log_time': k, 'data': 'x' * 5000}, 'bag')])
    assert _wait(lambda: errors)
    assert 'database or disk is full' in errors[0] and not store.healthy and not committed
    assert store.uncommitted_feedback == 3
    writer.execute('PRAGMA max_page_count = 1000000')  # room again
    assert recovered.wait(30) and store.healthy
    assert [e['log_time'] for e in committed] == [0, 1, 2] and store.uncommitted_feedback == 0
    assert store.close() == [] and len(errors) == 1  # said once


def _wait(condition, timeout=30):
    from waiting import wait_for
    return wait_for(condition, timeout)


def test_a_folder_that_cannot_be_created_keeps_feedback_in_memory_and_close_returns_it(tmp_path):
    (tmp_path / 'file').write_text('')
    errors = []
    store = _open(tmp_path / 'file' / 'records', errors)
    assert errors and errors[0].startswith(f"cannot open the state store {tmp_path / 'file' / 'records' / 'state.db'}")
    assert store.load(FINGERPRINT) == ([], None)
    entry = {'topic': '/stars/feedback', 'log_time': 2, 'data': '{"score": 1}'}
    store.write_person(None, [(entry, 'bag')])
    assert store.uncommitted_feedback == 1
    assert store.close() == [entry] and len(errors) == 1


HOLDER = textwrap.dedent('''
    import sys
    from stars_ros.state.store import StateStore
    store = StateStore(sys.argv[1], '/robot1/ranker', on_error=sys.exit)
    print('open', flush=True)
    sys.stdin.readline()
''')


def test_a_store_another_process_holds_is_refused_naming_it(tmp_path):
    holder = subprocess.Popen([sys.executable, '-c', HOLDER, str(tmp_path)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True, env=dict(os.environ, PYTHONPATH=REPO))
    try:
        assert holder.stdout.readline() == 'open\n'
        with pytest.raises(StoreLockedError, match=rf'the state store in {tmp_path} is held by /robot1/ranker \(pid '
                                                   rf'{holder.pid} on .+\): one store per node'):
            _open(tmp_path)
    finally:
        holder.kill()
        holder.wait()
    _open(tmp_path).close()  # the kill released it


def _legacy_files(folder):
    """What the node wrote before the store: user_models.json and a bag's feedback.jsonl,
    the last line cut by a hard kill."""
    users = {'ann': {**_model(covariance=False).to_json(), 'ratings_dropped': 3,
                     'ratings': [r.to_json() for r in _ann()],
                     'peer_ratings': [Rating(SCENE, 'navigate', 0.25, 's1', 'p1', 15, '/robot2/ranker').to_json()]},
             'bob': {**UserModel(np.zeros(2), -0.5, 1, 0.05).to_json(),
                     'ratings': [{'scene': [0.0, 1.5], 'action': 'wait', 'score': 1.0, 'scene_id': None}]}}
    (folder / migration.STATE_FILE).write_text(json.dumps(
        {'format': migration.FORMAT, 'version': 1, 'fingerprint': FINGERPRINT, 'users': users}))
    bag = folder / 'stars_2026_01_01-00_00_00'
    bag.mkdir()
    lines = [json.dumps({'topic': '/stars/feedback', 'log_time': k, 'data': f'{{"score": {k}}}'}) for k in (1, 2)]
    (bag / migration.JOURNAL).write_text('\n'.join(lines) + '\n{"topic": "/stars/fe')
    return bag


def test_the_files_of_earlier_versions_are_imported_once_and_kept(tmp_path):
    bag = _legacy_files(tmp_path)
    before = {p.name: p.read_bytes() for p in (tmp_path / migration.STATE_FILE, bag / migration.JOURNAL)}
    progress = []
    store = StateStore(tmp_path, '/ranker', on_error=pytest.fail, on_progress=progress.append)
    assert store.imported == [f'2 people from {tmp_path / migration.STATE_FILE}',
                              f'2 feedback messages from {bag / migration.JOURNAL}']
    assert progress[0].startswith(f'importing {tmp_path / migration.STATE_FILE} (0 MB, kept by an earlier version)')
    assert progress[1:] == [f'imported {k} of 2 people from {tmp_path / migration.STATE_FILE}' for k in (1, 2)]
    people, problem = store.load(FINGERPRINT)
    store.close()
    assert problem is None and {p.user_id for p in people} == {'ann', 'bob'}
    with open_reader(tmp_path) as reader:
        people = reader.people()
    ann = next(p for p in people if p.user_id == 'ann')
    assert ann.ratings == _ann() and ann.dropped == 3 and [r.rating_id for r in ann.peer_ratings] == ['p1']
    assert ann.model.covariance is None and not ann.solved  # solved again after the restart
    bob = next(p for p in people if p.user_id == 'bob')
    assert len(bob.ratings) == 1 and bob.ratings[0].rating_id  # named, as the file was read before
    with open_reader(tmp_path) as reader:
        assert [json.loads(e['data'])['score'] for e in reader.feedback(bag.name)] == [1, 2]
    assert {p.name: p.read_bytes() for p in (tmp_path / migration.STATE_FILE, bag / migration.JOURNAL)} == before
    store = _open(tmp_path)  # once
    assert store.imported == []
    store.close()
    with open_reader(tmp_path) as reader:
        assert len(reader.feedback()) == 2 and len(reader.summary()) == 2


@pytest.mark.parametrize('text', ['{"format":"stars_ros.user_models","version":1,"fingerprint":"abab', '[]',
                                  '{"format":"stars_ros.user_models","fingerprint":"x","users":[]}'])
def test_a_corrupted_state_file_is_not_imported_and_said_so(tmp_path, text):
    (tmp_path / migration.STATE_FILE).write_text(text)
    store = _open(tmp_path)
    people, problem = store.load(FINGERPRINT)
    store.close()
    assert people == [] and problem.startswith(f'cannot read {tmp_path / migration.STATE_FILE}: ')
    assert problem.endswith('its folded-in users are not imported')


def test_the_inspection_command_lists_people_and_their_ratings(tmp_path, capsys):
    store = _open(tmp_path)
    store.load(FINGERPRINT)
    store.write_person(PersonUpdate('ann', _model(), FINGERPRINT, _ann(), 0, [], True))
    _committed(store, {'topic': '/stars/feedback', 'log_time': 1, 'data': '{}'})
    store.close()
    assert inspect_cli.main(['state', str(tmp_path), '--json']) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown['schema_version'] == schema.SCHEMA_VERSION and shown['fingerprint'] == FINGERPRINT
    assert shown['feedback'] == 1
    [ann] = shown['people']
    assert (ann['person'], ann['ratings'], ann['peer_ratings'], ann['model'], ann['solved']) == (
        'ann', 2, 0, True, True)
    assert inspect_cli.main(['state', str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert 'ann' in text and '1 people' in text
    assert inspect_cli.main(['state', str(tmp_path / 'none')]) == 1


def test_a_damaged_store_is_a_store_error_saying_what_to_do(tmp_path, capsys):
    (tmp_path / schema.DATABASE).write_bytes(b'not a database, ' * 512)
    with pytest.raises(StoreError, match=f'cannot read the state store {tmp_path / schema.DATABASE}: .*check '
                                         'that it is a stars_ros state.db'):
        open_reader(tmp_path)
    assert inspect_cli.main(['state', str(tmp_path)]) == 1  # said in one line, no traceback
    assert capsys.readouterr().err.startswith(f'error: cannot read the state store {tmp_path}')


def test_a_version_1_store_is_upgraded_keeping_every_covariance(tmp_path):
    """Version 1 kept each covariance in ``people``: reading anybody's later columns read it."""
    database = sqlite3.connect(tmp_path / schema.DATABASE)
    database.executescript('''
        CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
        CREATE TABLE people (
            person TEXT PRIMARY KEY, fingerprint TEXT, p BLOB, b REAL, n_ratings INTEGER, regularisation REAL,
            covariance BLOB, solved INTEGER NOT NULL, dropped INTEGER NOT NULL, ratings INTEGER NOT NULL,
            peer_ratings INTEGER NOT NULL, rated INTEGER NOT NULL, updated REAL NOT NULL);''')
    model = _model()
    database.execute("INSERT INTO meta VALUES ('schema_version', '1')")
    database.execute(f"INSERT INTO meta VALUES ('fingerprint', '{FINGERPRINT}')")
    database.execute('INSERT INTO people VALUES (?, ?, ?, ?, ?, ?, ?, 1, 0, 0, 0, 1, 0.0)',
                     ('ann', FINGERPRINT, model.p.tobytes(), model.b, 2, 0.0, model.covariance.tobytes()))
    database.commit()
    database.close()
    progress = []
    store = StateStore(tmp_path, '/ranker', on_error=pytest.fail, on_progress=progress.append)
    [ann], problem = store.load(FINGERPRINT)
    assert problem is None and progress == [f'upgrading {tmp_path / schema.DATABASE} from schema version 1 '
                                            'to 2 (covariances in a table of their own)']
    assert isinstance(ann.model.covariance, Deferred)  # read when first used
    assert np.array_equal(loaded(ann.model.covariance), model.covariance) and np.array_equal(ann.model.p, model.p)
    store.close()
    with open_reader(tmp_path) as reader:
        assert reader.meta()['schema_version'] == str(schema.SCHEMA_VERSION)
        [ann] = reader.people()
    assert np.array_equal(ann.model.covariance, model.covariance)
