"""The state store's database (``state.db``, schema in docs/state.md): its tables, the rows
of a person that a write holds (``PersonUpdate``) and a read gives (``Person``), and how
arrays and rated scenes are kept in them."""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from stars_ros.state.person import UserModel, scene_digest

DATABASE = 'state.db'
LOCK_FILE = 'state.lock'
SCHEMA_VERSION = 2  # 2: a person's covariance in its own table, read when first used (1: in people)
SCHEMA = """
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
RATING_TABLES = ('ratings', 'peer_ratings')


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


def blob(array) -> bytes | None:
    return None if array is None else np.ascontiguousarray(array, dtype='<f8').tobytes()


def array(blob, shape=None):
    if blob is None:
        return None
    array = np.frombuffer(blob, dtype='<f8').astype(np.float64)
    return array if shape is None else array.reshape(shape)


def scene_row(scene) -> tuple[str, str]:
    """(``scene_digest``, content text) of a rated scene; a scene graph is serialised once
    for both (its text is what ``scene_digest`` hashes)."""
    if not isinstance(scene, dict):  # a tabular row: short
        return scene_digest(scene), json.dumps([float(v) for v in scene], separators=(',', ':'))
    text = json.dumps(scene, sort_keys=True, separators=(',', ':'))
    return hashlib.blake2b(text.encode(), digest_size=16).hexdigest(), text
