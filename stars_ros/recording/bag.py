"""The bag format: rosbag2's layout (Jazzy, metadata version 9) of std_msgs/String topics, and
of topics of other types handed in already CDR-encoded (the node's visualization_msgs/MarkerArray),
in MCAP files that ``ros2 bag``, Foxglove and rosbags open, and reading such bags back.

ROS-free: a String's CDR encoding is written here, other types come encoded with their
``MessageType`` (ros2msg definition and type hash), and mcap-ros2-support decodes them all
from the definitions, so no rclpy is needed to write or read a bag::

    <folder>/<name>/metadata.yaml        topics, counts, files
    <folder>/<name>/<name>_0.mcap, _1 …  rotated by size, ros2 profile, zstd chunks
    <folder>/<name>/recording.pid        present while a process records into the bag
    <folder>/state.db                    the node's state store and feedback journal (``stars_ros.state``)

metadata.yaml is block YAML, as rosbag2 writes it, or (``interim``, while recording) the
same document as one line of JSON, which is YAML too (rosbag2's yaml-cpp and rosbags read
it): PyYAML took 8-9 ms a flush, holding the GIL the node's executor needs.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Iterator

import yaml
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_ros2.decoder import DecoderFactory

from stars_ros import __version__
from stars_ros.files import atomic_write

STRING = 'std_msgs/msg/String'
STRING_DEFINITION = 'string data\n'
STRING_HASH = 'RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18'
PID_FILE = 'recording.pid'
METADATA_FILE = 'metadata.yaml'
ROSBAG2_VERSION = 9
CDR_LITTLE_ENDIAN = b'\x00\x01\x00\x00'  # encapsulation header: plain CDR, little-endian
_INFINITE = {'sec': 9223372036, 'nsec': 854775807}
_MAGIC = b'\x89MCAP0\r\n'


NODE_PLACEHOLDER = '{node}'


@dataclass(frozen=True)
class MessageType:
    """A ROS 2 message type as a bag stores it: its name (``pkg/msg/Type``), its ros2msg
    definition (with the definitions it uses, as rosbag2 writes them) and its RIHS01 hash."""

    name: str
    definition: str
    type_hash: str


STRING_TYPE = MessageType(STRING, STRING_DEFINITION, STRING_HASH)


def default_folder() -> Path:
    """Where bags go unless told: ``$ROS_HOME/stars_ros/records`` (ROS_HOME unset or empty:
    ``~/.ros``), where ROS keeps what nodes write (rcl's logs go to ``$ROS_HOME/log``), so a
    node started from any folder, or by ``ros2 launch``, records to the same place."""
    return Path(os.environ.get('ROS_HOME') or '~/.ros').expanduser() / 'stars_ros' / 'records'


def node_folder(folder: str, node_name: str) -> Path:
    """``folder`` with ``{node}`` replaced by the node's fully qualified name without its
    leading slash (``/robot1/ranker`` -> ``robot1/ranker``): one folder, one store, per node."""
    return Path(str(folder).replace(NODE_PLACEHOLDER, node_name.strip('/'))).expanduser()


def qos_profile(depth: int = 10, transient_local: bool = False) -> dict:
    """A reliable publisher's QoS as rosbag2 stores it (``offered_qos_profiles`` entry), so
    ``ros2 bag play`` offers the same durability again (latched user ids stay latched)."""
    return {'history': 'keep_last', 'depth': depth, 'reliability': 'reliable',
            'durability': 'transient_local' if transient_local else 'volatile',
            'deadline': dict(_INFINITE), 'lifespan': dict(_INFINITE), 'liveliness': 'automatic',
            'liveliness_lease_duration': dict(_INFINITE), 'avoid_ros_namespace_conventions': False}


def encode_string(text: str) -> bytes:
    """CDR bytes of a std_msgs/msg/String holding ``text``: the encapsulation header, the
    length of the UTF-8 text with its NUL terminator (uint32), the text, the NUL.
    mcap-ros2-support encodes only inside its own MCAP writer, so it is written here."""
    data = text.encode('utf-8') + b'\0'
    return CDR_LITTLE_ENDIAN + len(data).to_bytes(4, 'little') + data


def topic_qos(channel: Channel) -> dict:
    """The offered QoS a recorded channel keeps in its metadata (the default if none)."""
    profiles = yaml.safe_load(channel.metadata.get('offered_qos_profiles', '') or '[]') or [qos_profile()]
    return profiles[0]


@dataclass
class FileStats:
    """What metadata.yaml says about one MCAP file of a bag."""

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


class McapFile:
    """One file of a bag being written to ``stream``: an MCAP writer with the ros2 profile, a
    channel per topic (its QoS and type hash in the channel metadata, as rosbag2 writes
    them), a schema per message type (``types``: topic -> MessageType; String unless named)
    and the statistics of the file ``name``."""

    def __init__(self, stream: BinaryIO, name: str, topics: dict, chunk_size: int, custom: dict,
                 types: dict | None = None):
        self.stream = stream
        self.stats = FileStats(name)
        self.topics = topics
        self.types = types or {}
        self.writer = McapWriter(self.stream, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        self.writer.start(profile='ros2', library=f'stars_ros {__version__}')
        self.schemas = {}
        self.channels = {}
        if custom:
            self.writer.add_metadata('stars_ros', {k: str(v) for k, v in custom.items()})

    @classmethod
    def create(cls, path: Path, topics: dict, chunk_size: int, custom: dict, types: dict | None = None) -> 'McapFile':
        """A new file at ``path``, which it owns (``finish`` closes it)."""
        return cls(open(path, 'wb'), path.name, topics, chunk_size, custom, types)

    def _schema(self, kind: MessageType) -> int:
        if kind.name not in self.schemas:
            self.schemas[kind.name] = self.writer.register_schema(kind.name, 'ros2msg', kind.definition.encode())
        return self.schemas[kind.name]

    def write(self, topic: str, data: bytes, log_time: int):
        """Write ``data``, the CDR bytes of a message of the topic's type."""
        channel = self.channels.get(topic)
        if channel is None:
            kind = self.types.get(topic, STRING_TYPE)
            qos = yaml.safe_dump([self.topics.get(topic, qos_profile())], sort_keys=False)
            channel = self.channels[topic] = self.writer.register_channel(
                topic, 'cdr', self._schema(kind),
                {'offered_qos_profiles': qos, 'topic_type_hash': kind.type_hash})
        self.writer.add_message(channel, log_time=log_time, data=data, publish_time=log_time)
        self.stats.add(topic, log_time)

    def flush(self):
        """Write out the chunk in progress to the OS (the caller fsyncs)."""
        self.writer.flush()

    def size(self) -> int:
        return self.stream.tell()

    def end(self):
        """Write the summary and the closing magic; the stream stays open."""
        self.writer.finish()

    def finish(self):
        """End the file, fsync it and close it."""
        try:
            self.end()
            self.stream.flush()
            os.fsync(self.stream.fileno())
        finally:
            self.stream.close()


def metadata_text(files: list, topics: dict, custom: dict | None = None, interim: bool = False,
                  types: dict | None = None) -> str:
    """rosbag2's metadata.yaml for ``files`` (FileStats) with ``topics`` {name: qos} of
    ``types`` {name: MessageType; String unless named}: block YAML, or, ``interim`` (while
    recording), the same document as one line of JSON (0.1 ms instead of 8-9 ms)."""
    types = types or {}
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
            {'topic_metadata': {'name': topic, 'type': types.get(topic, STRING_TYPE).name,
                                'serialization_format': 'cdr', 'offered_qos_profiles': [qos],
                                'type_description_hash': types.get(topic, STRING_TYPE).type_hash},
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


def write_metadata(bag: Path, text: str) -> None:
    """Replace the bag's metadata.yaml with ``text`` (``metadata_text``), atomically."""
    data = text.encode()
    atomic_write(bag / METADATA_FILE, lambda handle: handle.write(data))


def bag_files(bag: Path) -> list:
    """The MCAP files of a bag directory in recording order (``<name>_0.mcap``, ``_1`` …)."""
    def index(path):
        suffix = path.stem.rsplit('_', 1)[-1]
        return int(suffix) if suffix.isdigit() else -1
    return sorted(Path(bag).glob('*.mcap'), key=lambda p: (index(p), p.name))


def is_finished(path: Path) -> bool:
    """True when the MCAP file ends with its closing magic (it was finished properly)."""
    with open(path, 'rb') as handle:
        handle.seek(0, os.SEEK_END)
        if handle.tell() < 2 * len(_MAGIC):
            return False
        handle.seek(-len(_MAGIC), os.SEEK_END)
        return handle.read() == _MAGIC


def _files_of(bag: Path) -> list:
    return bag_files(bag) if bag.is_dir() else [bag]


def read_decoded(bag, topics=None, type_name: str | None = None) -> Iterator[tuple]:
    """(topic, decoded message, log_time) of every message in a bag directory or MCAP file
    (of the type ``type_name`` only, if given), in file order; messages decode to objects
    with the definition's fields (``msg.markers[0].pose.position.x``)."""
    decoders = DecoderFactory()
    for path in _files_of(Path(bag)):
        with open(path, 'rb') as handle:
            for schema, channel, message in make_reader(handle).iter_messages(topics=topics):
                if type_name is None or (schema is not None and schema.name == type_name):
                    decode = decoders.decoder_for(channel.message_encoding, schema)
                    yield channel.topic, decode(message.data), message.log_time


def read_messages(bag, topics=None) -> Iterator[tuple]:
    """(topic, text, log_time) of every std_msgs/String message in a bag directory or MCAP
    file, in file order (other types, the markers, are left out)."""
    for topic, decoded, log_time in read_decoded(bag, topics, STRING):
        yield topic, decoded.data, log_time


def bag_topics(bag, type_name: str | None = STRING) -> dict:
    """{topic: offered QoS} of the topics of a finished bag directory or MCAP file of the
    type ``type_name`` (String: the JSON topics a replay can publish; None: all)."""
    bag = Path(bag)
    topics = {}
    for path in _files_of(bag):
        with open(path, 'rb') as handle:
            summary = make_reader(handle).get_summary()
        if summary is None:
            raise McapError(f'{path} has no summary: run `python -m stars_ros.recording recover {bag}` first')
        for channel in summary.channels.values():
            schema = summary.schemas.get(channel.schema_id)
            if type_name is None or (schema is not None and schema.name == type_name):
                topics.setdefault(channel.topic, topic_qos(channel))
    return topics
