"""Record std_msgs/String topics to MCAP bags that ``ros2 bag``, Foxglove and rosbags open.

ROS-free: messages are CDR-encoded by mcap-ros2-support from the ros2msg definition, so no
rclpy is needed to write or read a bag. The layout is rosbag2's (Jazzy, metadata version 9)::

    <folder>/<name>/metadata.yaml        topics, counts, files (rewritten at every flush)
    <folder>/<name>/<name>_0.mcap, _1 …  rotated by size, ros2 profile, zstd chunks
    <folder>/<name>/feedback.jsonl       journal of accepted feedback, fsync'd per message
    <folder>/<name>/recording.pid        present while a process records into the bag

Every ``flush_interval`` seconds the chunk in progress is written out and fsync'd and
metadata.yaml rewritten, so a hard kill loses at most that interval. While recording,
metadata.yaml is written as one line of JSON, which is YAML too (rosbag2's yaml-cpp and
rosbags read it): PyYAML took 8-9 ms a flush, holding the GIL the node's executor needs,
and that showed as a tail in the node's latency; ``close`` and ``recover`` write block YAML,
as rosbag2 does; ``recover`` turns such a bag back into a valid one and puts
back any journaled feedback that missed the MCAP files. Disk errors never raise to the
caller: they are reported through ``on_event`` and retried at each flush, and feedback that
could not be journaled is kept in memory until it can.
"""
from __future__ import annotations

import datetime
import json
import os
import threading
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterator

import yaml
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_ros2._dynamic import serialize_dynamic  # the encoder mcap_ros2.writer uses
from mcap_ros2.decoder import DecoderFactory

from stars_ros import __version__

STRING = 'std_msgs/msg/String'
STRING_DEFINITION = 'string data\n'
STRING_HASH = 'RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18'
JOURNAL = 'feedback.jsonl'
PID_FILE = 'recording.pid'
METADATA_FILE = 'metadata.yaml'
ROSBAG2_VERSION = 9
_INFINITE = {'sec': 9223372036, 'nsec': 854775807}
_MAGIC = b'\x89MCAP0\r\n'


def default_folder() -> Path:
    """Where bags go unless told: ``$ROS_HOME/stars_ros/records`` (ROS_HOME unset or empty:
    ``~/.ros``), where ROS keeps what nodes write (rcl's logs go to ``$ROS_HOME/log``), so a
    node started from any folder, or by ``ros2 launch``, records to the same place."""
    return Path(os.environ.get('ROS_HOME') or '~/.ros').expanduser() / 'stars_ros' / 'records'


def qos_profile(depth: int = 10, transient_local: bool = False) -> dict:
    """A reliable publisher's QoS as rosbag2 stores it (``offered_qos_profiles`` entry), so
    ``ros2 bag play`` offers the same durability again (latched user ids stay latched)."""
    return {'history': 'keep_last', 'depth': depth, 'reliability': 'reliable',
            'durability': 'transient_local' if transient_local else 'volatile',
            'deadline': dict(_INFINITE), 'lifespan': dict(_INFINITE), 'liveliness': 'automatic',
            'liveliness_lease_duration': dict(_INFINITE), 'avoid_ros_namespace_conventions': False}


_encode_string = serialize_dynamic(STRING, STRING_DEFINITION)[STRING]


def encode_string(text: str) -> bytes:
    """CDR bytes of a std_msgs/msg/String holding ``text``."""
    return _encode_string({'data': text})


@dataclass
class _FileStats:
    path: str
    count: int = 0
    start: int | None = None
    end: int | None = None
    topics: dict = field(default_factory=dict)

    def add(self, topic: str, log_time: int):
        self.count += 1
        self.start = log_time if self.start is None else min(self.start, log_time)
        self.end = log_time if self.end is None else max(self.end, log_time)
        self.topics[topic] = self.topics.get(topic, 0) + 1


