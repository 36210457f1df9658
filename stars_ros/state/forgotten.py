"""Forgotten people: how a person's id is recognised in stored bytes, and the tombstone that
keeps them forgotten without holding their id.

A tombstone is HMAC-SHA256(the record folder's secret, the id): the folder can tell whether
an id it meets (a refit's bag, a peer's model, new feedback) was forgotten, and a copy of
the tombstones alone names nobody. The secret (``forget.key``, 32 random bytes, mode 0600)
is the folder's own: whoever holds both the key and a guess of an id can test the guess,
so the key stays with the folder and is never shared with peers (each peer keeps its own
tombstones).

A peer's forget (``fleet_tag``) names the person by a tag a fleet peer can compute too:
HMAC-SHA256 under the fleet's feedback key (SHA-256 without keys) of a random salt and the
id. A peer keeps it as a fleet tombstone (``fleet:KEY_ID:SALT:TAG`` beside the folder's
tags), so a person it never met is refused too once a peer forgot them. ROS-free, standard
library only.
"""
from __future__ import annotations

import hashlib
import hmac
import json
import os
import re
from pathlib import Path
from typing import Callable, Iterable

SECRET_FILE = 'forget.key'
SECRET_BYTES = 32
_ID_CHARACTER = rb'[A-Za-z0-9_-]'
FLEET_PREFIX = 'fleet:'
_FLEET_DOMAIN = b'stars_ros/forget_person\0'  # a fleet tag is never a feedback MAC


def folder_secret(folder, create: bool = False) -> bytes | None:
    """The record folder's tombstone secret; made now when ``create`` and it has none
    (None: it has none)."""
    path = Path(folder).expanduser() / SECRET_FILE
    try:
        return bytes.fromhex(path.read_text().strip())
    except FileNotFoundError:
        if not create:
            return None
    path.parent.mkdir(parents=True, exist_ok=True)
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(descriptor, 'w') as handle:
        handle.write(os.urandom(SECRET_BYTES).hex() + '\n')
        handle.flush()
        os.fsync(handle.fileno())
    return folder_secret(folder)


def tombstone(secret: bytes, user_id: str) -> str:
    """The tag that marks ``user_id`` forgotten under ``secret`` (hex)."""
    return hmac.new(secret, user_id.encode('utf-8'), hashlib.sha256).hexdigest()


def fleet_tag(key: bytes | None, salt: bytes, user_id: str) -> str:
    """The tag a fleet forget names ``user_id`` by (hex): HMAC-SHA256(``key``, salt, id)
    under a feedback key, SHA-256(salt, id) without one."""
    data = _FLEET_DOMAIN + salt + user_id.encode('utf-8')
    return (hmac.new(key, data, hashlib.sha256) if key is not None else hashlib.sha256(data)).hexdigest()


def fleet_tombstone(key_id: str, salt: str, tag: str) -> str:
    """How a fleet forget's tag is kept among a folder's tombstones ('' key id: unsigned)."""
    return f'{FLEET_PREFIX}{key_id}:{salt}:{tag}'


class Forgotten:
    """The tombstones of one record folder: ``user_id in forgotten`` says whether they were
    forgotten there, or by a fleet peer (``fleet_keys``: key id -> secret, to check the fleet
    tombstones signed under them; one of a key no longer held is not checked); ``add`` marks
    one more (the caller stores the tag it returns)."""

    def __init__(self, secret: bytes | None, tags: Iterable[str] = (), fleet_keys: dict | None = None):
        self.secret, self.tags, self.fleet_keys = secret, set(tags), dict(fleet_keys or {})

    def __contains__(self, user_id) -> bool:
        if not self.tags:
            return False
        if self.secret is not None and tombstone(self.secret, str(user_id)) in self.tags:
            return True
        return any(self._fleet_match(tag, str(user_id)) for tag in self.tags if tag.startswith(FLEET_PREFIX))

    def _fleet_match(self, kept: str, user_id: str) -> bool:
        key_id, salt, tag = kept[len(FLEET_PREFIX):].split(':')
        key = self.fleet_keys.get(key_id) if key_id else None
        if key_id and key is None:
            return False
        return hmac.compare_digest(fleet_tag(key, bytes.fromhex(salt), user_id), tag)

    def __len__(self) -> int:
        return len(self.tags)

    def tag(self, user_id: str) -> str:
        if self.secret is None:
            raise ValueError('no tombstone secret: the record folder has not forgotten anyone yet')
        return tombstone(self.secret, user_id)

    def add(self, user_id: str) -> str:
        tag = self.tag(user_id)
        self.tags.add(tag)
        return tag


def id_forms(user_id: str) -> list:
    """The byte strings ``user_id`` is stored as: UTF-8 (also inside a CDR string) and
    JSON-escaped (``\\u`` escapes, as ``json.dumps`` writes non-ASCII and control
    characters)."""
    plain = user_id.encode('utf-8')
    escaped = json.dumps(user_id)[1:-1].encode('ascii')
    return list(dict.fromkeys((plain, escaped)))


def mentions(user_id: str) -> Callable[[bytes], bool]:
    """``mentions(data)``: True when ``data`` (a message's bytes, a journal entry) holds
    ``user_id`` in any of its ``id_forms``, as a whole id: not inside a longer one
    (``p2`` is not found in ``p21``), so other people's records stay as they are."""
    if not user_id:
        raise ValueError('an empty user id names nobody')
    pattern = re.compile(b'|'.join(rb'(?<!' + _ID_CHARACTER + rb')' + re.escape(form) + rb'(?!' + _ID_CHARACTER + rb')'
                                   for form in id_forms(user_id)))
    return lambda data: pattern.search(data) is not None
