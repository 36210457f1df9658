"""The ranker's state store: people, their models and ratings, peers' ratings (fleet
sharing) and the journal of accepted feedback, in one SQLite database in the record folder
(``state.db``, WAL mode; schema in docs/state.md).

One update writes only the rows it changes: a person's row, the ratings that joined or left
them, a scene the first time its content is rated (scenes are kept once, by content digest,
with a count of the ratings that name them). A thread of its own writes: the node's executor
queues an update and goes on; the writer takes everything queued into one transaction (group
commit), numbering each write (``write_person`` returns its sequence number). Only once a
transaction is committed does it hand each feedback entry on (``on_feedback_committed``) and
run what waited for its writes (``when_committed``: the node publishes a person's model
then, so nobody sees what a hard kill could take back). ``synchronous=FULL``: a commit
returns once the WAL is fsync'd, so what is committed survives a process kill and a power
cut alike (given a disk that honours flushes); what a kill or a power cut can lose is what
was queued or being written, never acknowledged.

A failing disk (full, read-only, a folder that cannot be created) is reported through
``on_error`` once; what waits is kept in memory, in order, and tried again every
``retry_interval`` seconds until the disk takes it. One process holds a store: ``state.lock``
is flock'd while it is open and names its holder, and a second ``StateStore`` on the same
folder raises StoreLockedError naming that holder (``locking``). ``open_reader`` reads a store
without holding it (``reader``). The rows each write changes are ``rows``'; the tables are in
``schema``; what earlier versions left is taken over at the open (``legacy``).
"""
from __future__ import annotations

import concurrent.futures
import contextlib
import functools
import queue
import sqlite3
import threading
import time
from pathlib import Path
from typing import Callable, Sequence

from stars_ros.errors import ConfigError, StoreError
from stars_ros.state import legacy, locking
from stars_ros.state.forgotten import Forgotten, folder_secret, mentions
from stars_ros.state.reader import StoreReader
from stars_ros.state.rows import Rows
from stars_ros.state.schema import DATABASE, SCHEMA, SCHEMA_VERSION, PersonUpdate


