"""Forgetting a person in a record folder: the state store and every bag, crash-safe.

``forget(folder, user_id)`` runs these steps, each of which can run again without harm:

1. an intent record, ``forgetting/<tombstone>.json``, written atomically (``record_intent``;
   a serving node writes it before it erases the person from memory): it holds the id (a
   re-run needs it) only until the last step removes it;
2. the state store erases the person and stores their tombstone (``StateStore.erase_person``:
   secure_delete, the write-ahead log truncated): in a serving node through the owner of
   people (``Personalisation.erase_stored``), with no node here, on a store opened for it;
3. every finished MCAP file holding a message that names them (``state.mentions``) is
   rewritten without those messages: everyone else's message bytes, topics and log times as
   they were, zstd chunks, an index and a summary, into a temporary file that is fsync'd and
   renamed over the old one; then the bag's metadata.yaml is rebuilt from its files;
4. the intent record goes.

A kill at any moment leaves each file before or after its step; ``finish_interrupted``
(run by the node at start and by the command line) finishes every intent it finds. A node
that records hands its ``Recorder`` in: the file it writes is finished first
(``Recorder.rewrite_finished``), so no file is rewritten while it is written.
"""
from __future__ import annotations

import concurrent.futures
import json
import multiprocessing
import os
import time
from pathlib import Path
from typing import Callable

import yaml
from mcap.reader import make_reader

from stars_ros.files import atomic_write
from stars_ros.recording.bag import (METADATA_FILE, FileStats, McapFile, MessageType, bag_files, is_finished,
                                     metadata_text, write_metadata)
from stars_ros.recording.recovery import abandoned_bags, recover, salvage
from stars_ros.state import StateStore, mentions
from stars_ros.state.forgotten import folder_secret, tombstone

INTENTS = 'forgetting'
CHILD_NICENESS = 10  # a serving node's bag rewrites yield the CPU to its rankings


def _fsync_folder(folder: Path) -> None:
    descriptor = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


def rewrite_without(path: Path, drop: Callable[[bytes], bool]) -> FileStats | None:
    """Rewrite the finished MCAP file ``path`` without the messages whose data ``drop``
    says (atomically); None, and the file untouched, when it holds none; else the new
    file's statistics, with ``removed`` {topic: messages removed}."""
    return rewrite_dropping(path, lambda message: drop(bytes(message.data)))


def rewrite_dropping(path: Path, drop: Callable[[object], bool]) -> FileStats | None:
    """``rewrite_without`` with ``drop`` asked of each message record (its ``data``,
    ``log_time``, ``channel_id``)."""
    found = salvage(path)
    if found.damage is not None:
        raise OSError(f'{path} is damaged ({found.damage}): run `python -m stars_ros.recording recover '
                      f'{path.parent}` first')
    kept = [m for m in found.messages if not drop(m)]
    if len(kept) == len(found.messages):
        return None
    topics, types, removed = {}, {}, {}
    found.declare(topics, types)
    for message in found.messages:
        if drop(message):
            topic = found.channels[message.channel_id].topic
            removed[topic] = removed.get(topic, 0) + 1
    written = []

    def write(handle):
        rewritten = McapFile(handle, path.name, topics, 1 << 20, found.custom, types)
        for message in kept:
            rewritten.write(found.channels[message.channel_id].topic, bytes(message.data), message.log_time)
        rewritten.end()
        written.append(rewritten.stats)
    atomic_write(path, write)
    written[0].removed = removed
    return written[0]


def file_stats(path: Path) -> FileStats:
    """What metadata.yaml says of a finished MCAP file, from its summary."""
    with open(path, 'rb') as handle:
        summary = make_reader(handle).get_summary()
    stats = FileStats(path.name)
    if summary is None or summary.statistics is None:
        return stats
    statistics = summary.statistics
    for channel_id, count in statistics.channel_message_counts.items():
        topic = summary.channels[channel_id].topic
        stats.topics[topic] = stats.topics.get(topic, 0) + count
    stats.count = statistics.message_count
    if stats.count:
        stats.start, stats.end = statistics.message_start_time, statistics.message_end_time
    return stats


