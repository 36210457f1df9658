"""The rows a state store's writer changes, one transaction at a time (``Rows``): a
person's row, the ratings that joined or left them, a scene the first time its content is
rated (kept once, by content digest, with a count of the ratings that name them), the
removal of a person, their erase with the journal entries that name them and their
tombstone, retention's erase of what is older, and the VACUUM and write-ahead log
truncation after an erase. Only ``store.StateStore``'s writer thread calls it."""
from __future__ import annotations

import contextlib
import json
import sqlite3
import time

import numpy as np

from stars_ros.state.forgotten import Forgotten, folder_secret, mentions
from stars_ros.state.schema import RATING_TABLES, PersonUpdate, blob, scene_row


class Rows:
    """The rows of the store in ``folder`` through ``connection`` (``attach``), and what the
    writer knows of them: ``committed`` (table, person) -> {rating id: scene digest} of those
    written, ``rated`` person -> order of their last rating change, ``counter`` (positions and
    rating orders, increasing), ``foreign`` (the rows belong to another checkpoint: replaced on
    the first write) and ``fingerprint`` (the checkpoint the rows belong to, as meta holds it).
    A transaction's changes to ``committed`` go in a ``written`` dict, kept once it commits."""

    def __init__(self, folder):
        self.folder = folder
        self.connection = None
        self.committed, self.rated, self.counter = {}, {}, 0
        self.foreign, self.fingerprint = False, None

    def attach(self, connection: sqlite3.Connection) -> None:
        """Write through ``connection`` from now on, continuing the orders it holds (what each
        person holds is read when first written)."""
        self.connection = connection
        self.counter = max([connection.execute(f'SELECT COALESCE(MAX(position), 0) FROM {t}').fetchone()[0]
                            for t in RATING_TABLES] +
                           [connection.execute('SELECT COALESCE(MAX(rated), 0) FROM people').fetchone()[0]])
        self.rated = dict(connection.execute('SELECT person, rated FROM people'))
        self.fingerprint = self.meta('fingerprint')

    @contextlib.contextmanager
    def transaction(self):
        self.connection.execute('BEGIN IMMEDIATE')
        try:
            yield
        except BaseException:
            with contextlib.suppress(sqlite3.Error):
                self.connection.execute('ROLLBACK')
            raise
        self.connection.execute('COMMIT')

    def keep(self, written: dict) -> None:
        """A transaction that changed ``written`` committed."""
        if written.pop('replaced', False):
            self.foreign = False
        self.committed.update(written)
        for key in [k for k, v in self.committed.items() if v is None]:
            del self.committed[key]

    def vacuum(self) -> None:
        """Write every page again from what is left, then empty the write-ahead log."""
        self.connection.execute('VACUUM')
        self.truncate_log()

    def truncate_log(self):
        """Checkpoint the write-ahead log into the database and truncate it to nothing, so
        no page of it keeps what a commit deleted; retried while a reader holds it."""
        for _ in range(200):
            busy, _, _ = self.connection.execute('PRAGMA wal_checkpoint(TRUNCATE)').fetchone()
            if not busy:
                return
            time.sleep(0.05)
        raise sqlite3.OperationalError('the write-ahead log stays in use by a reader: not truncated')

    def meta(self, key: str) -> str | None:
        row = self.connection.execute('SELECT value FROM meta WHERE key = ?', (key,)).fetchone()
        return None if row is None else row[0]

    def set_fingerprint(self, fingerprint: str):
        if fingerprint != self.fingerprint:
            self.connection.execute("INSERT OR REPLACE INTO meta VALUES ('fingerprint', ?)", (fingerprint,))
            self.fingerprint = fingerprint

    def replace_foreign(self, written: dict):
        """The first write over another checkpoint's people removes them (once per
        transaction: ``written`` notes it)."""
        if self.foreign and not written.get('replaced'):
            for table in ('people', 'posteriors', 'scenes', *RATING_TABLES):
                self.connection.execute(f'DELETE FROM {table}')
            written.update({key: None for key in self.committed}, replaced=True)
            self.rated, self.fingerprint = {}, None

    def _held(self, written: dict, table: str, user_id: str) -> dict:
        """{rating id: scene digest} of what ``user_id`` holds in ``table`` in this transaction."""
        key = (table, user_id)
        if key not in written and key not in self.committed:
            written[key] = dict(self.connection.execute(f'SELECT id, scene FROM {table} WHERE person = ?',
                                                        (user_id,)))
        held = written[key] if key in written else self.committed[key]
        return dict(held or {})

    def write(self, update: PersonUpdate, written: dict):
        """The rows of ``update`` that differ from what is stored: ratings in and out, the
        person's row; ``written`` gets what the transaction leaves stored."""
        connection, user_id = self.connection, update.user_id
        self.set_fingerprint(update.fingerprint)
        changed = False
        for table, ratings in zip(RATING_TABLES, (update.ratings, update.peer_ratings)):
            held = self._held(written, table, user_id)
            wanted = {r.rating_id: r for r in ratings}
            for rating_id in held.keys() - wanted.keys():
                connection.execute(f'DELETE FROM {table} WHERE person = ? AND id = ?', (user_id, rating_id))
                self._release_scene(held.pop(rating_id))
                changed = True
            for rating_id, rating in wanted.items():
                if rating_id in held:
                    continue
                digest, text = scene_row(rating.scene)
                connection.execute('INSERT INTO scenes VALUES (?, ?, 1) ON CONFLICT(digest) DO UPDATE SET '
                                   'refs = refs + 1', (digest, text))
                self.counter += 1
                connection.execute(
                    f'INSERT INTO {table} VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)',
                    (user_id, rating_id, self.counter, int(rating.stamp), rating.origin, rating.action,
                     float(rating.score), rating.scene_id, digest,
                     None if rating.feedback is None else json.dumps(rating.feedback, separators=(',', ':'))))
                held[rating_id] = digest
                changed = True
            written[(table, user_id)] = held
            for rating in ratings if update.encoded else ():
                h = update.encoded.get(id(rating.scene))
                if h is not None:
                    connection.execute('INSERT OR IGNORE INTO encodings VALUES (?, ?, ?)',
                                       (held[rating.rating_id], update.fingerprint, blob(h)))
        if changed or user_id not in self.rated:
            self.counter += 1
            self.rated[user_id] = self.counter
        model = update.model
        connection.execute(
            'INSERT OR REPLACE INTO people VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)',
            (user_id, update.fingerprint if model is not None else None,
             None if model is None else blob(model.p), None if model is None else float(model.b),
             None if model is None else int(model.n_ratings),
             None if model is None else float(model.regularisation),
             int(bool(update.solved and model is not None)),
             int(update.dropped), len(written[('ratings', user_id)]), len(written[('peer_ratings', user_id)]),
             self.rated[user_id], time.time()))
        covariance = None if model is None else model.covariance
        if isinstance(covariance, np.ndarray):
            connection.execute('INSERT OR REPLACE INTO posteriors VALUES (?, ?)', (user_id, blob(covariance)))
        elif covariance is None:
            connection.execute('DELETE FROM posteriors WHERE person = ?', (user_id,))
        # Deferred: the model restored as stored, whose covariance the row holds already

    def remove(self, user_id: str, written: dict):
        for table in RATING_TABLES:
            for digest in self._held(written, table, user_id).values():
                self._release_scene(digest)
            self.connection.execute(f'DELETE FROM {table} WHERE person = ?', (user_id,))
            written[(table, user_id)] = None
        self.connection.execute('DELETE FROM people WHERE person = ?', (user_id,))
        self.connection.execute('DELETE FROM posteriors WHERE person = ?', (user_id,))
        self.rated.pop(user_id, None)

    def erase(self, user_id: str, written: dict) -> dict:
        """``remove`` and the journal entries that name ``user_id``, and their tombstone;
        {what: rows removed}."""
        connection = self.connection
        removed = {table: connection.execute(f'SELECT COUNT(*) FROM {table} WHERE person = ?',
                                             (user_id,)).fetchone()[0]
                   for table in ('people', 'posteriors', *RATING_TABLES)}
        self.remove(user_id, written)
        named = mentions(user_id)
        journal = [seq for seq, data in connection.execute('SELECT seq, data FROM feedback')
                   if named(data.encode('utf-8'))]
        connection.executemany('DELETE FROM feedback WHERE seq = ?', [(seq,) for seq in journal])
        removed['journal'] = len(journal)
        secret = folder_secret(self.folder, create=True)
        connection.execute('INSERT OR IGNORE INTO forgotten VALUES (?, ?)',
                           (Forgotten(secret).tag(user_id), time.time()))
        return removed

    def erase_older(self, cutoff: int, written: dict) -> dict:
        """``StateStore.erase_older``'s rows, in the transaction under way; {what: rows removed}."""
        connection, removed = self.connection, {}
        for table in RATING_TABLES:
            rows = connection.execute(f'SELECT person, id FROM {table} WHERE stamp < ?', (cutoff,)).fetchall()
            by_person = {}
            for person, rating_id in rows:
                by_person.setdefault(person, []).append(rating_id)
            for person, ids in by_person.items():
                held = self._held(written, table, person)
                for rating_id in ids:
                    self._release_scene(held.pop(rating_id))
                    connection.execute(f'DELETE FROM {table} WHERE person = ? AND id = ?',
                                       (person, rating_id))
                written[(table, person)] = held
                connection.execute(f'UPDATE people SET {table} = ?, solved = 0 WHERE person = ?',
                                   (len(held), person))
            removed[table] = len(rows)
        gone = [person for (person,) in connection.execute(
            'SELECT person FROM people WHERE ratings = 0 AND peer_ratings = 0')]
        for person in gone:
            self.remove(person, written)
        removed['people'] = len(gone)
        removed['journal'] = connection.execute('DELETE FROM feedback WHERE log_time < ?', (cutoff,)).rowcount
        return removed

    def _release_scene(self, digest: str):
        self.connection.execute('UPDATE scenes SET refs = refs - 1 WHERE digest = ?', (digest,))
        if self.connection.execute('DELETE FROM scenes WHERE digest = ? AND refs <= 0', (digest,)).rowcount:
            self.connection.execute('DELETE FROM encodings WHERE digest = ?', (digest,))
