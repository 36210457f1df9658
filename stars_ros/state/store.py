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
folder raises StoreLockedError naming that holder. ``open_reader`` reads a store without
holding it (the inspection command, ``refit``, recovery, tests), also while a node writes.
"""
from __future__ import annotations

import concurrent.futures
import contextlib
import fcntl
import functools
import gc
import hashlib
import json
import os
import queue
import socket
import sqlite3
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, NamedTuple, Sequence

import numpy as np

from stars_ros.errors import ConfigError, StoreError, StoreLockedError
from stars_ros.state import migration
from stars_ros.state.forgotten import Forgotten, folder_secret, mentions
from stars_ros.state.person import Deferred, Rating, UserModel, scene_digest

DATABASE = 'state.db'
LOCK_FILE = 'state.lock'
SCHEMA_VERSION = 2  # 2: a person's covariance in its own table, read when first used (1: in people)
_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS people (
    person TEXT PRIMARY KEY, fingerprint TEXT, p BLOB, b REAL, n_ratings INTEGER, regularisation REAL,
    solved INTEGER NOT NULL, dropped INTEGER NOT NULL, ratings INTEGER NOT NULL,
    peer_ratings INTEGER NOT NULL, rated INTEGER NOT NULL, updated REAL NOT NULL);
CREATE TABLE IF NOT EXISTS posteriors (person TEXT PRIMARY KEY, covariance BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS scenes (digest TEXT PRIMARY KEY, content TEXT NOT NULL, refs INTEGER NOT NULL)
    WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS ratings (
    person TEXT NOT NULL, id TEXT NOT NULL, position INTEGER NOT NULL, stamp INTEGER NOT NULL,
    origin TEXT NOT NULL, action TEXT NOT NULL, score REAL NOT NULL, scene_id TEXT, scene TEXT NOT NULL,
    feedback TEXT, PRIMARY KEY (person, id)) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS peer_ratings (
    person TEXT NOT NULL, id TEXT NOT NULL, position INTEGER NOT NULL, stamp INTEGER NOT NULL,
    origin TEXT NOT NULL, action TEXT NOT NULL, score REAL NOT NULL, scene_id TEXT, scene TEXT NOT NULL,
    feedback TEXT, PRIMARY KEY (person, id)) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS encodings (digest TEXT NOT NULL, fingerprint TEXT NOT NULL, h BLOB NOT NULL,
    PRIMARY KEY (digest, fingerprint)) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS feedback (
    seq INTEGER PRIMARY KEY, bag TEXT NOT NULL, topic TEXT NOT NULL, log_time INTEGER NOT NULL,
    data TEXT NOT NULL, committed REAL NOT NULL);
CREATE TABLE IF NOT EXISTS forgotten (tag TEXT PRIMARY KEY, forgotten REAL NOT NULL) WITHOUT ROWID;
"""
_RATING_TABLES = ('ratings', 'peer_ratings')


class PersonUpdate(NamedTuple):
    """What the store is to hold of one person now: ``model`` (None: none served),
    ``fingerprint`` of the checkpoint it was solved against, own ``ratings`` in arrival
    order, ``dropped`` (own ratings no longer kept), ``peer_ratings``, and ``solved``: the
    model was solved from exactly these ratings (False: they changed since); ``encoded``:
    id(scene) -> h_i [dim] of rated scenes the checkpoint ``fingerprint`` has encoded and
    the store may not hold yet (a deterministic function of the scene and the checkpoint,
    kept so that a restored person is solved again without running the encoder)."""

    user_id: str
    model: UserModel | None
    fingerprint: str
    ratings: list
    dropped: int
    peer_ratings: list
    solved: bool
    encoded: dict | None = None


@dataclass
class Person:
    """One person as the store holds them (``PersonUpdate``'s fields, and when they last
    changed, seconds since the epoch)."""

    user_id: str
    model: UserModel | None
    fingerprint: str | None
    ratings: list = field(default_factory=list)
    dropped: int = 0
    peer_ratings: list = field(default_factory=list)
    solved: bool = False
    updated: float = 0.0


