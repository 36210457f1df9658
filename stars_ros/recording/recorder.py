"""The recorder: String messages of the node's topics, and CDR-encoded messages of other types
(``types``), into one bag (``bag``), from the threads that serve requests; feedback once the
state store has committed it (``stars_ros.state``), so the bag's feedback is what the store journaled.

Every ``flush_interval`` seconds a thread of its own writes out the chunk in progress,
fsyncs it and rewrites metadata.yaml, so a hard kill loses at most that interval of the
other topics (``recovery.recover`` adds the store's committed feedback back); the fsyncs
run outside the lock the serving threads record under. Disk errors never raise to the
caller: they are reported through ``on_event`` and retried at each flush, and committed
feedback the file could not take waits in memory until it can. ``close`` writes block
YAML, as rosbag2 does, and repairs a file that a failure left unfinished.
"""
from __future__ import annotations

import datetime
import os
import threading
from dataclasses import replace
from pathlib import Path
from typing import Callable

from stars_ros.recording.bag import PID_FILE, McapFile, encode_string, metadata_text, write_metadata
from stars_ros.recording.recovery import recover


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
        types (dict, optional): topic name -> ``bag.MessageType`` of the topics that are not
            std_msgs/String; their messages are recorded with ``write_encoded``.
    """

    def __init__(self, folder, topics: dict, *, rotation_bytes: int = 64 << 20, flush_interval: float = 1.0,
                 name: str | None = None, custom: dict | None = None,
                 on_event: Callable[[str, str], None] | None = None, types: dict | None = None):
        if rotation_bytes < 4096:
            raise ValueError('rotation_bytes must be at least 4096')
        if not flush_interval > 0:
            raise ValueError('flush_interval must be positive')
        stamp = datetime.datetime.now(datetime.timezone.utc).strftime('%Y_%m_%d-%H_%M_%S')
        self.name = name or f'stars_{stamp}'
        self.path = Path(folder).expanduser() / self.name
        self.topics = dict(topics)
        self.types = dict(types or {})
        self.rotation_bytes = rotation_bytes
        self.flush_interval = flush_interval
        self.custom = dict(custom or {})
        self.error: str | None = None
        self.dropped = 0
        self._on_event = on_event or (lambda level, text: None)
        self._chunk_size = min(1 << 20, rotation_bytes // 8)
        self._lock = threading.RLock()
        self._sync_lock = threading.Lock()  # orders metadata writes; taken after _lock, never before it
        self._metadata_generation = self._metadata_written = 0
        self._files: list = []
        self._file: McapFile | None = None
        self._unrecorded: list = []  # committed feedback not yet in an MCAP file
        self._closed = False
        self._damaged = False
        self._stop = threading.Event()
        with self._lock:
            self._open()
        self._flusher = threading.Thread(target=self._flush_loop, name='stars-recorder-flush', daemon=True)
        self._flusher.start()

    # -- state -----------------------------------------------------------------------------
    @property
    def unrecorded_feedback(self) -> int:
        """Committed feedback not yet in an MCAP file (kept in memory, retried)."""
        with self._lock:
            return len(self._unrecorded)

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
        """Create the bag directory and next file; on failure stay in error state."""
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            (self.path / PID_FILE).write_text(f'{os.getpid()}\n')
            path = self.path / f'{self.name}_{len(self._files)}.mcap'
            self._file = McapFile.create(path, self.topics, self._chunk_size, self.custom, self.types)
            self._files.append(self._file.stats)
            self._write_metadata(self._metadata_snapshot())
        except OSError as error:
            self._fail(error, 'opening the bag')
            return
        self._record_committed()
        self._check_healthy()

    def _check_healthy(self):
        if self.error is not None and self._file is not None and not self._unrecorded:
            self.error = None
            self._on_event('info', f'recording to {self.path} works again')

    # -- writing ---------------------------------------------------------------------------
    def write(self, topic: str, text: str, log_time: int) -> bool:
        """Record ``text`` on ``topic`` at ``log_time`` (ns); False if it could not be."""
        return self.write_encoded(topic, encode_string(text), log_time)

    def write_encoded(self, topic: str, data: bytes, log_time: int) -> bool:
        """Record ``data``, the CDR bytes of a message of the topic's type (``types``; String
        unless named), at ``log_time`` (ns); False if it could not be."""
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

    def write_feedback(self, topic: str, text: str, log_time: int) -> None:
        """Record feedback the state store has committed; kept in memory, in order, while
        the file cannot take it. Not to be called once ``close`` has begun."""
        with self._lock:
            self._unrecorded.append((topic, text, log_time))
            self._record_committed()

    def _record_committed(self):
        """Committed feedback into the MCAP file, oldest first, while the file takes it."""
        while self._unrecorded and self._file is not None:
            if not self.write(*self._unrecorded[0]):
                return
            self._unrecorded.pop(0)

    def _rotate(self):
        self._file.finish()
        self._file = None
        self._open()

    def rewrite_finished(self, rewrite: Callable[[Path], object]) -> list:
        """Finish the file being written (the next message starts a new one), then call
        ``rewrite(path)`` on each finished file of the bag, outside the lock, so recording
        goes on meanwhile; a rewrite that returns new ``FileStats`` has them in
        metadata.yaml. Returns those FileStats (a forget rewrites a person out)."""
        with self._lock:
            if self._file is not None and self._file.stats.count:
                self._rotate()
            finished = self._files[:-1] if self._file is not None else list(self._files)
        rewritten = {}
        for stats in finished:
            new = rewrite(self.path / stats.path)
            if new is not None:
                rewritten[stats.path] = new
        with self._lock:
            self._files = [rewritten.get(f.path, f) for f in self._files]
            snapshot = self._metadata_snapshot()
        self._write_metadata(snapshot)
        return list(rewritten.values())

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
            if self._file is not None:
                try:
                    self._file.flush()
                    synced = (self._file, os.dup(self._file.stream.fileno()), self._metadata_snapshot())
                except OSError as error:
                    self._fail(error, 'flushing')
            self._record_committed()
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
        text = metadata_text(files, self.topics, self.custom, interim, self.types)
        with self._sync_lock:
            if generation > self._metadata_written:
                write_metadata(self.path, text)
                self._metadata_written = generation

    def _flush_loop(self):
        while not self._stop.wait(self.flush_interval):
            self.flush()

    def close(self) -> int:
        """Finish the current file, write metadata.yaml and remove the pid marker (a bag
        left damaged is repaired, with the store's committed feedback). Returns how many
        committed feedback messages the MCAP files could not take (recovery adds them)."""
        self._stop.set()
        if self._flusher is not threading.current_thread():
            self._flusher.join()
        with self._lock:
            if self._closed:
                return len(self._unrecorded)
            self._record_committed()
            self._closed = True
            try:
                if self._file is not None:
                    self._file.finish()
                    self._file = None
                if self._damaged or self._unrecorded:
                    recover(self.path)
                elif self._files:
                    self._write_metadata(self._metadata_snapshot(), interim=False)
                (self.path / PID_FILE).unlink(missing_ok=True)
            except OSError as error:
                self._fail(error, 'closing')
            return len(self._unrecorded)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
