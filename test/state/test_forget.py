"""Forgetting a person (docs/privacy.md): after it, no byte of the record folder holds their
id, neither the state store's files (database, write-ahead log, shared memory) nor any bag
record by record with its chunks decompressed; everyone else is as they were; a refit from
a bag copied before leaves them out; a kill at any moment of it is finished by a re-run."""
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from mcap.records import Chunk
from mcap.stream_reader import StreamReader

from stars_ros import StarsRecommender, messages, recording, state
from stars_ros.data.scene_source import read_scenes, scene_request
from stars_ros.personalisation.refit import forgotten_in, read_logs
from stars_ros.recording import erasure
from core_harness import Node, drain, make_core, published_models
from forget_search import bag_records, holds, store_bytes

FORGOTTEN = 'p2'
OTHERS = ('p21', 'ann-7')  # p21: an id that holds the forgotten one, which must stay


def messages_of(folder: Path) -> list:
    """(bag, topic, data bytes, log time) of every message, in file order."""
    found = []
    for bag in sorted(p for p in folder.iterdir() if p.is_dir() and list(p.glob('*.mcap'))):
        for topic, decoded, log_time in recording.read_decoded(bag):
            found.append((bag.name, topic, getattr(decoded, 'data', None), log_time))
    return found


def populate(folder: Path, checkpoint, scenes, sessions: int = 2, ratings: int = 3):
    """A record folder as a node leaves it: ``sessions`` bags, each person rating scenes."""
    for session in range(sessions):
        node = Node()
        core = make_core(node, checkpoint, record_folder=str(folder), flush_interval=60.0)
        for n, scene in enumerate(scenes[:ratings]):
            for k, user_id in enumerate((FORGOTTEN, *OTHERS)):
                scene_id = f'scene-{k}-{session}-{n}'  # not named after the person: a search finds the person only
                core.accept_scene(messages.dumps(scene_request(scene_id, scene, user_id)), 0)
                drain(core)
                core.accept_feedback(messages.dumps({'user_id': user_id, 'scene_id': scene_id, 'action': 'navigate',
                                                     'score': 0.25 + 0.1 * n}))
                drain(core)
        core.close()


@pytest.fixture(scope='module')
def scenes(synthetic_root):
    return read_scenes(synthetic_root / 'raw' / 'h.jsonl')[:4]


@pytest.fixture
def folder(tmp_path, tiny_checkpoint, scenes):
    populate(tmp_path / 'records', tiny_checkpoint, scenes)
    return tmp_path / 'records'


def _stored(folder: Path) -> dict:
    with state.open_reader(folder) as reader:
        return {p.user_id: ([r.to_json() for r in p.ratings], p.model.to_json() if p.model else None)
                for p in reader.people()}


def test_a_forgotten_person_is_in_no_byte_of_the_folder_and_everyone_else_is_unchanged(folder):
    before_store, before_bags = store_bytes(folder), bag_records(folder)
    assert holds(before_store['state.db'] + before_store.get('state.db-wal', b''), FORGOTTEN)  # the shm holds
    # only the log's index, never a row
    assert any(holds(record, FORGOTTEN) for record in before_bags)
    others_stored = {u: v for u, v in _stored(folder).items() if u != FORGOTTEN}
    others_messages = [m for m in messages_of(folder) if not holds((m[2] or '').encode(), FORGOTTEN)]
    assert FORGOTTEN in _stored(folder) and set(others_stored) == set(OTHERS)

    removed = erasure.forget(folder, FORGOTTEN)

    assert removed['state_store']['ratings'] == 6 and removed['state_store']['people'] == 1
    assert removed['state_store']['journal'] == 6
    assert sum(removed['bags'].values()) > 0
    after = store_bytes(folder)
    for name, data in after.items():
        assert not holds(data, FORGOTTEN), name
    for record in bag_records(folder):
        assert not holds(record, FORGOTTEN)
    assert _stored(folder) == others_stored
    assert messages_of(folder) == others_messages
    for bag in (p for p in folder.iterdir() if p.is_dir() and list(p.glob('*.mcap'))):
        info = recording.bag.yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
        assert info['message_count'] == sum(1 for m in others_messages if m[0] == bag.name)
        assert all(recording.is_finished(path) for path in recording.bag_files(bag))
        assert recording.bag_topics(bag, None)  # the summary reads
    assert FORGOTTEN in state.forgotten_in(folder) and 'p21' not in state.forgotten_in(folder)
    assert not list((folder / erasure.INTENTS).iterdir())
    assert erasure.forget(folder, FORGOTTEN)['bags'] == {name: 0 for name in removed['bags']}  # idempotent