class _McapFile:
    """One file of a bag: an MCAP writer with the ros2 profile and its channels."""

    def __init__(self, path: Path, topics: dict, chunk_size: int, custom: dict):
        self.stream = open(path, 'wb')
        self.stats = _FileStats(path.name)
        self.topics = topics
        self.writer = McapWriter(self.stream, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        self.writer.start(profile='ros2', library=f'stars_ros {__version__}')
        self.schema = self.writer.register_schema(STRING, 'ros2msg', STRING_DEFINITION.encode())
        self.channels = {}
        if custom:
            self.writer.add_metadata('stars_ros', {k: str(v) for k, v in custom.items()})

    def write(self, topic: str, data: bytes, log_time: int):
        channel = self.channels.get(topic)
        if channel is None:
            qos = yaml.safe_dump([self.topics.get(topic, qos_profile())], sort_keys=False)
            channel = self.channels[topic] = self.writer.register_channel(
                topic, 'cdr', self.schema,
                {'offered_qos_profiles': qos, 'topic_type_hash': STRING_HASH})
        self.writer.add_message(channel, log_time=log_time, data=data, publish_time=log_time)
        self.stats.add(topic, log_time)

    def flush(self):
        """Write out the chunk in progress to the OS (the caller fsyncs)."""
        self.writer.flush()

    def size(self) -> int:
        return self.stream.tell()

    def finish(self):
        try:
            self.writer.finish()
            self.stream.flush()
            os.fsync(self.stream.fileno())
        finally:
            self.stream.close()


def _atomic_write(path: Path, text: str):
    tmp = path.with_name(path.name + '.tmp')
    with open(tmp, 'w') as handle:
        handle.write(text)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)


def write_metadata(bag: Path, files: list, topics: dict, custom: dict | None = None):
    """Write rosbag2's metadata.yaml for ``files`` (``_FileStats``) with ``topics`` {name: qos}."""
    _atomic_write(bag / METADATA_FILE, metadata_text(files, topics, custom))


def metadata_text(files: list, topics: dict, custom: dict | None = None, interim: bool = False) -> str:
    """rosbag2's metadata.yaml for ``files`` (``_FileStats``) with ``topics`` {name: qos}:
    block YAML, or, ``interim`` (while recording), the same document as one line of JSON
    (0.1 ms instead of 8-9 ms)."""
    counts = {}
    for stats in files:
        for topic, n in stats.topics.items():
            counts[topic] = counts.get(topic, 0) + n
    starts = [f.start for f in files if f.start is not None]
    ends = [f.end for f in files if f.end is not None]
    start = min(starts) if starts else 0
    info = {
        'version': ROSBAG2_VERSION,
        'storage_identifier': 'mcap',
        'duration': {'nanoseconds': (max(ends) - start) if ends else 0},
        'starting_time': {'nanoseconds_since_epoch': start},
        'message_count': sum(f.count for f in files),
        'topics_with_message_count': [
            {'topic_metadata': {'name': topic, 'type': STRING, 'serialization_format': 'cdr',
                                'offered_qos_profiles': [qos], 'type_description_hash': STRING_HASH},
             'message_count': counts.get(topic, 0)}
            for topic, qos in topics.items()],
        'compression_format': '',
        'compression_mode': '',
        'relative_file_paths': [f.path for f in files],
        'files': [{'path': f.path, 'starting_time': {'nanoseconds_since_epoch': f.start or 0},
                   'duration': {'nanoseconds': (f.end - f.start) if f.count else 0},
                   'message_count': f.count} for f in files],
        'custom_data': {k: str(v) for k, v in (custom or {}).items()},
        'ros_distro': 'jazzy',
    }
    if interim:
        return json.dumps({'rosbag2_bagfile_information': info}, separators=(',', ':')) + '\n'
    return yaml.safe_dump({'rosbag2_bagfile_information': info}, sort_keys=False)