def rebuild_metadata(bag: Path) -> None:
    """metadata.yaml of a finished bag from its files' summaries (the topics, their QoS
    and types, and the custom data as the old one gave them)."""
    info = yaml.safe_load((bag / METADATA_FILE).read_text())['rosbag2_bagfile_information']
    topics, types = {}, {}
    for entry in info['topics_with_message_count']:
        meta = entry['topic_metadata']
        topics[meta['name']] = (meta.get('offered_qos_profiles') or [None])[0]
        types[meta['name']] = MessageType(meta['type'], '', meta.get('type_description_hash', ''))
    write_metadata(bag, metadata_text([file_stats(path) for path in bag_files(bag)], topics,
                                      info.get('custom_data') or {}, types=types))


def rewrite_without_person(path: str, user_id: str) -> FileStats | None:
    """``rewrite_without`` the messages naming ``user_id``, by arguments a child process takes."""
    return rewrite_without(Path(path), mentions(user_id))


def _erase_from_bags(folder: Path, rewrite: Callable[[Path], FileStats | None], recorder) -> dict:
    """{bag name: messages removed} of every bag in ``folder``, each file through ``rewrite``."""
    removed = {}
    if recorder is not None:
        removed[recorder.name] = sum(sum(stats.removed.values()) for stats in recorder.rewrite_finished(rewrite))
    for bag in sorted(p for p in folder.iterdir() if p.is_dir() and p.name != INTENTS):
        if recorder is not None and bag == recorder.path:
            continue
        for left in bag.glob('*.tmp'):  # a rewrite a kill interrupted: the old file is still in place
            left.unlink()
        files = bag_files(bag)
        if not files:
            continue
        count = 0
        for path in files:
            if not is_finished(path):
                raise OSError(f'{path} is not finished: recover its bag first')
            stats = rewrite(path)
            count += 0 if stats is None else sum(stats.removed.values())
        if (bag / METADATA_FILE).exists():
            rebuild_metadata(bag)  # also after a kill between a file's rename and this
        removed[bag.name] = count
    return removed


def record_intent(folder: Path, user_id: str) -> Path:
    """Write (again) the intent record of forgetting ``user_id`` in ``folder``, durable once
    this returns: a kill from then on leaves the forget for the next start to finish."""
    if not user_id:
        raise ValueError('user_id is empty: an empty id names nobody')
    intents = folder / INTENTS
    intents.mkdir(exist_ok=True)
    intent = intents / f'{tombstone(folder_secret(folder, create=True), user_id)}.json'
    if not intent.exists():
        data = json.dumps({'user_id': user_id, 'started': time.time()}).encode()
        atomic_write(intent, lambda handle: handle.write(data))
    return intent


def forget(folder, user_id: str, erase_stored: Callable[[str], dict] | None = None, recorder=None,
           timeout: float = 600, in_child: bool = False) -> dict:
    """Erase ``user_id`` from the record folder ``folder`` (the module docstring's steps).
    ``erase_stored``: a running node's owner of people, which erases them from the store it
    holds ({table: rows removed}); None: no node runs, and the store is opened here (refused
    while a node holds it: StoreLockedError). ``recorder``: that node's Recorder.
    ``in_child``: the bag files are rewritten in a child process at a lower CPU priority, so a
    serving node's rankings keep its interpreter and come first for the CPU. Returns
    {'state_store': {table: rows removed}, 'bags': {bag: messages removed}}."""
    folder = Path(folder).expanduser()
    intent = record_intent(folder, user_id)
    erased = _erase_offline(folder, user_id, timeout) if erase_stored is None else erase_stored(user_id)
    if recorder is None:
        for bag in abandoned_bags(folder):
            recover(bag)
    if not in_child:
        bags = _erase_from_bags(folder, lambda path: rewrite_without(path, mentions(user_id)), recorder)
    else:
        with concurrent.futures.ProcessPoolExecutor(1, multiprocessing.get_context('spawn'), os.nice,
                                                    (CHILD_NICENESS,)) as child:
            bags = _erase_from_bags(folder, lambda path: child.submit(rewrite_without_person, str(path),
                                                                      user_id).result(), recorder)
    intent.unlink()
    _fsync_folder(intent.parent)
    return {'state_store': erased, 'bags': bags}