def test_a_node_serving_the_folder_forgets_in_memory_and_on_disk(folder, tiny_checkpoint, scenes):
    node = Node()
    core = make_core(node, tiny_checkpoint, record_folder=str(folder), flush_interval=60.0)
    assert core.predictor.user_model(FORGOTTEN) is not None or FORGOTTEN in core.personalisation.pending
    core.accept_scene(messages.dumps(scene_request('live', scenes[0], FORGOTTEN)), 0)
    drain(core)
    assert holds(store_bytes(folder).get('state.db-wal', b'') + store_bytes(folder)['state.db'], FORGOTTEN)
    others = {u: core.predictor.user_model(u) for u in OTHERS}

    removed = core.forget_person(FORGOTTEN)

    assert removed['memory']['ratings'] == 6 and removed['memory']['scene_requests'] >= 1
    assert removed['state_store']['people'] == 1 and removed['bags']
    assert core.predictor.user_model(FORGOTTEN) is None and FORGOTTEN not in core.personalisation.histories
    for data in store_bytes(folder).values():
        assert not holds(data, FORGOTTEN)
    assert {u: core.predictor.user_model(u) for u in OTHERS} == others
    core.accept_scene(messages.dumps(scene_request('again', scenes[1], 'ann-7')), 0)
    drain(core)
    assert core.accept_feedback(messages.dumps({'user_id': FORGOTTEN, 'scene_id': 'live', 'action': 'navigate',
                                                'score': 0.5})) is False  # refused: a tombstone
    core.close()
    assert not any(holds(record, FORGOTTEN) for record in bag_records(folder))
    assert FORGOTTEN not in _stored(folder)


def test_rankings_are_served_while_the_disk_part_of_a_forget_runs(folder, tiny_checkpoint, scenes, monkeypatch):
    """The store's and the bags' erase runs on the erasing thread: held there, the core ranks
    others and the person themself (as a stranger), records nothing that names them, holds
    their models back, and answers only once the erase is done."""
    node = Node()
    core = make_core(node, tiny_checkpoint, record_folder=str(folder), flush_interval=60.0)
    release, running = threading.Event(), threading.Event()
    forget = erasure.forget

    def held_forget(*args, **kwargs):
        running.set()
        assert release.wait(60)
        return forget(*args, **kwargs)
    monkeypatch.setattr(erasure, 'forget', held_forget)
    answers = []
    erase = core.begin_forget(FORGOTTEN, then=lambda removed, error: answers.append((removed, error)))
    assert running.wait(60) and FORGOTTEN in erasure.interrupted(folder)  # the intent record is written first
    for index, user_id in enumerate([*OTHERS, FORGOTTEN]):
        core.accept_scene(messages.dumps(scene_request(f'meanwhile-{index}', scenes[index], user_id)), 0)
    drain(core)
    rankings = {r['scene_id']: r for r in node.on('stars/ranking')}
    assert {f'meanwhile-{i}' for i in range(3)} <= set(rankings) and not answers
    # their request, its ranking, the stranger warning:
    assert core.diagnostics()[2]['not_recorded_while_forgetting'] == 3
    release.set()
    assert erase.done.wait(60)
    drain(core)
    (removed, error), = answers
    assert error is None and removed['state_store']['people'] == 1 and removed['bags']
    core.accept_scene(messages.dumps(scene_request('after', scenes[3], FORGOTTEN)), 0)  # back under the same id
    drain(core)
    core.close()
    assert not erasure.interrupted(folder)
    logged = [m for m in messages_of(folder) if (m[2] or '').startswith('{')]
    meanwhile = [m for m in logged if 'meanwhile-' in m[2]]
    assert not any(holds(m[2].encode(), FORGOTTEN) for m in meanwhile)
    assert {json.loads(m[2]).get('user_id') for m in meanwhile if m[1] == '/stars/scene'} == set(OTHERS)
    assert any('"after"' in m[2] and FORGOTTEN in m[2] for m in logged)  # recorded again once the forget ended