class Recorder:
    """Writes String messages of the given topics into one rosbag2-layout MCAP bag.

    Args:
        folder (str or Path): where the bag directory is created.
        topics (dict): topic name -> offered QoS (``qos_profile()``), the topics to record.
        rotation_bytes (int, optional): start a new file once one reaches this size.
            (default: 64 MiB)
        flush_interval (float, optional): seconds between flushes; a hard kill loses at most
            this much. (default: 1.0)
        name (str, optional): bag directory name. (default: ``stars_<UTC time>``)
        custom (dict, optional): kept in metadata.yaml ``custom_data`` and in each file.
        on_event (callable, optional): ``on_event(level, text)`` with level ``'error'`` or
            ``'info'`` for disk failures and recoveries; called from any thread.
    """

    def __init__(self, folder, topics: dict, *, rotation_bytes: int = 64 << 20, flush_interval: float = 1.0,
                 name: str | None = None, custom: dict | None = None,
                 on_event: Callable[[str, str], None] | None = None):
        if rotation_bytes < 4096:
            raise ValueError('rotation_bytes must be at least 4096')
        if not flush_interval > 0:
            raise ValueError('flush_interval must be positive')
        stamp = datetime.datetime.now(datetime.timezone.utc).strftime('%Y_%m_%d-%H_%M_%S')
        self.name = name or f'stars_{stamp}'
        self.path = Path(folder).expanduser() / self.name
        self.topics = dict(topics)
        self.rotation_bytes = rotation_bytes
        self.flush_interval = flush_interval
        self.custom = dict(custom or {})
        self.error: str | None = None
        self.dropped = 0
        self._on_event = on_event or (lambda level, text: None)
        self._chunk_size = min(1 << 20, rotation_bytes // 8)
        self._lock = threading.RLock()
        self._sync_lock = threading.Lock()  # taken after _lock, never before it
        self._metadata_generation = self._metadata_written = 0
        self._files: list = []
        self._file: _McapFile | None = None
        self._journal = None
        self._unjournaled: list = []  # accepted feedback not yet safe on disk
        self._syncing: list = []  # feedback written to the journal, its fsync under way
        self._unrecorded: list = []  # journaled feedback not yet in an MCAP file
        self._closed = False
        self._damaged = False
        self._stop = threading.Event()
        with self._lock:
            self._open()
        self._flusher = threading.Thread(target=self._flush_loop, name='stars-recorder-flush', daemon=True)
        self._flusher.start()

    # -- state -----------------------------------------------------------------------------
    @property
    def pending_feedback(self) -> int:
        """Accepted feedback that is not yet journaled on disk (kept in memory, retried)."""
        return len(self._unjournaled) + len(self._syncing)

    @property
    def files(self) -> list:
        with self._lock:
            return [self.path / f.path for f in self._files]

    def _fail(self, error: Exception, doing: str, lose_file: bool = True):
        message = f'recording to {self.path} failed while {doing}: {error}'
        first = self.error is None
        self.error = message
        if lose_file and self._file is not None:
            self._damaged = True  # the file is left unfinished: close() repairs it
            try:
                self._file.stream.close()
            except OSError:
                pass
            self._file = None
        if first:
            self._on_event('error', message)

    def _open(self):
        """Create the bag directory, journal and next file; on failure stay in error state."""
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            (self.path / PID_FILE).write_text(f'{os.getpid()}\n')
            if self._journal is None:
                self._journal = open(self.path / JOURNAL, 'a')
            path = self.path / f'{self.name}_{len(self._files)}.mcap'
            self._file = _McapFile(path, self.topics, self._chunk_size, self.custom)
            self._files.append(self._file.stats)
            self._write_metadata(self._metadata_snapshot())
        except OSError as error:
            self._fail(error, 'opening the bag')
            return
        self._retry_feedback()
        self._check_healthy()

    def _check_healthy(self):
        if self.error is not None and self._file is not None and self._journal is not None \
                and not self._unjournaled:
            self.error = None
            self._on_event('info', f'recording to {self.path} works again')

    # -- writing ---------------------------------------------------------------------------
    def write(self, topic: str, text: str, log_time: int) -> bool:
        """Record ``text`` on ``topic`` at ``log_time`` (ns); False if it could not be."""
        data = encode_string(text)
        with self._lock:
            if self._closed or self._file is None:
                self.dropped += 1
                return False
            try:
                self._file.write(topic, data, log_time)
                if self._file.size() >= self.rotation_bytes:
                    self._rotate()
            except OSError as error:
                self._fail(error, 'writing')
                self.dropped += 1
                return False
            return True

    def write_feedback(self, topic: str, text: str, log_time: int) -> bool:
        """Record feedback: journaled and fsync'd before returning True; kept in memory and
        retried at each flush when the disk refuses it, so it is never silently lost. The
        fsync runs outside the lock ``write`` takes, so other messages are recorded
        meanwhile. Not to be called once ``close`` has begun."""
        entry = {'topic': topic, 'log_time': log_time, 'data': text}
        with self._lock:
            self._unjournaled.append(entry)
            if self._journal is None or len(self._unjournaled) > 1:  # the disk is failing: retry all now
                self._retry_feedback()
                return entry not in self._unjournaled
            try:
                self._journal.write(json.dumps(entry) + '\n')
                self._journal.flush()
                descriptor = os.dup(self._journal.fileno())
            except OSError as error:
                self._journal = None  # reopened at the next flush
                self._fail(error, 'journaling feedback', lose_file=False)
                return False
            self._unjournaled.remove(entry)
            self._syncing.append(entry)
        failure = None
        try:
            os.fsync(descriptor)
        except OSError as error:
            failure = error
        finally:
            os.close(descriptor)
        with self._lock:
            self._syncing.remove(entry)
            if failure is not None:
                self._unjournaled.insert(0, entry)
                self._fail(failure, 'journaling feedback', lose_file=False)
                return False
            self._unrecorded.append(entry)
            self._retry_feedback()  # into the MCAP file
            return True

    def _retry_feedback(self):
        while self._unjournaled and self._journal is not None:
            entry = self._unjournaled[0]
            try:
                self._journal.write(json.dumps(entry) + '\n')
                self._journal.flush()
                os.fsync(self._journal.fileno())
            except OSError as error:
                self._journal = None  # reopened at the next flush
                self._fail(error, 'journaling feedback', lose_file=False)
                return
            self._unrecorded.append(self._unjournaled.pop(0))
        while self._unrecorded and self._file is not None:
            entry = self._unrecorded[0]
            if not self.write(entry['topic'], entry['data'], entry['log_time']):
                return
            self._unrecorded.pop(0)

    def _rotate(self):
        self._file.finish()
        self._file = None
        self._open()

    def flush(self):
        """Write out the chunk in progress, fsync it and rewrite metadata.yaml; retry a failed
        disk. Called every ``flush_interval`` by a background thread. The fsyncs run outside
        the lock, on a duplicate of the file descriptor, so the threads that record (the
        ranker's request path) never wait for the disk."""
        synced = None
        with self._lock:
            if self._closed:
                return
            if self._file is None:
                self._open()
            elif self._journal is None:
                try:
                    self._journal = open(self.path / JOURNAL, 'a')
                except OSError as error:
                    self._fail(error, 'reopening the feedback journal', lose_file=False)
            if self._file is not None:
                try:
                    self._file.flush()
                    synced = (self._file, os.dup(self._file.stream.fileno()), self._metadata_snapshot())
                except OSError as error:
                    self._fail(error, 'flushing')
            self._retry_feedback()
            self._check_healthy()
        if synced is None:
            return
        file, descriptor, metadata = synced
        failure = None
        try:
            os.fsync(descriptor)
            self._write_metadata(metadata)
        except OSError as error:
            failure = error
        finally:
            os.close(descriptor)
        if failure is not None:
            with self._lock:
                if self._file is file:
                    self._fail(failure, 'flushing')

    def _metadata_snapshot(self) -> tuple:
        """(generation, copies of the files' statistics so far); call with the lock held."""
        self._metadata_generation += 1
        return self._metadata_generation, [replace(f, topics=dict(f.topics)) for f in self._files]

    def _write_metadata(self, snapshot: tuple, interim: bool = True):
        """Write ``snapshot`` unless a newer one is already on disk (the flusher writes its
        snapshot after releasing the lock, so a rotation may have overtaken it)."""
        generation, files = snapshot
        text = metadata_text(files, self.topics, self.custom, interim)
        with self._sync_lock:
            if generation > self._metadata_written:
                _atomic_write(self.path / METADATA_FILE, text)
                self._metadata_written = generation

    def _flush_loop(self):
        while not self._stop.wait(self.flush_interval):
            self.flush()

    def close(self) -> list:
        """Finish the current file, write metadata.yaml and remove the pid marker. Returns
        the feedback entries that could not be journaled (to be logged by the caller)."""
        self._stop.set()
        if self._flusher is not threading.current_thread():
            self._flusher.join()
        with self._lock:
            if self._closed:
                return list(self._unjournaled)
            self._retry_feedback()
            self._closed = True
            try:
                if self._file is not None:
                    self._file.finish()
                    self._file = None
                if self._journal is not None:
                    self._journal.close()
                if self._damaged:
                    recover(self.path)
                elif self._files:
                    self._write_metadata(self._metadata_snapshot(), interim=False)
                (self.path / PID_FILE).unlink(missing_ok=True)
            except OSError as error:
                self._fail(error, 'closing')
            return list(self._unjournaled)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# -- reading and recovery ----------------------------------------------------------------------
def _mcap_files(bag: Path) -> list:
    def index(path):
        return int(path.stem.rsplit('_', 1)[-1]) if path.stem.rsplit('_', 1)[-1].isdigit() else -1
    return sorted(bag.glob('*.mcap'), key=lambda p: (index(p), p.name))


def is_finished(path: Path) -> bool:
    """True when the MCAP file ends with its closing magic (it was finished properly)."""
    with open(path, 'rb') as handle:
        handle.seek(0, os.SEEK_END)
        if handle.tell() < 2 * len(_MAGIC):
            return False
        handle.seek(-len(_MAGIC), os.SEEK_END)
        return handle.read() == _MAGIC


def read_messages(bag, topics=None) -> Iterator[tuple]:
    """(topic, text, log_time) of every message in a bag directory or MCAP file, in file order."""
    bag = Path(bag)
    for path in (_mcap_files(bag) if bag.is_dir() else [bag]):
        with open(path, 'rb') as handle:
            reader = make_reader(handle, decoder_factories=[DecoderFactory()])
            for _, channel, message, decoded in reader.iter_decoded_messages(topics=topics):
                yield channel.topic, decoded.data, message.log_time


def bag_topics(bag) -> dict:
    """{topic: offered QoS} of a finished bag directory or MCAP file."""
    bag = Path(bag)
    topics = {}
    for path in (_mcap_files(bag) if bag.is_dir() else [bag]):
        with open(path, 'rb') as handle:
            summary = make_reader(handle).get_summary()
        if summary is None:
            raise McapError(f'{path} has no summary: run `python -m stars_ros.recording.bag recover {bag}` first')
        for channel in summary.channels.values():
            topics.setdefault(channel.topic, _topic_qos(channel))
    return topics


def _salvage(path: Path) -> tuple:
    """Records of a possibly truncated file up to the first damaged one."""
    schemas, channels, messages, custom = {}, {}, [], {}
    with open(path, 'rb') as handle:
        try:
            for record in StreamReader(handle, emit_chunks=False).records:
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Message):
                    messages.append(record)
                elif isinstance(record, Metadata) and record.name == 'stars_ros':
                    custom = dict(record.metadata)
        except (McapError, EOFError, ValueError, OSError, RuntimeError) as error:
            return schemas, channels, messages, custom, f'{type(error).__name__}: {error}'
    return schemas, channels, messages, custom, None