class StateStore:
    """The node's store in ``folder``, held by this process until ``close``.

    Args:
        folder (str or Path): the record folder; created if missing.
        holder (str): who holds it (the node's name), as a refusal names it.
        on_error (callable): ``on_error(text)`` when the disk refuses (once per failure).
        on_recovered (callable, optional): ``on_recovered(text)`` once it works again.
        retry_interval (float, optional): seconds between two tries of a failing disk.
        on_feedback_committed (callable, optional): ``on_feedback_committed(entry)`` on the
            writer's thread for each feedback entry once it is committed.
        on_progress (callable, optional): ``on_progress(text)`` while the open imports a
            state file of an earlier version (how far it is).

    StoreLockedError when another process holds the folder's store. Any other failure
    (the folder cannot be created, the disk is full) leaves the store failing and retried:
    updates wait in memory.
    """

    def __init__(self, folder, holder: str, on_error: Callable[[str], None],
                 on_recovered: Callable[[str], None] | None = None, retry_interval: float = 1.0,
                 on_feedback_committed: Callable[[dict], None] | None = None,
                 on_progress: Callable[[str], None] | None = None):
        self.folder = Path(folder).expanduser()
        self.path = self.folder / DATABASE
        self.holder = f'{holder} ({locking.holder_text()})'
        self.error: str | None = None
        self._on_error, self._on_recovered = on_error, on_recovered or (lambda text: None)
        self._retry_interval = retry_interval
        self._on_feedback_committed = on_feedback_committed or (lambda entry: None)
        self._on_progress = on_progress or (lambda text: None)
        self._connection = None
        self._lock_handle = None
        self._queue = queue.SimpleQueue()
        self._closing = threading.Event()
        self._waiting = []  # items taken from the queue and not committed yet, oldest first
        self._waiting_feedback = 0  # feedback entries queued or waiting, not committed
        self._count_lock = threading.Lock()
        self._sequence = 0  # of the latest write queued
        self._committed_lock = threading.RLock()
        self._committed_sequence = 0  # of the latest write committed
        self._after_commit = []  # (sequence, callback) waiting for their write's commit, in order
        self._rows = Rows(self.folder)  # what each write changes, and what the writer knows of the rows
        self.reader: StoreReader | None = None  # what ``load`` read from, and the Deferred ratings read
        self.imported: list = []  # what the open imported from the files of earlier versions
        self._import_problems: list = []
        self._open()
        self._thread = threading.Thread(target=self._loop, name='stars-state-store', daemon=True)
        self._thread.start()

    # -- opening -----------------------------------------------------------------------------
    def _open(self) -> bool:
        """Lock, open and set up the database; False (reported) when the disk refuses."""
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            if self._lock_handle is None:
                self._lock_handle = locking.hold(self.folder, self.holder)
            connection = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False, timeout=30)
            try:
                connection.execute('PRAGMA journal_mode=WAL')
                connection.execute('PRAGMA synchronous=FULL')
                connection.execute('PRAGMA secure_delete=ON')  # what is deleted is overwritten with zeros
                connection.executescript(SCHEMA)
                version = connection.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
                if version is None:
                    connection.execute("INSERT INTO meta VALUES ('schema_version', ?)",
                                       (str(SCHEMA_VERSION),))
                elif int(version[0]) == 1:
                    legacy.upgrade_from_version_1(connection, self.path, self._on_progress)
                elif int(version[0]) != SCHEMA_VERSION:
                    raise ConfigError(f'{self.path} has schema version {version[0]}; this stars_ros reads '
                                      f'version {SCHEMA_VERSION}')
                self._connection = connection
                self._rows.attach(connection)
                legacy.clear_free_pages(self._rows, fresh=version is None)
                imported, problems = legacy.import_earlier_files(self._rows, self.folder, self._on_progress)
                self.imported += imported
                self._import_problems += problems
            except BaseException:
                self._connection = None
                connection.close()
                raise
        except (OSError, sqlite3.Error) as error:
            self._fail(f'cannot open the state store {self.path}: {error}')
            return False
        if self.error is not None:
            self.error = None
            self._on_recovered(f'state store {self.path} works again')
        return True

    # -- the executor's side -------------------------------------------------------------------
    @property
    def healthy(self) -> bool:
        return self.error is None

    @property
    def uncommitted_feedback(self) -> int:
        """Accepted feedback entries queued or waiting for the disk, not yet committed."""
        with self._count_lock:
            return self._waiting_feedback

    def write_person(self, update: PersonUpdate | None, feedback: Sequence[tuple[dict, str]] = ()) -> int:
        """Queue what the store is to hold of one person now (None: nobody, the feedback
        alone) with the ``feedback`` entries ({'topic', 'log_time', 'data'}, recording) that
        changed it, in one transaction; ``on_feedback_committed(entry)`` runs on the writer's
        thread for each once it is committed. Returns the write's sequence number, for
        ``when_committed``."""
        with self._count_lock:
            self._waiting_feedback += len(feedback)
            self._sequence += 1
            self._queue.put(('person', list(feedback), update, self._sequence))
            return self._sequence

    def forget_person(self, user_id: str) -> int:
        """Remove a person and their ratings (evicted: they go back to the checkpoint);
        returns the write's sequence number."""
        with self._count_lock:
            self._sequence += 1
            self._queue.put(('forget', (), user_id, self._sequence))
            return self._sequence

    def erase_person(self, user_id: str) -> concurrent.futures.Future:
        """Erase ``user_id`` for good: their row, model, ratings, peers' ratings of them and
        every journal entry that names them, with ``secure_delete`` and the write-ahead log
        truncated after the commit, so no page of the files keeps them; and store their
        tombstone (``forgotten``). Idempotent. The Future gives {what: rows removed} once
        done (its exception: why not)."""
        done = concurrent.futures.Future()
        with self._count_lock:
            self._sequence += 1
            self._queue.put(('erase', (), (user_id, done), self._sequence))
        return done

    def erase_older(self, cutoff: int) -> concurrent.futures.Future:
        """Retention: erase every rating and peer rating stamped, and every journal entry
        logged, before ``cutoff`` (ROS time, ns), as ``erase_person`` erases (secure_delete,
        the write-ahead log truncated); a person left with no ratings goes. Queued after
        every write before it. The Future gives {what: rows removed}."""
        done = concurrent.futures.Future()
        with self._count_lock:
            self._sequence += 1
            self._queue.put(('retention', (), (cutoff, done), self._sequence))
        return done

    def keep_tombstone(self, tag: str) -> int:
        """Store one more tombstone (a fleet peer's forget, ``forgotten.fleet_tombstone``);
        returns the write's sequence number."""
        with self._count_lock:
            self._sequence += 1
            self._queue.put(('tombstone', (), tag, self._sequence))
            return self._sequence

    def known_people(self) -> set:
        """Every id the store holds something of (read now): people, peers' ratings, and the
        user ids of the journal's feedback."""
        reader = StoreReader(self.path)
        try:
            return reader.known_people()
        finally:
            reader.close()

    def forgotten(self) -> Forgotten:
        """The tombstones stored here (read now); none while the store cannot be opened (a
        folder that cannot be written: nothing is stored, and the store reports why)."""
        if self.error is not None:
            return Forgotten(None)
        reader = StoreReader(self.path)
        try:
            return Forgotten(folder_secret(self.folder), reader.forgotten_tags())
        finally:
            reader.close()

    def when_committed(self, sequence: int, callback: Callable[[], None]) -> None:
        """``callback()`` once the write ``sequence`` (and every earlier one) is committed:
        now, on this thread, if it is; else on the writer's thread right after the commit.
        Callbacks run in the order their writes were queued, never two at once."""
        with self._committed_lock:
            if sequence > self._committed_sequence:
                self._after_commit.append((sequence, callback))
                return
            self._run(callback)

    @property
    def committed_sequence(self) -> int:
        """The latest write committed (every earlier one is)."""
        with self._committed_lock:
            return self._committed_sequence

    def set_fingerprint(self, fingerprint: str) -> None:
        """The checkpoint now served (a reload): the people rows from now on belong to it."""
        with self._count_lock:
            self._sequence += 1
            self._queue.put(('fingerprint', (), fingerprint, self._sequence))

    def load(self, fingerprint: str) -> tuple[list, str | None]:
        """(the Person rows to restore, least recently rated first, their ratings Deferred;
        why none are restored, else None). People of another checkpoint are not restored;
        their rows are replaced by the first update. Call before the first update."""
        problems = list(self._import_problems)
        if self._connection is None:
            return [], None
        stored = self._rows.meta('fingerprint')
        self.reader = StoreReader(self.path)
        people = self.reader.people(deferred=True)
        if stored is None or not people:
            self.set_fingerprint(fingerprint)
            return [], '; '.join(problems) or None
        if stored != fingerprint:
            self._rows.foreign = True
            problems.append(f'{self.path} holds people solved against checkpoint {stored[:12]}, not the '
                            f'served {fingerprint[:12]}: folded-in users are not restored')
            return [], '; '.join(problems)
        return people, '; '.join(problems) or None

    def signed_feedback(self) -> list:
        """The signed feedback messages of the people ``load`` read (replays stay refused)."""
        return [] if self.reader is None else self.reader.signed_feedback()

    def encodings(self, scenes: Sequence, fingerprint: str) -> dict:
        """id(scene) -> h_i stored for ``fingerprint``, of the restored people's ``scenes``
        (``StoreReader.encodings``; {} before ``load`` or when the disk refuses: the caller
        encodes them)."""
        if self.reader is None:
            return {}
        try:
            return self.reader.encodings(scenes, fingerprint)
        except StoreError:
            return {}

    def close(self) -> list:
        """Commit what waits and close; returns the feedback entries that could not be
        committed (to be logged by the caller)."""
        self._closing.set()
        self._queue.put(('close', (), None, None))
        self._thread.join(timeout=10)
        unstored = [entry for item in self._waiting for entry, _ in item[1]]
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                break
            unstored += [entry for entry, _ in item[1]]
        if self._connection is not None:
            with contextlib.suppress(sqlite3.Error):
                self._connection.close()
            self._connection = None
        if self.reader is not None:
            self.reader.close()
            self.reader = None
        if self._lock_handle is not None:
            self._lock_handle.close()
            self._lock_handle = None
        return unstored

    # -- the writer ------------------------------------------------------------------------------
    def _loop(self):
        closing = False
        while True:
            try:
                self._waiting.append(self._queue.get(timeout=self._retry_interval if self._waiting else None))
            except queue.Empty:
                pass
            while True:
                try:
                    self._waiting.append(self._queue.get_nowait())
                except queue.Empty:
                    break
            if self._waiting and self._waiting[-1][0] == 'close':
                self._waiting.pop()
                closing = True
            if self._waiting and self._commit():
                self._waiting = []
            if closing:
                return
            if self._waiting:  # the disk refuses: wait, then try all of it again (new items join)
                self._closing.wait(self._retry_interval)

    def _commit(self) -> bool:
        """Write every waiting item in one transaction; True once committed."""
        if self._connection is None and not self._open():
            return False
        rows, written, erased = self._rows, {}, []
        try:
            with rows.transaction():
                for kind, feedback, value, _ in self._waiting:
                    for entry, bag in feedback:
                        self._connection.execute(
                            'INSERT INTO feedback (bag, topic, log_time, data, committed) '
                            'VALUES (?, ?, ?, ?, ?)',
                            (bag, entry['topic'], int(entry['log_time']), entry['data'], time.time()))
                    if kind == 'person' and value is not None:
                        rows.replace_foreign(written)
                        rows.write(value, written)
                    elif kind == 'forget':
                        rows.remove(value, written)
                    elif kind == 'retention':
                        erased.append((value[1], rows.erase_older(value[0], written), lambda data: False))
                    elif kind == 'tombstone':
                        self._connection.execute('INSERT OR IGNORE INTO forgotten VALUES (?, ?)',
                                                 (value, time.time()))
                    elif kind == 'erase':
                        erased.append((value[1], rows.erase(value[0], written), mentions(value[0])))
                    elif kind == 'fingerprint':
                        rows.replace_foreign(written)
                        rows.set_fingerprint(value)
        except (sqlite3.Error, OSError) as error:
            rows.fingerprint = None  # rolled back: written again by the next try
            self._fail(f'could not write the state store {self.path}: {error}')
            return False
        rows.keep(written)
        committed = [entry for _, feedback, _, _ in self._waiting for entry, _ in feedback]
        with self._count_lock:
            self._waiting_feedback -= len(committed)
        for entry in committed:  # an erased person's, committed with the erase, is gone from the journal too
            if not any(named(entry['data'].encode('utf-8')) for _, _, named in erased):
                self._run(functools.partial(self._on_feedback_committed, entry))
        if erased:
            self._finish_erasures(erased)
        with self._committed_lock:
            self._committed_sequence = self._waiting[-1][3]
            ready = [callback for sequence, callback in self._after_commit
                     if sequence <= self._committed_sequence]
            self._after_commit = [(s, c) for s, c in self._after_commit if s > self._committed_sequence]
            for callback in ready:
                self._run(callback)
        if self.error is not None:
            self.error = None
            self._on_recovered(f'state store {self.path} works again')
        return True

    def _run(self, callback: Callable[[], None]) -> None:
        try:
            callback()
        except Exception as error:  # noqa: BLE001 - the writer must go on: what it wrote is committed
            self._on_error(f'after a commit of the state store: {type(error).__name__}: {error}')

    def _fail(self, text: str):
        first = self.error is None
        self.error = text
        if first:
            self._on_error(text)

    def _finish_erasures(self, erased: list):
        """Rebuild the database and truncate the write-ahead log after the commit that erased
        people, then tell who waits what was removed. secure_delete zeroes the deleted rows,
        but an index's interior pages keep copies of keys as dividers, which can outlive the
        rows they came from (seen: an erased id left in state.db in one run of six):
        VACUUM writes every page again from what is left."""
        try:
            self._rows.vacuum()
        except sqlite3.Error as error:
            for done, _, _ in erased:
                done.set_exception(StoreError(f'{self.path}: erased, but the write-ahead log still holds old '
                                              f'pages: {error}; erasing again truncates it'))
            return
        for done, removed, _ in erased:
            done.set_result(removed)
