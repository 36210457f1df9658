"""Reading a state store without holding it (``StoreReader``, ``open_reader``): the
inspection command, ``refit``, recovery and tests read a store, also while a node writes it
(what the node had committed when each query ran); the node's store reads its restored
people's ratings and encodings through one."""
from __future__ import annotations

import functools
import json
import sqlite3
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from stars_ros.errors import StoreError
from stars_ros.state.forgotten import Forgotten, folder_secret
from stars_ros.state.person import Deferred, Rating, UserModel
from stars_ros.state.schema import DATABASE, RATING_TABLES, SCHEMA_VERSION, Person, array

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
            raise StoreError(f'cannot read the state store {self.path}: {error}; check that it is a '
                             'stars_ros state.db, readable, and not damaged (a copy of the record folder can '
                             'be inspected with python -m stars_ros.recording state FOLDER)') from None
    return read


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
        connection = sqlite3.connect(f'file:{self.path}?mode=ro', uri=True, timeout=30,
                                     check_same_thread=False)
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
            'SELECT person, fingerprint, p IS NOT NULL, n_ratings, solved, dropped, ratings, peer_ratings, '
            'updated FROM people ORDER BY rated')
        return [{'person': person, 'ratings': ratings, 'peer_ratings': peer_ratings, 'dropped': dropped,
                 'model': bool(has_model), 'solved': bool(solved), 'n_ratings': n_ratings,
                 'fingerprint': fingerprint, 'updated': updated}
                for (person, fingerprint, has_model, n_ratings, solved, dropped, ratings, peer_ratings,
                     updated) in rows]

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
                p = array(p)
                covariance = None
                if person in posterior:
                    read = functools.partial(self.covariance, person, len(p) + 1)
                    covariance = Deferred(_ReadOnce(read)) if deferred else read()
                model = UserModel(p, b, n_ratings, regularisation, covariance)
            held = [(Deferred(functools.partial(self.ratings, person, table)) if deferred else
                     self.ratings(person, table)) if count else []
                    for table, count in zip(RATING_TABLES, (own, peer))]
            people.append(Person(person, model, fingerprint, held[0], dropped, held[1], bool(solved),
                                 updated))
        return people

    @_reading
    def ratings(self, person: str, table: str = 'ratings') -> list:
        """``person``'s ratings (``table`` 'peer_ratings': their peers'), oldest first."""
        rows = self._connection.execute(
            f'SELECT r.id, r.stamp, r.origin, r.action, r.score, r.scene_id, r.scene, r.feedback, s.content '
            f'FROM {table} r JOIN scenes s ON s.digest = r.scene WHERE r.person = ? ORDER BY r.position',
            (person,))
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
                    f'SELECT digest, h FROM encodings WHERE fingerprint = ? AND digest IN ({marks})',
                    (fingerprint, *chunk)):
                found[digests[digest]] = array(h)
        return found

    @_reading
    def covariance(self, person: str, size: int) -> np.ndarray | None:
        """``person``'s stored covariance [size, size] (None: none stored)."""
        row = self._connection.execute(f'SELECT covariance FROM {self._posteriors} WHERE person = ?',
                                       (person,)).fetchone()
        return None if row is None else array(row[0], (size, size))

    @_reading
    def signed_feedback(self) -> list:
        """The signed feedback messages of every person's own ratings (replays stay refused)."""
        return [json.loads(text) for (text,) in
                self._connection.execute('SELECT feedback FROM ratings WHERE feedback IS NOT NULL')]

    @_reading
    def forgotten_tags(self) -> set:
        """The tombstones of the people forgotten here (``state.forgotten``)."""
        table = self._connection.execute("SELECT 1 FROM sqlite_master WHERE name = 'forgotten'").fetchone()
        if table is None:
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