def _topic_qos(channel: Channel) -> dict:
    profiles = yaml.safe_load(channel.metadata.get('offered_qos_profiles', '') or '[]') or [qos_profile()]
    return profiles[0]


def recover(bag) -> dict:
    """Make an unfinished bag (hard kill, power loss) valid again.

    Damaged files are rewritten with every complete record they hold, journaled feedback
    missing from the files is written to a new file, and metadata.yaml is rebuilt. Returns
    {'repaired': [file names], 'feedback_restored': n, 'messages': n}.
    """
    bag = Path(bag)
    files, topics, custom, repaired = [], {}, {}, []
    seen = set()
    for path in _mcap_files(bag):
        schemas, channels, messages, file_custom, damage = _salvage(path)
        custom = custom or file_custom
        for channel in channels.values():
            topics.setdefault(channel.topic, _topic_qos(channel))
        for message in messages:
            seen.add((channels[message.channel_id].topic, message.log_time, bytes(message.data)))
        if damage is not None or not is_finished(path):
            tmp = path.with_name(path.name + '.tmp')
            rewritten = _McapFile(tmp, topics, 1 << 20, file_custom)
            for message in messages:
                rewritten.write(channels[message.channel_id].topic, bytes(message.data), message.log_time)
            rewritten.finish()
            os.replace(tmp, path)
            rewritten.stats.path = path.name
            files.append(rewritten.stats)
            repaired.append(path.name)
        else:
            stats = _FileStats(path.name)
            for message in messages:
                stats.add(channels[message.channel_id].topic, message.log_time)
            files.append(stats)
    missing = []
    journal = bag / JOURNAL
    if journal.exists():
        for line in journal.read_text().splitlines():
            try:
                entry = json.loads(line)
            except ValueError:
                continue  # a line cut by the kill was never acknowledged as journaled
            key = (entry['topic'], entry['log_time'], encode_string(entry['data']))
            if key not in seen:
                seen.add(key)
                missing.append(entry)
    if missing:
        name = bag.name
        path = bag / f'{name}_{len(files)}.mcap'
        for entry in missing:
            topics.setdefault(entry['topic'], qos_profile())
        extra = _McapFile(path, topics, 1 << 20, custom)
        for entry in missing:
            extra.write(entry['topic'], encode_string(entry['data']), entry['log_time'])
        extra.finish()
        files.append(extra.stats)
    write_metadata(bag, files, topics, custom)
    (bag / PID_FILE).unlink(missing_ok=True)
    return {'repaired': repaired, 'feedback_restored': len(missing), 'messages': sum(f.count for f in files)}


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def abandoned_bags(folder) -> list:
    """Bags under ``folder`` whose recording process died without closing them."""
    found = []
    for marker in sorted(Path(folder).expanduser().glob(f'*/{PID_FILE}')):
        try:
            pid = int(marker.read_text().strip())
        except (OSError, ValueError):
            pid = -1
        if pid <= 0 or not _alive(pid) or pid == os.getpid():
            found.append(marker.parent)
    return found


def main(argv=None) -> int:
    """``python -m stars_ros.recording.bag recover BAG...``: repair bags left by a hard kill."""
    import argparse

    parser = argparse.ArgumentParser(prog='python -m stars_ros.recording.bag', description=main.__doc__)
    parser.add_argument('command', choices=['recover'])
    parser.add_argument('bags', nargs='+', type=Path)
    args = parser.parse_args(argv)
    for bag in args.bags:
        print(f'{bag}: {recover(bag)}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
