"""MCAP recording: rosbag2 layout read back by mcap-ros2-support and rosbags, rotation,
hard-kill recovery (with the state store's committed feedback), and disk failures that never
lose committed feedback."""
import json
import os
import signal
import subprocess
import sys
import textwrap

import pytest
import yaml
from mcap.reader import make_reader
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from stars_ros import recording, state

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TOPICS = {'/stars/scene': recording.qos_profile(), '/stars/user_id': recording.qos_profile(1, transient_local=True),
          '/stars/feedback': recording.qos_profile(100)}


def _rosbags_messages(path):
    store = get_typestore(Stores.ROS2_JAZZY)
    with Reader(path) as reader:
        return [(c.topic, store.deserialize_cdr(raw, c.msgtype).data, t) for c, t, raw in reader.messages()]


def test_round_trip_with_both_readers(tmp_path):
    with recording.Recorder(tmp_path, TOPICS, name='bag', custom={'fingerprint': 'f00'}) as recorder:
        recorder.write('/stars/user_id', 'g', 10)
        for k in range(50):
            recorder.write('/stars/scene', json.dumps({'scene_id': f's{k}'}), 100 + k)
        recorder.write_feedback('/stars/feedback', '{"score": 0.5}', 1000)
    bag = tmp_path / 'bag'
    assert sorted(p.name for p in bag.iterdir()) == ['bag_0.mcap', 'metadata.yaml']
    written = [('/stars/user_id', 'g', 10)] + [('/stars/scene', json.dumps({'scene_id': f's{k}'}), 100 + k)
                                               for k in range(50)] + [('/stars/feedback', '{"score": 0.5}', 1000)]
    assert list(recording.read_messages(bag)) == written
    assert sorted(_rosbags_messages(bag), key=lambda m: m[2]) == written
    assert sorted(_rosbags_messages(bag / 'bag_0.mcap'), key=lambda m: m[2]) == written

    with open(bag / 'bag_0.mcap', 'rb') as handle:
        summary = make_reader(handle).get_summary()
        header = make_reader(open(bag / 'bag_0.mcap', 'rb')).get_header()
    assert header.profile == 'ros2'
    assert {s.encoding for s in summary.schemas.values()} == {'ros2msg'}
    channels = {c.topic: c for c in summary.channels.values()}
    assert {c.message_encoding for c in channels.values()} == {'cdr'}
    latched = yaml.safe_load(channels['/stars/user_id'].metadata['offered_qos_profiles'])[0]
    assert latched['durability'] == 'transient_local' and latched['depth'] == 1

    info = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert info['version'] == 9 and info['storage_identifier'] == 'mcap' and info['message_count'] == 52
    counts = {t['topic_metadata']['name']: t['message_count'] for t in info['topics_with_message_count']}
    assert counts == {'/stars/scene': 50, '/stars/user_id': 1, '/stars/feedback': 1}
    assert info['custom_data'] == {'fingerprint': 'f00'}
    assert info['starting_time']['nanoseconds_since_epoch'] == 10 and info['duration']['nanoseconds'] == 990


def test_string_type_hash_matches_rosbags():
    assert get_typestore(Stores.ROS2_JAZZY).hash_rihs01('std_msgs/msg/String') == recording.STRING_HASH


@pytest.mark.parametrize('text', ['', 'a', 'abcd', 'é ✓', '{"score": 0.5}'])
def test_string_encoding_decodes_with_both_readers(text):
    data = recording.encode_string(text)
    schema = Schema(id=1, name=recording.STRING, encoding='ros2msg', data=b'string data\n')
    assert DecoderFactory().decoder_for('cdr', schema)(data).data == text
    assert get_typestore(Stores.ROS2_JAZZY).deserialize_cdr(data, recording.STRING).data == text


