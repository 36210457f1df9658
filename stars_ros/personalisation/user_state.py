"""The ranker's state file, ``user_models.json``: every folded-in user's model and rating
history, with the fingerprint of the checkpoint they were solved against, so a restart
with the same checkpoint carries on where the last run stopped.

ROS-free. One JSON object::

    {"format": "stars_ros.user_models", "version": 1, "fingerprint": "<checkpoint digest>",
     "users": {"<user id>": {"p_u": [...], "b_u": ..., "n_ratings": ..., "regularisation": ...,
                             "ratings_dropped": <oldest ratings no longer kept>,
                             "ratings": [<this node's ratings, foldin.Rating.to_json>],
                             "peer_ratings": [<ratings peers shared (fleet sharing)>]}}}

``save`` writes it atomically (a temporary file, fsync'd, renamed over the old one);
``StateWriter`` does so from a thread of its own, at most once per interval, so an fsync
never holds up serving and a hard kill loses at most one interval.
"""
from __future__ import annotations

import hashlib
import json
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Mapping

from stars_ros import messages
from stars_ros.errors import StarsError
from stars_ros.files import atomic_write
from stars_ros.personalisation.foldin import Rating, UserModel

STATE_FILE = 'user_models.json'
FORMAT = 'stars_ros.user_models'
VERSION = 1


class UserStateError(StarsError):
    """The state file cannot be read, or holds users solved against another checkpoint."""


@dataclass(frozen=True)
class UserState:
    """Folded-in users: ``models`` user -> foldin.UserModel, ``histories`` user -> (ratings,
    ratings dropped), as ``histories.FeedbackHistories.snapshot`` gives them, and ``peers``
    user -> [Rating] that peers shared (``fleet``)."""

    fingerprint: str
    models: dict
    histories: dict
    peers: dict


def to_dict(fingerprint: str, models: Mapping, histories: Mapping, peers: Mapping | None = None) -> dict:
    """The file's content for the users of ``models``, with their histories."""
    users = {}
    for user_id, model in models.items():
        ratings, dropped = histories.get(user_id, ((), 0))
        users[user_id] = {**model.to_json(), 'ratings_dropped': int(dropped),
                          'ratings': [r.to_json() for r in ratings],
                          'peer_ratings': [r.to_json() for r in (peers or {}).get(user_id, ())]}
    return {'format': FORMAT, 'version': VERSION, 'fingerprint': fingerprint, 'users': users}


def _ratings(user_id: str, entries: list, kind: str) -> list:
    """Ratings of the file; one written before ratings had ids is named by a digest of the
    user, its place and its content, the same at every load."""
    def fallback(k, entry):
        text = json.dumps([user_id, kind, k, entry['scene'], entry['action'], entry['score']], sort_keys=True)
        return hashlib.blake2b(text.encode(), digest_size=16).hexdigest()
    return [Rating.from_json(entry, fallback(k, entry)) for k, entry in enumerate(entries)]


def from_dict(state) -> UserState:
    """The users of a file's content; ValueError, KeyError or TypeError when it is malformed."""
    if not isinstance(state, dict) or state.get('format') != FORMAT:
        raise ValueError(f'not a {FORMAT} file')
    users = state['users']
    models = {u: UserModel.from_json(v) for u, v in users.items()}
    histories = {u: (_ratings(u, v['ratings'], 'own'), int(v.get('ratings_dropped', 0))) for u, v in users.items()}
    peers = {u: _ratings(u, v['peer_ratings'], 'peer') for u, v in users.items() if v.get('peer_ratings')}
    return UserState(str(state['fingerprint']), models, histories, peers)


def save(path: Path, state: dict) -> None:
    """Write ``state`` (``to_dict``) to ``path`` atomically; OSError when the disk refuses."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = messages.dumps(state).encode()
    atomic_write(path, lambda handle: handle.write(text))


def load(path: Path, fingerprint: str) -> UserState | None:
    """The users in ``path`` if they were solved against the checkpoint ``fingerprint``;
    None when there is no file. UserStateError, saying that no user is restored, when the
    file cannot be read or belongs to another checkpoint."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        state = from_dict(json.loads(path.read_text()))
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as error:
        raise UserStateError(f'cannot read {path}: {error}; folded-in users are not restored') from None
    if state.fingerprint != fingerprint:
        raise UserStateError(f'{path} was solved against checkpoint {state.fingerprint[:12]}, not the served '
                             f'{fingerprint[:12]}: folded-in users are not restored')
    return state


class StateWriter:
    """Saves ``state()`` to ``path`` from a thread of its own when ``request`` is called, at
    most once per ``interval`` seconds: a stream of feedback costs one write per interval,
    not one per rating. A failed write goes to ``on_error(text)``; ``close`` writes what is
    still wanted before it returns."""

    def __init__(self, path: Path, state: Callable[[], dict], interval: float, on_error: Callable[[str], None]):
        self.path, self._state, self._interval, self._on_error = Path(path), state, interval, on_error
        self._wanted = threading.Event()
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._loop, name='stars-ranker-state', daemon=True)
        self._thread.start()

    def request(self) -> None:
        self._wanted.set()

    def write(self) -> None:
        try:
            save(self.path, self._state())
        except OSError as error:
            self._on_error(f'could not write {self.path}: {error}')

    def close(self) -> None:
        wanted = self._wanted.is_set()
        self._closing.set()
        self._wanted.set()
        self._thread.join(timeout=10)
        if wanted:  # the last updates are on disk before the process ends
            self.write()

    def _loop(self):
        while True:
            self._wanted.wait()
            if self._closing.is_set():
                return
            self._wanted.clear()
            self.write()
            self._closing.wait(self._interval)
