"""What earlier versions left in a record folder, taken over when a store opens: a database of
schema version 1 upgraded, the free pages of a store written without ``secure_delete``
cleared once, and ``user_models.json`` and every bag's ``feedback.jsonl`` imported once each
(``migration`` reads those files)."""
from __future__ import annotations

import contextlib
import gc
import time
from pathlib import Path
from typing import Callable

from stars_ros.state import migration
from stars_ros.state.rows import Rows
from stars_ros.state.schema import SCHEMA_VERSION, PersonUpdate


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


def upgrade_from_version_1(connection, path: Path, on_progress: Callable[[str], None]) -> None:
    """Move the covariances out of ``people`` into ``posteriors`` (schema version 2)."""
    on_progress(f'upgrading {path} from schema version 1 to 2 (covariances in a table of their own)')
    connection.execute('BEGIN IMMEDIATE')
    try:
        connection.execute('INSERT INTO posteriors SELECT person, covariance FROM people '
                           'WHERE covariance IS NOT NULL')
        connection.execute('ALTER TABLE people DROP COLUMN covariance')
        connection.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'", (str(SCHEMA_VERSION),))
    except BaseException:
        connection.execute('ROLLBACK')
        raise
    connection.execute('COMMIT')


def clear_free_pages(rows: Rows, fresh: bool) -> None:
    """Once per store: VACUUM what earlier versions deleted without ``secure_delete``
    (their free pages and cells may still hold it), then empty the write-ahead log; a
    store made now has nothing to clear."""
    if rows.meta('secure_delete') is not None:
        return
    if fresh:
        rows.connection.execute("INSERT INTO meta VALUES ('secure_delete', ?)", (str(time.time()),))
        return
    rows.connection.execute('VACUUM')
    rows.connection.execute("INSERT INTO meta VALUES ('secure_delete', ?)", (str(time.time()),))
    rows.truncate_log()


def import_earlier_files(rows: Rows, folder: Path, on_progress: Callable[[str], None]) -> tuple[list, list]:
    """user_models.json and every bag's feedback.jsonl, once each (noted in meta): (what
    was imported, the problems that kept something out)."""
    connection, imported, problems = rows.connection, [], []
    meta = dict(connection.execute('SELECT key, value FROM meta'))
    state_file = folder / migration.STATE_FILE
    key = f'imported:{migration.STATE_FILE}'
    if state_file.exists() and key not in meta:
        on_progress(f'importing {state_file} ({state_file.stat().st_size / 1e6:.0f} MB, kept by an earlier '
                    'version) into the state store, once: the node serves when it is in')
        with _collector_paused():
            try:
                state = migration.read_state_file(state_file)
            except ValueError as error:
                problems.append(f'{error}: its folded-in users are not imported')
                state = None
            with rows.transaction():
                if state is not None:
                    _import_state(rows, state, state_file, problems, on_progress)
                connection.execute('INSERT INTO meta VALUES (?, ?)', (key, str(time.time())))
        if state is not None:
            imported.append(f'{len(state.models)} people from {state_file}')
    for journal in sorted(folder.glob(f'*/{migration.JOURNAL}')):
        key = f'imported:{journal.parent.name}/{migration.JOURNAL}'
        if key in meta:
            continue
        entries = migration.read_journal(journal)
        with rows.transaction():
            connection.executemany(
                'INSERT INTO feedback (bag, topic, log_time, data, committed) VALUES (?, ?, ?, ?, ?)',
                [(journal.parent.name, e['topic'], int(e['log_time']), e['data'], time.time())
                 for e in entries])
            connection.execute('INSERT INTO meta VALUES (?, ?)', (key, str(time.time())))
        imported.append(f'{len(entries)} feedback messages from {journal}')
    return imported, problems


def _import_state(rows: Rows, state: migration.LegacyState, state_file: Path, problems: list,
                  on_progress: Callable[[str], None]) -> None:
    if rows.connection.execute('SELECT COUNT(*) FROM people').fetchone()[0] == 0:
        rows.set_fingerprint(state.fingerprint)
    elif rows.meta('fingerprint') != state.fingerprint:
        problems.append(f'{state_file} holds people of checkpoint {state.fingerprint[:12]}, the store '
                        'those of another: not imported')
        return
    written = {}
    people = sorted(state.models.keys() | state.histories.keys() | state.peers.keys())
    step = max(1, len(people) // 10)
    for done, user_id in enumerate(people, 1):
        ratings, dropped = state.histories.get(user_id, ([], 0))
        rows.write(PersonUpdate(user_id, state.models.get(user_id), state.fingerprint, ratings, dropped,
                                state.peers.get(user_id, []), False), written)
        if done % step == 0 or done == len(people):
            on_progress(f'imported {done} of {len(people)} people from {state_file}')
    rows.committed.update(written)