def _blob(array) -> bytes | None:
    return None if array is None else np.ascontiguousarray(array, dtype='<f8').tobytes()


def _array(blob, shape=None):
    if blob is None:
        return None
    array = np.frombuffer(blob, dtype='<f8').astype(np.float64)
    return array if shape is None else array.reshape(shape)


def _scene_row(scene) -> tuple[str, str]:
    """(``scene_digest``, content text) of a rated scene; a scene graph is serialised once
    for both (its text is what ``scene_digest`` hashes)."""
    if not isinstance(scene, dict):  # a tabular row: short
        return scene_digest(scene), json.dumps([float(v) for v in scene], separators=(',', ':'))
    text = json.dumps(scene, sort_keys=True, separators=(',', ':'))
    return hashlib.blake2b(text.encode(), digest_size=16).hexdigest(), text


@contextlib.contextmanager
def _collector_paused():
    """Python's cyclic garbage collector off for a while: decoding a legacy state file makes
    millions of small objects, none in a cycle, and with the collector on each of its full
    passes walks all of them (measured: 4× the decode's own time)."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


class _ReadOnce:
    """``read()`` the first time it is called, what it gave every time after."""

    __slots__ = ('_read', '_value')

    def __init__(self, read: Callable[[], object]):
        self._read, self._value = read, None

    def __call__(self):
        if self._value is None:
            self._value = self._read()
        return self._value


def _reading(method):
    """``method`` with sqlite3's errors raised as StoreError naming the store and what to do."""
    @functools.wraps(method)
    def read(self, *args, **kwargs):
        try:
            return method(self, *args, **kwargs)
        except sqlite3.Error as error:
            raise StoreError(f'cannot read the state store {self.path}: {error}; check that it is a stars_ros '
                             'state.db, readable, and not damaged (a copy of the record folder can be inspected '
                             'with python -m stars_ros.recording state FOLDER)') from None
    return read


def holder_text() -> str:
    return f'pid {os.getpid()} on {socket.gethostname()}'