def _erase_offline(folder: Path, user_id: str, timeout: float) -> dict:
    """The store's step with no node running: the only writer of a person besides the owner
    a serving node holds (``Personalisation``), and only while no node holds the store."""
    store = StateStore(folder, 'python -m offline_training.forget', on_error=lambda text: None)
    try:
        if store.error is not None:
            raise OSError(store.error)
        return store.erase_person(user_id).result(timeout)
    finally:
        store.close()


def interrupted(folder) -> list:
    """The ids of forgets begun in ``folder`` and not finished (the intent records)."""
    intents = Path(folder).expanduser() / INTENTS
    found = []
    for path in sorted(intents.glob('*.json')) if intents.is_dir() else ():
        try:
            found.append(json.loads(path.read_text())['user_id'])
        except (OSError, ValueError, KeyError, TypeError):
            path.unlink(missing_ok=True)  # a kill before its atomic write finished leaves no intent
    return found


def finish_interrupted(folder, erase_stored: Callable[[str], dict] | None = None, recorder=None) -> dict:
    """Finish every forget a kill interrupted in ``folder`` (``forget``'s arguments):
    {user_id: what was removed}."""
    return {user_id: forget(folder, user_id, erase_stored, recorder) for user_id in interrupted(folder)}


def _older(cutoff: int):
    def older(path: Path) -> FileStats | None:
        stats = file_stats(path)
        if not stats.count or stats.start >= cutoff:  # nothing old in it: not read
            return None
        return rewrite_dropping(path, lambda message: message.log_time < cutoff)
    return older


def erase_older(folder, cutoff: int, recorder=None) -> dict:
    """Retention: every bag message of ``folder`` logged before ``cutoff`` (ROS time, ns)
    goes, each file rewritten atomically as a forget rewrites it (a kill leaves each file
    before or after; the next pass finishes); {bag: messages removed}. ``recorder``: a
    serving node's, whose bag is rewritten through it (its file in progress finished first)."""
    folder = Path(folder).expanduser()
    older, removed = _older(cutoff), {}
    for bag in sorted(p for p in folder.iterdir() if p.is_dir() and p.name != INTENTS):
        if recorder is not None and bag == recorder.path:  # its file in progress is finished first (a new one
            count = sum(sum(stats.removed.values()) for stats in recorder.rewrite_finished(older))  # each pass)
            if count:
                removed[bag.name] = count
            continue
        for left in bag.glob('*.tmp'):
            left.unlink()
        count, files = 0, bag_files(bag)
        for path in files:
            if is_finished(path):
                stats = older(path)
                count += 0 if stats is None else sum(stats.removed.values())
        if (count or _bag_start(bag) < cutoff) and files and (bag / METADATA_FILE).exists():
            rebuild_metadata(bag)  # also after a kill between a file's rename and this
        if count:
            removed[bag.name] = count
    return removed


def _bag_start(bag: Path) -> float:
    """When the recording ``bag`` began, by its metadata.yaml (ns; infinite when it says nothing)."""
    try:
        info = yaml.safe_load((bag / METADATA_FILE).read_text())['rosbag2_bagfile_information']
        return int(info['starting_time']['nanoseconds_since_epoch']) if info['message_count'] else float('inf')
    except (OSError, KeyError, TypeError, ValueError):
        return float('inf')