def test_rotation_by_size(tmp_path):
    with recording.Recorder(tmp_path, TOPICS, name='bag', rotation_bytes=16384) as recorder:
        for k in range(600):
            recorder.write('/stars/scene', os.urandom(60).hex(), k)  # random: zstd cannot shrink it
    files = sorted((tmp_path / 'bag').glob('*.mcap'))
    assert len(files) >= 3 and all(recording.is_finished(f) for f in files)
    assert all(f.stat().st_size < 16384 + 4 * 8192 for f in files)
    assert [t for _, _, t in recording.read_messages(tmp_path / 'bag')] == list(range(600))
    assert len(_rosbags_messages(tmp_path / 'bag')) == 600


KILLED_WRITER = textwrap.dedent('''
    import os, signal, sys, threading
    from stars_ros import recording, state
    topics = {'/stars/scene': recording.qos_profile(), '/stars/feedback': recording.qos_profile()}
    recorder = recording.Recorder(sys.argv[1], topics, name='bag', rotation_bytes=16384, flush_interval=3600)
    store = state.StateStore(sys.argv[1], 'killed writer', on_error=sys.exit)
    for k in range(400):
        recorder.write('/stars/scene', f'{k:04d}' + os.urandom(30).hex(), k)
    recorder.flush()  # what the flusher does every interval: all of the above is on disk
    committed = threading.Event()
    store.when_committed(store.write_person(None, [({'topic': '/stars/feedback', 'log_time': 10_000,
                                                      'data': '{"score": 1}'}, 'bag')]), committed.set)
    committed.wait(30)  # in the store; the bag has it in memory only
    for k in range(5):
        recorder.write('/stars/scene', 'after the last flush', 20_000 + k)
    os.kill(os.getpid(), signal.SIGKILL)
''')


def test_metadata_while_recording_is_one_json_line_with_what_close_writes_as_block_yaml(tmp_path):
    recorder = recording.Recorder(tmp_path, TOPICS, name='bag', flush_interval=3600, custom={'fingerprint': 'f00'})
    recorder.write('/stars/user_id', 'g', 10)
    recorder.write('/stars/scene', 'a', 20)
    recorder.flush()
    interim = (tmp_path / 'bag' / 'metadata.yaml').read_text()
    assert interim.count('\n') == 1 and json.loads(interim) == yaml.safe_load(interim)
    recorder.close()
    final = (tmp_path / 'bag' / 'metadata.yaml').read_text()
    assert final.startswith('rosbag2_bagfile_information:\n  version: 9\n')
    assert yaml.safe_load(interim) == yaml.safe_load(final)
    info = yaml.safe_load(final)['rosbag2_bagfile_information']
    assert info['message_count'] == 2 and info['custom_data'] == {'fingerprint': 'f00'}
    (tmp_path / 'bag' / 'metadata.yaml').write_text(interim)  # rosbags reads the interim form too
    assert [(topic, text) for topic, text, _ in _rosbags_messages(tmp_path / 'bag')] == [
        ('/stars/user_id', 'g'), ('/stars/scene', 'a')]


def test_hard_kill_loses_at_most_the_last_interval_and_no_feedback(tmp_path):
    run = subprocess.run([sys.executable, '-c', KILLED_WRITER, str(tmp_path)], env=dict(os.environ, PYTHONPATH=REPO),
                         timeout=60, capture_output=True)
    assert run.returncode == -signal.SIGKILL, run.stderr.decode()
    bag = tmp_path / 'bag'
    assert recording.abandoned_bags(tmp_path) == [bag]
    assert not recording.is_finished(sorted(bag.glob('*.mcap'))[-1])

    report = recording.recover(bag)
    assert report['feedback_restored'] == 1 and report['repaired']
    assert recording.abandoned_bags(tmp_path) == []
    messages = list(recording.read_messages(bag))
    scenes = [t for topic, _, t in messages if topic == '/stars/scene']
    assert scenes[:400] == list(range(400))
    assert ('/stars/feedback', '{"score": 1}', 10_000) in messages
    assert len(_rosbags_messages(bag)) == len(messages)
    info = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert info['message_count'] == len(messages)
    assert recording.recover(bag)['feedback_restored'] == 0  # idempotent


