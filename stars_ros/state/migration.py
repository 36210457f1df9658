"""The files the node kept its state in before the state store (``store``), read once
to import them: ``user_models.json`` in the record folder and ``feedback.jsonl`` in each bag.
Both are left as they were; the store notes that it imported them, so it happens once.

``user_models.json`` was one JSON object::

    {"format": "stars_ros.user_models", "version": 1, "fingerprint": "<checkpoint digest>",
     "users": {"<user id>": {"p_u": [...], "b_u": ..., "n_ratings": ..., "regularisation": ...,
                             "ratings_dropped": <oldest ratings no longer kept>,
                             "ratings": [<foldin.Rating.to_json>], "peer_ratings": [...]}}}

``feedback.jsonl`` held one line of JSON per accepted feedback message,
``{"topic": ..., "log_time": <ns>, "data": <the message text>}``.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

from stars_ros.state.person import Rating, UserModel

STATE_FILE = 'user_models.json'
JOURNAL = 'feedback.jsonl'
FORMAT = 'stars_ros.user_models'


@dataclass(frozen=True)
class LegacyState:
    """A state file's users: ``models`` user -> UserModel, ``histories`` user -> (ratings,
    ratings dropped), ``peers`` user -> [Rating] that peers shared."""

    fingerprint: str
    models: dict
    histories: dict
    peers: dict


def _ratings(user_id: str, entries: list, kind: str) -> list:
    """Ratings of the file; one written before ratings had ids is named by a digest of the
    user, its place and its content, the same at every import."""
    def fallback(k, entry):
        text = json.dumps([user_id, kind, k, entry['scene'], entry['action'], entry['score']], sort_keys=True)
        return hashlib.blake2b(text.encode(), digest_size=16).hexdigest()
    return [Rating.from_json(entry, '' if entry.get('id') else fallback(k, entry)) for k, entry in enumerate(entries)]


def from_dict(state) -> LegacyState:
    """The users of a state file's content; ValueError, KeyError or TypeError when malformed."""
    if not isinstance(state, dict) or state.get('format') != FORMAT:
        raise ValueError(f'not a {FORMAT} file')
    users = state['users']
    models = {u: UserModel.from_json(v) for u, v in users.items()}
    histories = {u: (_ratings(u, v['ratings'], 'own'), int(v.get('ratings_dropped', 0))) for u, v in users.items()}
    peers = {u: _ratings(u, v['peer_ratings'], 'peer') for u, v in users.items() if v.get('peer_ratings')}
    return LegacyState(str(state['fingerprint']), models, histories, peers)


def read_state_file(path: Path) -> LegacyState:
    """The users of ``path``; ValueError naming the file when it cannot be read."""
    try:
        return from_dict(json.loads(Path(path).read_text()))
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as error:
        raise ValueError(f'cannot read {path}: {error}') from None


def read_journal(path: Path) -> list:
    """The entries of a journal file; a line cut by a hard kill was never acknowledged as
    journaled and is passed over."""
    entries = []
    for line in Path(path).read_text().splitlines():
        try:
            entry = json.loads(line)
        except ValueError:
            continue
        if isinstance(entry, dict) and {'topic', 'log_time', 'data'} <= set(entry):
            entries.append(entry)
    return entries