def test_a_refit_from_a_bag_copied_before_the_forget_leaves_the_person_out(folder, tiny_checkpoint, tmp_path):
    copy = tmp_path / 'copy'
    shutil.copytree(folder, copy, ignore=shutil.ignore_patterns('state.*', 'forget.key'))
    predictor = StarsRecommender.load(tiny_checkpoint).predictor
    bags = [p for p in copy.iterdir() if p.is_dir()]
    before = read_logs(bags, predictor).ratings
    erasure.forget(folder, FORGOTTEN)
    found = read_logs(bags, predictor, forgotten_in([folder]))
    assert FORGOTTEN not in found.ratings and set(found.ratings) == set(OTHERS)
    assert found.problems['forgotten person'] == len(before[FORGOTTEN]) > 0


def test_the_command_line_forgets_and_refuses_while_a_node_holds_the_store(folder, tiny_checkpoint):
    node = Node()
    core = make_core(node, tiny_checkpoint, record_folder=str(folder), flush_interval=60.0)
    held = subprocess.run([sys.executable, '-m', 'offline_training.forget', '--record-folder', str(folder),
                           '--user-id', FORGOTTEN], capture_output=True, text=True)
    assert held.returncode == 2 and 'held by' in held.stderr
    core.close()
    done = subprocess.run([sys.executable, '-m', 'offline_training.forget', '--record-folder', str(folder),
                           '--user-id', FORGOTTEN], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert '"people": 1' in done.stdout and FORGOTTEN not in done.stdout.replace('p21', '')
    assert not any(holds(record, FORGOTTEN) for record in bag_records(folder))


_KILLED_AT = """
import os
import signal
import sys
kill_at, seen = int(sys.argv[1]), 0
def count_file_operations(event, args):
    global seen
    if event in ('open', 'os.rename', 'os.remove', 'os.mkdir', 'os.truncate', 'sqlite3.connect'):
        seen += 1
        if seen == kill_at:
            os.kill(os.getpid(), signal.SIGKILL)
"""
_FORGET = """
from stars_ros.recording import erasure
sys.addaudithook(count_file_operations)
erasure.forget(sys.argv[2], sys.argv[3])
print(seen, flush=True)
"""
_RETENTION = """
from stars_ros.recording import erasure
from stars_ros.state import StateStore
sys.addaudithook(count_file_operations)
store = StateStore(sys.argv[2], 'retention', on_error=lambda text: None)
store.erase_older(int(sys.argv[3])).result(60)
store.close()
erasure.erase_older(sys.argv[2], int(sys.argv[3]))
print(seen, flush=True)
"""


def _run_killed(program: str, kill_at: int, *args) -> subprocess.CompletedProcess:
    """``program`` in a process SIGKILLed at its ``kill_at``-th file operation (0: never)."""
    return subprocess.run([sys.executable, '-c', _KILLED_AT + program, str(kill_at), *map(str, args)],
                          env={**os.environ, 'PYTHONPATH': os.getcwd()}, capture_output=True, text=True)


@pytest.mark.slow
def test_a_kill_at_any_moment_of_a_forget_is_finished_by_a_rerun(folder, tmp_path):
    """SIGKILL at every file operation of a forget in turn (opens, renames, removals,
    database connections, counted by an audit hook, so where a kill falls does not depend
    on timing): the re-run ends with the person forgotten and nothing of anyone else lost."""
    others_stored = {u: v for u, v in _stored(folder).items() if u != FORGOTTEN}
    others_messages = [m for m in messages_of(folder) if not holds((m[2] or '').encode(), FORGOTTEN)]
    pristine = tmp_path / 'pristine'
    shutil.copytree(folder, pristine)
    whole = _run_killed(_FORGET, 0, folder, FORGOTTEN)  # never killed: how many operations a whole one makes
    assert whole.returncode == 0, whole.stderr
    left_an_intent = []
    for kill_at in range(1, int(whole.stdout) + 1):
        shutil.rmtree(folder)
        shutil.copytree(pristine, folder)
        killed = _run_killed(_FORGET, kill_at, folder, FORGOTTEN)
        assert killed.returncode == -signal.SIGKILL, killed.stderr
        left_an_intent.append(bool(erasure.interrupted(folder)))
        erasure.finish_interrupted(folder)  # what the next start does
        if FORGOTTEN not in state.forgotten_in(folder):  # killed before it began: the command failed, run again
            erasure.forget(folder, FORGOTTEN)
        assert not erasure.interrupted(folder)
        for data in store_bytes(folder).values():
            assert not holds(data, FORGOTTEN)
        assert not any(holds(record, FORGOTTEN) for record in bag_records(folder))
        assert _stored(folder) == others_stored
        assert messages_of(folder) == others_messages
    began = left_an_intent.index(True)  # from the intent's rename on, every kill leaves it for the next start
    assert all(left_an_intent[began:-1]) and began < len(left_an_intent) // 2, left_an_intent


def _retention_pass(folder: Path, cutoff: int) -> None:
    """What a node's retention pass does on disk (``_RETENTION``'s steps), in this process."""
    store = state.StateStore(folder, 'retention', on_error=lambda text: None)
    store.erase_older(cutoff).result(60)
    store.close()
    erasure.erase_older(folder, cutoff)


@pytest.mark.slow
def test_a_kill_at_any_moment_of_a_retention_pass_is_finished_by_the_next(folder, tmp_path):
    """SIGKILL at every file operation of a retention pass (the store's erase, then every
    bag's) in turn: the next pass leaves the folder as one uninterrupted pass does."""
    times = sorted(log_time for *_, log_time in messages_of(folder))
    cutoff = times[len(times) // 2]
    pristine, reference = tmp_path / 'pristine', tmp_path / 'reference'
    shutil.copytree(folder, pristine)
    shutil.copytree(folder, reference)
    whole = _run_killed(_RETENTION, 0, reference, cutoff)
    assert whole.returncode == 0, whole.stderr
    expected_stored, expected_messages = _stored(reference), messages_of(reference)
    assert 0 < len(expected_messages) < len(times) and all(m[3] >= cutoff for m in expected_messages)
    assert expected_stored != _stored(pristine)  # some ratings were old enough
    for kill_at in range(1, int(whole.stdout) + 1):
        shutil.rmtree(folder)
        shutil.copytree(pristine, folder)
        killed = _run_killed(_RETENTION, kill_at, folder, cutoff)
        assert killed.returncode == -signal.SIGKILL, killed.stderr
        _retention_pass(folder, cutoff)  # the next one
        assert _stored(folder) == expected_stored
        assert messages_of(folder) == expected_messages


def test_a_peers_model_of_a_forgotten_person_arriving_later_is_refused(tiny_checkpoint, scenes, tmp_path):
    """Fleet sharing: robot A forgets p2; robot B, which still holds p2, sends its model of
    them: A refuses it without naming them, and takes B's model of anyone else."""
    peer_node, node = Node(), Node()
    peer = make_core(peer_node, tiny_checkpoint, fleet_sharing=True)
    core = make_core(node, tiny_checkpoint, record_folder=str(tmp_path / 'a'), fleet_sharing=True)
    for k, user_id in enumerate((FORGOTTEN, 'ann-7')):
        peer.accept_scene(messages.dumps(scene_request(f'scene-{k}', scenes[0], user_id)), 0)
        drain(peer)
        peer.accept_feedback(messages.dumps({'user_id': user_id, 'scene_id': f'scene-{k}', 'action': 'navigate',
                                             'score': 0.5}))
        drain(peer)
    core.forget_person(FORGOTTEN)
    for text in published_models(peer_node):
        core.accept_user_model(text)
    drain(core)
    assert core.predictor.user_model(FORGOTTEN) is None and core.predictor.user_model('ann-7') is not None
    [refusal] = [e for e in node.on('stars/errors') if e['kind'] == 'forgotten']
    assert not holds(json.dumps(refusal).encode(), FORGOTTEN)
    core.close()
    peer.close()
    assert FORGOTTEN not in _stored(tmp_path / 'a') and 'ann-7' in _stored(tmp_path / 'a')


def test_rewritten_bags_keep_zstd_chunks_like_the_recorder_writes(folder):
    erasure.forget(folder, FORGOTTEN)
    for path in folder.rglob('*.mcap'):
        with open(path, 'rb') as handle:
            chunks = [r for r in StreamReader(handle, emit_chunks=True).records if isinstance(r, Chunk)]
        assert chunks and {c.compression for c in chunks} == {'zstd'}
