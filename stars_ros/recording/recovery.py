"""After a hard kill or power loss: find the bags left unfinished, make them valid again,
and read what a damaged file still holds."""
from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

from mcap.exceptions import McapError
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory

from stars_ros.files import atomic_write
from stars_ros.recording.bag import (PID_FILE, STRING, FileStats, McapFile, MessageType, bag_files, encode_string,
                                     is_finished, metadata_text, qos_profile, topic_qos, write_metadata)
from stars_ros.state.migration import JOURNAL, read_journal
from stars_ros.state.reader import committed_feedback


class Salvage(NamedTuple):
    """The records of a possibly truncated MCAP file up to the first damaged one."""

    schemas: dict        # id -> Schema
    channels: dict       # id -> Channel
    messages: list       # Message records, in file order
    custom: dict         # the file's 'stars_ros' metadata
    damage: str | None   # what stopped the reading ('EOFError: …'), None for an intact file

    def declare(self, topics: dict, types: dict) -> None:
        """Add this file's topics ({topic: QoS}) and typed topics' message types ({topic:
        MessageType}) to ``topics`` and ``types``, what a rewrite of it declares again."""
        for channel in self.channels.values():
            topics.setdefault(channel.topic, topic_qos(channel))
            schema = self.schemas.get(channel.schema_id)
            if schema is not None and schema.name != STRING:
                types.setdefault(channel.topic, MessageType(schema.name, bytes(schema.data).decode(),
                                                            channel.metadata.get('topic_type_hash', '')))


def salvage(path: Path) -> Salvage:
    """Every complete record of the MCAP file ``path``, however it ends."""
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
            return Salvage(schemas, channels, messages, custom, f'{type(error).__name__}: {error}')
    return Salvage(schemas, channels, messages, custom, None)


def salvage_messages(path: Path) -> tuple[list, str | None]:
    """(topic, text, log_time) of the complete String messages of a possibly damaged MCAP
    file, in file order, and what damaged it (None): ``read_messages`` for a file that was
    never finished. OSError when the file cannot be read at all."""
    found = salvage(path)
    decoders = DecoderFactory()
    messages = []
    for message in found.messages:
        channel = found.channels.get(message.channel_id)
        schema = None if channel is None else found.schemas.get(channel.schema_id)
        if schema is None or schema.name != STRING:
            continue
        decode = decoders.decoder_for(channel.message_encoding, schema)
        if decode is not None:
            messages.append((channel.topic, decode(message.data).data, message.log_time))
    return messages, found.damage


def recover(bag) -> dict:
    """Make an unfinished bag (hard kill, power loss) valid again.

    Damaged files are rewritten with every complete record they hold, feedback the state
    store in the bag's folder committed for it (and a feedback.jsonl of an earlier version)
    missing from the files is written to a new file, and metadata.yaml is rebuilt. Returns
    {'repaired': [file names], 'feedback_restored': n, 'messages': n}.
    """
    bag = Path(bag)
    files, topics, types, custom, repaired = [], {}, {}, {}, []
    seen = set()
    for path in bag_files(bag):
        found = salvage(path)
        custom = custom or found.custom
        found.declare(topics, types)
        for message in found.messages:
            seen.add((found.channels[message.channel_id].topic, message.log_time, bytes(message.data)))
        if found.damage is not None or not is_finished(path):
            files.append(_rewrite(path, found, topics, types))
            repaired.append(path.name)
        else:
            stats = FileStats(path.name)
            for message in found.messages:
                stats.add(found.channels[message.channel_id].topic, message.log_time)
            files.append(stats)
    missing = []
    journal = bag / JOURNAL
    for entry in committed_feedback(bag.parent, bag.name) + (read_journal(journal) if journal.exists() else []):
        key = (entry['topic'], entry['log_time'], encode_string(entry['data']))
        if key not in seen:
            seen.add(key)
            missing.append(entry)
    if missing:
        for entry in missing:
            topics.setdefault(entry['topic'], qos_profile())
        extra = McapFile.create(bag / f'{bag.name}_{len(files)}.mcap', topics, 1 << 20, custom)
        for entry in missing:
            extra.write(entry['topic'], encode_string(entry['data']), entry['log_time'])
        extra.finish()
        files.append(extra.stats)
    write_metadata(bag, metadata_text(files, topics, custom, types=types))
    (bag / PID_FILE).unlink(missing_ok=True)
    return {'repaired': repaired, 'feedback_restored': len(missing), 'messages': sum(f.count for f in files)}


def _rewrite(path: Path, found: Salvage, topics: dict, types: dict) -> FileStats:
    """Replace the damaged file ``path`` with a finished one of the records ``found`` in it."""
    written = []

    def write(handle):
        rewritten = McapFile(handle, path.name, topics, 1 << 20, found.custom, types)
        for message in found.messages:
            rewritten.write(found.channels[message.channel_id].topic, bytes(message.data), message.log_time)
        rewritten.end()
        written.append(rewritten.stats)
    atomic_write(path, write)
    return written[0]


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