class StoreReader:
    """A state store opened read-only: it takes no lock and changes nothing, so it reads a
    store a running node holds (what the node had committed when each query ran)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        if self.path.is_dir():
            self.path = self.path / DATABASE
        if not self.path.exists():
            raise FileNotFoundError(f'no state store at {self.path}')
        self._connection = self._connect()
        version = int(self.meta().get('schema_version', SCHEMA_VERSION))
        self._posteriors = 'people' if version == 1 else 'posteriors'  # where the covariances are
        self._scenes = {}  # digest -> scene object: ratings of one content share one
        self._digests = {}  # id(scene object) -> its digest, of the scenes read

    @_reading
    def _connect(self):
        connection = sqlite3.connect(f'file:{self.path}?mode=ro', uri=True, timeout=30, check_same_thread=False)
        connection.execute('SELECT COUNT(*) FROM meta').fetchone()  # not a database, or not a store: said now
        return connection

    def close(self):
        self._connection.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    @_reading
    def meta(self) -> dict:
        return dict(self._connection.execute('SELECT key, value FROM meta'))

    @property
    def fingerprint(self) -> str | None:
        return self.meta().get('fingerprint')

    @_reading
    def summary(self) -> list:
        """One dict per person, least recently rated first: ratings and peer ratings held,
        dropped, whether a model is stored and solved from them, the model's fingerprint,
        and when they last changed (seconds since the epoch)."""
        rows = self._connection.execute(
            'SELECT person, fingerprint, p IS NOT NULL, n_ratings, solved, dropped, ratings, peer_ratings, updated '
            'FROM people ORDER BY rated')
        return [{'person': person, 'ratings': ratings, 'peer_ratings': peer_ratings, 'dropped': dropped,
                 'model': bool(has_model), 'solved': bool(solved), 'n_ratings': n_ratings,
                 'fingerprint': fingerprint, 'updated': updated}
                for person, fingerprint, has_model, n_ratings, solved, dropped, ratings, peer_ratings, updated in rows]

    @_reading
    def people(self, deferred: bool = False) -> list:
        """Every Person, least recently rated first, with their ratings and their model's
        covariance; ``deferred``: as ``Deferred`` loaders that read them when first used (a
        person without any ratings: []), so that reading 10,000 people reads no covariance."""
        people = []
        posterior = {person for (person,) in self._connection.execute(
            f'SELECT person FROM {self._posteriors} WHERE covariance IS NOT NULL')}
        for row in self._connection.execute(
                'SELECT person, fingerprint, p, b, n_ratings, regularisation, solved, dropped, ratings, '
                'peer_ratings, updated FROM people ORDER BY rated'):
            person, fingerprint, p, b, n_ratings, regularisation, solved, dropped, own, peer, updated = row
            model = None
            if p is not None:
                p = _array(p)
                covariance = None
                if person in posterior:
                    read = functools.partial(self.covariance, person, len(p) + 1)
                    covariance = Deferred(_ReadOnce(read)) if deferred else read()
                model = UserModel(p, b, n_ratings, regularisation, covariance)
            held = [(Deferred(functools.partial(self.ratings, person, table)) if deferred else
                     self.ratings(person, table)) if count else [] for table, count in zip(_RATING_TABLES, (own, peer))]
            people.append(Person(person, model, fingerprint, held[0], dropped, held[1], bool(solved), updated))
        return people

    @_reading
    def ratings(self, person: str, table: str = 'ratings') -> list:
        """``person``'s ratings (``table`` 'peer_ratings': their peers'), oldest first."""
        rows = self._connection.execute(
            f'SELECT r.id, r.stamp, r.origin, r.action, r.score, r.scene_id, r.scene, r.feedback, s.content '
            f'FROM {table} r JOIN scenes s ON s.digest = r.scene WHERE r.person = ? ORDER BY r.position', (person,))
        ratings = []
        for rating_id, stamp, origin, action, score, scene_id, digest, feedback, content in rows:
            scene = self._scenes.get(digest)
            if scene is None:
                scene = self._scenes[digest] = json.loads(content)
                self._digests[id(scene)] = digest
            ratings.append(Rating(scene, action, score, scene_id, rating_id, stamp, origin,
                                  None if feedback is None else json.loads(feedback)))
        return ratings

    @_reading
    def encodings(self, scenes: Sequence, fingerprint: str) -> dict:
        """id(scene) -> h_i [dim] stored for checkpoint ``fingerprint``, of those of ``scenes``
        (scene objects this reader's ``ratings`` gave) that have one."""
        digests = {self._digests[id(scene)]: id(scene) for scene in scenes if id(scene) in self._digests}
        found, keys = {}, list(digests)
        for start in range(0, len(keys), 500):
            chunk = keys[start:start + 500]
            marks = ','.join('?' * len(chunk))
            for digest, h in self._connection.execute(
                    f'SELECT digest, h FROM encodings WHERE fingerprint = ? AND digest IN ({marks})', (fingerprint, *chunk)):
                found[digests[digest]] = _array(h)
        return found

    @_reading
    def covariance(self, person: str, size: int) -> np.ndarray | None:
        """``person``'s stored covariance [size, size] (None: none stored)."""
        row = self._connection.execute(f'SELECT covariance FROM {self._posteriors} WHERE person = ?',
                                       (person,)).fetchone()
        return None if row is None else _array(row[0], (size, size))

    @_reading
    def signed_feedback(self) -> list:
        """The signed feedback messages of every person's own ratings (replays stay refused)."""
        return [json.loads(text) for (text,) in
                self._connection.execute('SELECT feedback FROM ratings WHERE feedback IS NOT NULL')]

    @_reading
    def forgotten_tags(self) -> set:
        """The tombstones of the people forgotten here (``state.forgotten``)."""
        if self._connection.execute("SELECT 1 FROM sqlite_master WHERE name = 'forgotten'").fetchone() is None:
            return set()  # a store of a version that forgot nobody
        return {tag for (tag,) in self._connection.execute('SELECT tag FROM forgotten')}

    @_reading
    def known_people(self) -> set:
        """Every id this store holds something of: people, peers' ratings, the journal's
        feedback (its ``user_id``, read by SQLite's JSON functions)."""
        query = ('SELECT person FROM people UNION SELECT person FROM peer_ratings UNION '
                 "SELECT json_extract(data, '$.user_id') FROM feedback WHERE json_valid(data)")
        return {person for (person,) in self._connection.execute(query) if isinstance(person, str) and person}

    @_reading
    def feedback_count(self) -> int:
        return self._connection.execute('SELECT COUNT(*) FROM feedback').fetchone()[0]

    @_reading
    def feedback(self, bag: str | None = None) -> list:
        """Committed feedback entries {'topic', 'log_time', 'data', 'bag'} in commit order
        (of one bag's recording, or all)."""
        query, args = 'SELECT topic, log_time, data, bag FROM feedback', ()
        if bag is not None:
            query, args = query + ' WHERE bag = ?', (bag,)
        return [{'topic': t, 'log_time': n, 'data': d, 'bag': b}
                for t, n, d, b in self._connection.execute(query + ' ORDER BY seq', args)]


def open_reader(path) -> StoreReader:
    """A read-only StoreReader of the store in folder ``path`` (or the database file
    ``path``); FileNotFoundError when there is none."""
    return StoreReader(Path(path).expanduser())


def forgotten_in(folder) -> Forgotten:
    """The tombstones of the record folder ``folder`` (none without a store or a secret);
    StoreError when its store cannot be read."""
    secret = folder_secret(folder)
    path = Path(folder).expanduser() / DATABASE
    if secret is None or not path.exists():
        return Forgotten(secret)
    with open_reader(path) as reader:
        return Forgotten(secret, reader.forgotten_tags())


def committed_feedback(folder, bag: str) -> list:
    """The feedback a store in ``folder`` committed for the recording ``bag`` ([] without a
    store); StoreError when it cannot be read."""
    path = Path(folder) / DATABASE
    if not path.exists():
        return []
    with open_reader(path) as reader:
        return reader.feedback(bag)


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
        self.holder = f'{holder} ({holder_text()})'
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
        self._written = {}  # (table, person) -> {rating id: scene digest}, as committed, of those written
        self._rated = {}  # person -> order of their last rating change
        self._counter = 0  # positions and rating orders, increasing
        self._foreign = False  # the rows belong to another checkpoint: replaced on the first write
        self._fingerprint = None  # the checkpoint the rows belong to, as meta holds it
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
            self._lock()
            connection = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False, timeout=30)
            try:
                connection.execute('PRAGMA journal_mode=WAL')
                connection.execute('PRAGMA synchronous=FULL')
                connection.execute('PRAGMA secure_delete=ON')  # what is deleted is overwritten with zeros
                connection.executescript(_SCHEMA)
                version = connection.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
                if version is None:
                    connection.execute("INSERT INTO meta VALUES ('schema_version', ?)", (str(SCHEMA_VERSION),))
                elif int(version[0]) == 1:
                    self._upgrade_from_version_1(connection)
                elif int(version[0]) != SCHEMA_VERSION:
                    raise ConfigError(f'{self.path} has schema version {version[0]}; this stars_ros reads '
                                      f'version {SCHEMA_VERSION}')
                self._connection = connection
                self._clear_free_pages(fresh=version is None)
                self._read_written()
                self._import_earlier_files()
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

    def _upgrade_from_version_1(self, connection):
        """Move the covariances out of ``people`` into ``posteriors`` (schema version 2)."""
        self._on_progress(f'upgrading {self.path} from schema version 1 to 2 (covariances in a table of their own)')
        connection.execute('BEGIN IMMEDIATE')
        try:
            connection.execute('INSERT INTO posteriors SELECT person, covariance FROM people WHERE covariance IS NOT '
                               'NULL')
            connection.execute('ALTER TABLE people DROP COLUMN covariance')
            connection.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'", (str(SCHEMA_VERSION),))
        except BaseException:
            connection.execute('ROLLBACK')
            raise
        connection.execute('COMMIT')

    def _clear_free_pages(self, fresh: bool):
        """Once per store: VACUUM what earlier versions deleted without ``secure_delete``
        (their free pages and cells may still hold it), then empty the write-ahead log; a
        store made now has nothing to clear."""
        if self._meta('secure_delete') is not None:
            return
        if fresh:
            self._connection.execute("INSERT INTO meta VALUES ('secure_delete', ?)", (str(time.time()),))
            return
        self._connection.execute('VACUUM')
        self._connection.execute("INSERT INTO meta VALUES ('secure_delete', ?)", (str(time.time()),))
        self._truncate_log()

    def _truncate_log(self):
        """Checkpoint the write-ahead log into the database and truncate it to nothing, so
        no page of it keeps what a commit deleted; retried while a reader holds it."""
        for _ in range(200):
            busy, _, _ = self._connection.execute('PRAGMA wal_checkpoint(TRUNCATE)').fetchone()
            if not busy:
                return
            time.sleep(0.05)
        raise sqlite3.OperationalError('the write-ahead log stays in use by a reader: not truncated')

    def _lock(self):
        if self._lock_handle is not None:
            return
        handle = open(self.folder / LOCK_FILE, 'a+')
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            other = handle.read().strip() or 'another process'
            handle.close()
            raise StoreLockedError(f'the state store in {self.folder} is held by {other}: one store per node; give '
                                   'this node its own record_folder (the default is named after the node)') from None
        except OSError:
            handle.close()
            raise
        handle.seek(0)
        handle.truncate()
        handle.write(self.holder + '\n')
        handle.flush()
        self._lock_handle = handle

    def _read_written(self):
        """The orders the writer continues from (what each person holds is read when first written)."""
        self._counter = max([self._connection.execute(f'SELECT COALESCE(MAX(position), 0) FROM {t}').fetchone()[0]
                             for t in _RATING_TABLES] +
                            [self._connection.execute('SELECT COALESCE(MAX(rated), 0) FROM people').fetchone()[0]])
        self._rated = dict(self._connection.execute('SELECT person, rated FROM people'))
        self._fingerprint = self._meta('fingerprint')

    def _import_earlier_files(self):
        """user_models.json and every bag's feedback.jsonl, once each (noted in meta)."""
        meta = dict(self._connection.execute('SELECT key, value FROM meta'))
        state_file = self.folder / migration.STATE_FILE
        key = f'imported:{migration.STATE_FILE}'
        if state_file.exists() and key not in meta:
            self._on_progress(f'importing {state_file} ({state_file.stat().st_size / 1e6:.0f} MB, kept by an earlier '
                              'version) into the state store, once: the node serves when it is in')
            with _collector_paused():
                try:
                    state = migration.read_state_file(state_file)
                except ValueError as error:
                    self._import_problems.append(f'{error}: its folded-in users are not imported')
                    state = None
                with self._transaction():
                    if state is not None:
                        self._import_state(state)
                    self._connection.execute('INSERT INTO meta VALUES (?, ?)', (key, str(time.time())))
            if state is not None:
                self.imported.append(f'{len(state.models)} people from {state_file}')
        for journal in sorted(self.folder.glob(f'*/{migration.JOURNAL}')):
            key = f'imported:{journal.parent.name}/{migration.JOURNAL}'
            if key in meta:
                continue
            entries = migration.read_journal(journal)
            with self._transaction():
                self._connection.executemany(
                    'INSERT INTO feedback (bag, topic, log_time, data, committed) VALUES (?, ?, ?, ?, ?)',
                    [(journal.parent.name, e['topic'], int(e['log_time']), e['data'], time.time()) for e in entries])
                self._connection.execute('INSERT INTO meta VALUES (?, ?)', (key, str(time.time())))
            self.imported.append(f'{len(entries)} feedback messages from {journal}')

    def _import_state(self, state: migration.LegacyState):
        if self._connection.execute('SELECT COUNT(*) FROM people').fetchone()[0] == 0:
            self._set_fingerprint(state.fingerprint)
        elif self._meta('fingerprint') != state.fingerprint:
            self._import_problems.append(f'{self.folder / migration.STATE_FILE} holds people of checkpoint '
                                         f'{state.fingerprint[:12]}, the store those of another: not imported')
            return
        written = {}
        people = sorted(state.models.keys() | state.histories.keys() | state.peers.keys())
        step = max(1, len(people) // 10)
        for done, user_id in enumerate(people, 1):
            ratings, dropped = state.histories.get(user_id, ([], 0))
            self._write_person(PersonUpdate(user_id, state.models.get(user_id), state.fingerprint, ratings, dropped,
                                            state.peers.get(user_id, []), False), written)
            if done % step == 0 or done == len(people):
                self._on_progress(f'imported {done} of {len(people)} people from {self.folder / migration.STATE_FILE}')
        self._written.update(written)

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
        stored = self._meta('fingerprint')
        self.reader = StoreReader(self.path)
        people = self.reader.people(deferred=True)
        if stored is None or not people:
            self.set_fingerprint(fingerprint)
            return [], '; '.join(problems) or None
        if stored != fingerprint:
            self._foreign = True
            problems.append(f'{self.path} holds people solved against checkpoint {stored[:12]}, not the served '
                            f'{fingerprint[:12]}: folded-in users are not restored')
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
        written, erased = {}, []
        try:
            with self._transaction():
                for kind, feedback, value, _ in self._waiting:
                    for entry, bag in feedback:
                        self._connection.execute(
                            'INSERT INTO feedback (bag, topic, log_time, data, committed) VALUES (?, ?, ?, ?, ?)',
                            (bag, entry['topic'], int(entry['log_time']), entry['data'], time.time()))
                    if kind == 'person' and value is not None:
                        self._replace_foreign(written)
                        self._write_person(value, written)
                    elif kind == 'forget':
                        self._forget(value, written)
                    elif kind == 'retention':
                        erased.append((value[1], self._erase_older(value[0], written), lambda data: False))
                    elif kind == 'tombstone':
                        self._connection.execute('INSERT OR IGNORE INTO forgotten VALUES (?, ?)', (value, time.time()))
                    elif kind == 'erase':
                        erased.append((value[1], self._erase(value[0], written), mentions(value[0])))
                    elif kind == 'fingerprint':
                        self._replace_foreign(written)
                        self._set_fingerprint(value)
        except (sqlite3.Error, OSError) as error:
            self._fingerprint = None  # rolled back: written again by the next try
            self._fail(f'could not write the state store {self.path}: {error}')
            return False
        if written.pop('replaced', False):
            self._foreign = False
        self._written.update(written)
        for key in [k for k, v in self._written.items() if v is None]:
            del self._written[key]
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
            ready = [callback for sequence, callback in self._after_commit if sequence <= self._committed_sequence]
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

    @contextlib.contextmanager
    def _transaction(self):
        self._connection.execute('BEGIN IMMEDIATE')
        try:
            yield
        except BaseException:
            with contextlib.suppress(sqlite3.Error):
                self._connection.execute('ROLLBACK')
            raise
        self._connection.execute('COMMIT')

    def _fail(self, text: str):
        first = self.error is None
        self.error = text
        if first:
            self._on_error(text)

    def _meta(self, key: str) -> str | None:
        row = self._connection.execute('SELECT value FROM meta WHERE key = ?', (key,)).fetchone()
        return None if row is None else row[0]

    def _set_fingerprint(self, fingerprint: str):
        if fingerprint != self._fingerprint:
            self._connection.execute("INSERT OR REPLACE INTO meta VALUES ('fingerprint', ?)", (fingerprint,))
            self._fingerprint = fingerprint

    def _replace_foreign(self, written: dict):
        """The first write over another checkpoint's people removes them (once per
        transaction: ``written`` notes it)."""
        if self._foreign and not written.get('replaced'):
            for table in ('people', 'posteriors', 'scenes', *_RATING_TABLES):
                self._connection.execute(f'DELETE FROM {table}')
            written.update({key: None for key in self._written}, replaced=True)
            self._rated, self._fingerprint = {}, None

    def _held(self, written: dict, table: str, user_id: str) -> dict:
        """{rating id: scene digest} of what ``user_id`` holds in ``table`` in this transaction."""
        key = (table, user_id)
        if key not in written and key not in self._written:
            written[key] = dict(self._connection.execute(f'SELECT id, scene FROM {table} WHERE person = ?', (user_id,)))
        held = written[key] if key in written else self._written[key]
        return dict(held or {})

    def _write_person(self, update: PersonUpdate, written: dict):
        """The rows of ``update`` that differ from what is stored: ratings in and out, the
        person's row; ``written`` gets what the transaction leaves stored."""
        connection, user_id = self._connection, update.user_id
        self._set_fingerprint(update.fingerprint)
        changed = False
        for table, ratings in zip(_RATING_TABLES, (update.ratings, update.peer_ratings)):
            held = self._held(written, table, user_id)
            wanted = {r.rating_id: r for r in ratings}
            for rating_id in held.keys() - wanted.keys():
                connection.execute(f'DELETE FROM {table} WHERE person = ? AND id = ?', (user_id, rating_id))
                self._release_scene(held.pop(rating_id))
                changed = True
            for rating_id, rating in wanted.items():
                if rating_id in held:
                    continue
                digest, text = _scene_row(rating.scene)
                connection.execute('INSERT INTO scenes VALUES (?, ?, 1) ON CONFLICT(digest) DO UPDATE SET '
                                   'refs = refs + 1', (digest, text))
                self._counter += 1
                connection.execute(
                    f'INSERT INTO {table} VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)',
                    (user_id, rating_id, self._counter, int(rating.stamp), rating.origin, rating.action,
                     float(rating.score), rating.scene_id, digest,
                     None if rating.feedback is None else json.dumps(rating.feedback, separators=(',', ':'))))
                held[rating_id] = digest
                changed = True
            written[(table, user_id)] = held
            for rating in ratings if update.encoded else ():
                h = update.encoded.get(id(rating.scene))
                if h is not None:
                    connection.execute('INSERT OR IGNORE INTO encodings VALUES (?, ?, ?)',
                                       (held[rating.rating_id], update.fingerprint, _blob(h)))
        if changed or user_id not in self._rated:
            self._counter += 1
            self._rated[user_id] = self._counter
        model = update.model
        connection.execute(
            'INSERT OR REPLACE INTO people VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)',
            (user_id, update.fingerprint if model is not None else None,
             None if model is None else _blob(model.p), None if model is None else float(model.b),
             None if model is None else int(model.n_ratings), None if model is None else float(model.regularisation),
             int(bool(update.solved and model is not None)),
             int(update.dropped), len(written[('ratings', user_id)]), len(written[('peer_ratings', user_id)]),
             self._rated[user_id], time.time()))
        covariance = None if model is None else model.covariance
        if isinstance(covariance, np.ndarray):
            connection.execute('INSERT OR REPLACE INTO posteriors VALUES (?, ?)', (user_id, _blob(covariance)))
        elif covariance is None:
            connection.execute('DELETE FROM posteriors WHERE person = ?', (user_id,))
        # Deferred: the model restored as stored, whose covariance the row holds already

    def _forget(self, user_id: str, written: dict):
        for table in _RATING_TABLES:
            for digest in self._held(written, table, user_id).values():
                self._release_scene(digest)
            self._connection.execute(f'DELETE FROM {table} WHERE person = ?', (user_id,))
            written[(table, user_id)] = None
        self._connection.execute('DELETE FROM people WHERE person = ?', (user_id,))
        self._connection.execute('DELETE FROM posteriors WHERE person = ?', (user_id,))
        self._rated.pop(user_id, None)

    def _erase(self, user_id: str, written: dict) -> dict:
        """``_forget`` and the journal entries that name ``user_id``, and their tombstone;
        {what: rows removed}."""
        connection = self._connection
        removed = {table: connection.execute(f'SELECT COUNT(*) FROM {table} WHERE person = ?', (user_id,)).fetchone()[0]
                   for table in ('people', 'posteriors', *_RATING_TABLES)}
        self._forget(user_id, written)
        named = mentions(user_id)
        journal = [seq for seq, data in connection.execute('SELECT seq, data FROM feedback')
                   if named(data.encode('utf-8'))]
        connection.executemany('DELETE FROM feedback WHERE seq = ?', [(seq,) for seq in journal])
        removed['journal'] = len(journal)
        secret = folder_secret(self.folder, create=True)
        connection.execute('INSERT OR IGNORE INTO forgotten VALUES (?, ?)',
                           (Forgotten(secret).tag(user_id), time.time()))
        return removed

    def _erase_older(self, cutoff: int, written: dict) -> dict:
        """``erase_older``'s rows, in the transaction under way; {what: rows removed}."""
        connection, removed = self._connection, {}
        for table in _RATING_TABLES:
            rows = connection.execute(f'SELECT person, id FROM {table} WHERE stamp < ?', (cutoff,)).fetchall()
            by_person = {}
            for person, rating_id in rows:
                by_person.setdefault(person, []).append(rating_id)
            for person, ids in by_person.items():
                held = self._held(written, table, person)
                for rating_id in ids:
                    self._release_scene(held.pop(rating_id))
                    connection.execute(f'DELETE FROM {table} WHERE person = ? AND id = ?', (person, rating_id))
                written[(table, person)] = held
                connection.execute(f'UPDATE people SET {table} = ?, solved = 0 WHERE person = ?', (len(held), person))
            removed[table] = len(rows)
        gone = [person for (person,) in connection.execute(
            'SELECT person FROM people WHERE ratings = 0 AND peer_ratings = 0')]
        for person in gone:
            self._forget(person, written)
        removed['people'] = len(gone)
        removed['journal'] = connection.execute('DELETE FROM feedback WHERE log_time < ?', (cutoff,)).rowcount
        return removed

    def _finish_erasures(self, erased: list):
        """Rebuild the database and truncate the write-ahead log after the commit that erased
        people, then tell who waits what was removed. secure_delete zeroes the deleted rows,
        but an index's interior pages keep copies of keys as dividers, which can outlive the
        rows they came from (seen: an erased id left in state.db in one run of six):
        VACUUM writes every page again from what is left."""
        try:
            self._connection.execute('VACUUM')
            self._truncate_log()
        except sqlite3.Error as error:
            for done, _, _ in erased:
                done.set_exception(StoreError(f'{self.path}: erased, but the write-ahead log still holds old pages: '
                                              f'{error}; erasing again truncates it'))
            return
        for done, removed, _ in erased:
            done.set_result(removed)

    def _release_scene(self, digest: str):
        self._connection.execute('UPDATE scenes SET refs = refs - 1 WHERE digest = ?', (digest,))
        if self._connection.execute('DELETE FROM scenes WHERE digest = ? AND refs <= 0', (digest,)).rowcount:
            self._connection.execute('DELETE FROM encodings WHERE digest = ?', (digest,))


def write_people(folder, fingerprint: str, people: Iterable[PersonUpdate]) -> None:
    """Fill the store in ``folder`` with ``people`` in one transaction (benchmarks, tests)."""
    store = StateStore(folder, 'write_people', on_error=lambda text: None)
    try:
        if store.error is not None:
            raise OSError(store.error)
        with store._transaction():
            store._set_fingerprint(fingerprint)
            written = {}
            for update in people:
                store._write_person(update, written)
    finally:
        store.close()