def test_full_disk_is_reported_and_committed_feedback_reaches_the_bag_once_it_can(tmp_path):
    """The chunk holding the feedback is lost with the full disk; the store committed it, and
    the repair at close writes it back into the bag."""
    bag = tmp_path / 'bag'
    bag.mkdir()
    (bag / 'bag_0.mcap').symlink_to('/dev/full')  # every write there fails with ENOSPC
    events = []
    recorder = recording.Recorder(tmp_path, TOPICS, name='bag', flush_interval=3600,
                                  on_event=lambda level, text: events.append((level, text)))
    committed = []
    store = state.StateStore(tmp_path, 'test', on_error=pytest.fail, on_feedback_committed=lambda entry: (
        committed.append(entry), recorder.write_feedback(entry['topic'], entry['data'], 2)))
    recorder.write('/stars/scene', 'lost with the full disk', 1)
    store.write_person(None, [({'topic': '/stars/feedback', 'log_time': 2, 'data': '{"score": 0.1}'}, 'bag')])
    assert store.close() == [] and len(committed) == 1
    recorder.flush()
    assert recorder.error and 'No space left' in recorder.error and events[0][0] == 'error'
    recorder.write_feedback('/stars/feedback', '{"score": 0.2}', 3)  # waits for a file that takes it
    assert recorder.unrecorded_feedback == 1
    recorder.flush()  # the next file works
    assert recorder.unrecorded_feedback == 0 and recorder.error is None and events[-1][0] == 'info'
    assert recorder.write('/stars/scene', 'after', 4)
    assert recorder.close() == 0
    messages = list(recording.read_messages(bag))
    assert ('/stars/feedback', '{"score": 0.1}', 2) in messages and ('/stars/scene', 'after', 4) in messages
    assert ('/stars/feedback', '{"score": 0.2}', 3) in messages
    assert len(_rosbags_messages(bag)) == len(messages)


def test_unwritable_folder_never_raises_and_counts_unrecorded_feedback(tmp_path):
    blocker = tmp_path / 'file'
    blocker.write_text('not a folder')
    events = []
    recorder = recording.Recorder(blocker / 'records', TOPICS, on_event=lambda level, text: events.append(level))
    assert recorder.error is not None and events == ['error']
    assert not recorder.write('/stars/scene', 'x', 1) and recorder.dropped == 1
    recorder.write_feedback('/stars/feedback', '{"score": 1}', 2)
    assert recorder.close() == 1


def test_invalid_settings_refused(tmp_path):
    with pytest.raises(ValueError, match='rotation_bytes'):
        recording.Recorder(tmp_path, TOPICS, rotation_bytes=10)
    with pytest.raises(ValueError, match='flush_interval'):
        recording.Recorder(tmp_path, TOPICS, flush_interval=0)


def test_a_flush_fsyncs_without_holding_up_writers(tmp_path, monkeypatch):
    """The periodic flush waits for the disk outside the lock the ranker records under."""
    import threading
    real_fsync = os.fsync
    syncing, release, gave_up = threading.Event(), threading.Event(), threading.Event()

    def slow_fsync(descriptor):
        syncing.set()
        if not release.wait(10):  # only a writer blocked behind this fsync keeps it from being released
            gave_up.set()
        real_fsync(descriptor)

    with recording.Recorder(tmp_path, TOPICS, name='bag', flush_interval=3600) as recorder:
        recorder.write('/stars/scene', 'before', 1)
        monkeypatch.setattr(os, 'fsync', slow_fsync)
        thread = threading.Thread(target=recorder.flush)
        thread.start()
        assert syncing.wait(10)
        assert recorder.write('/stars/scene', 'during', 3)  # would wait for the fsync if it held the lock
        recorder.write_feedback('/stars/feedback', 'fb', 2)
        assert not gave_up.is_set()
        release.set()
        thread.join(10)
        monkeypatch.setattr(os, 'fsync', real_fsync)
        assert recorder.error is None
    expected = ['before', 'fb', 'during']  # by log time
    assert [m[1] for m in recording.read_messages(tmp_path / 'bag')] == expected
    assert yaml.safe_load((tmp_path / 'bag' / 'metadata.yaml').read_text())[
        'rosbag2_bagfile_information']['message_count'] == len(expected)
