"""Signed feedback: the key file, the form a feedback message is signed in, and its checks.

Anyone who reaches the ROS domain can publish on stars/feedback, and a rating steers what
the robot does for the person it names (with fleet sharing, on every robot). With the
ranker's ``feedback_key_file`` set, a message counts only when a holder of one of its keys
signed it: ``"auth": {"key_id", "stamp", "mac"}`` where ``mac`` is HMAC-SHA256(secret,
``canonical(fields, stamp)``), ``stamp`` the signing time (ROS time, ns). The node refuses
(kind ``auth``) a message without a valid ``auth``, of an unknown key, with a wrong MAC,
stamped further than ``feedback_max_age`` in the past or the future, or whose MAC it already
took within that window. A folded-in rating keeps its signed message, and its id is the
MAC, so peers check each shared rating too and one signature can make one rating only.
docs/security.md says what this guarantees and what it does not.

ROS-free and standard library only, so a client (``stars_ros.sign_feedback``) can sign
without the rest of the package.
"""
from __future__ import annotations

import hashlib
import heapq
import hmac
import json
import os
import re
import stat
from pathlib import Path
from typing import Callable, Mapping, Sequence

from stars_ros.errors import ConfigError
from stars_ros.state.person import check_score

KEY_ID = re.compile(r'[A-Za-z0-9._-]{1,64}')
MAC = re.compile(r'[0-9a-f]{64}')
MIN_SECRET_BYTES = 16  # 128 bits: shorter secrets can be guessed offline from one signed message
AUTH_FIELDS = frozenset(('key_id', 'stamp', 'mac'))
MAX_STAMP = 2 ** 63 - 1  # ROS time in ns is an int64


def load_keys(path) -> dict[str, bytes]:
    """The keys of a key file: one ``KEY_ID:HEX_SECRET`` a line (blank lines and lines
    starting with ``#`` aside), several at once while keys rotate. ConfigError names the
    line of a malformed one, never its secret."""
    path = Path(path).expanduser()
    try:
        lines = path.read_text(encoding='utf-8').splitlines()
    except (OSError, UnicodeDecodeError) as error:
        raise ConfigError(f'feedback key file {path} cannot be read: {error}') from None
    keys = {}
    for number, line in enumerate(lines, 1):
        line = line.strip()
        if not line or line.startswith('#'):
            continue
        key_id, colon, secret = line.partition(':')
        where = f'feedback key file {path}, line {number}'
        if not colon or not KEY_ID.fullmatch(key_id):
            raise ConfigError(f'{where}: expected KEY_ID:HEX_SECRET with a key id of 1 to 64 letters, digits, '
                              "'.', '_' or '-'")
        try:
            secret_bytes = bytes.fromhex(secret)
        except ValueError:
            raise ConfigError(f"{where}: the secret of key '{key_id}' is not hexadecimal") from None
        if len(secret_bytes) < MIN_SECRET_BYTES:
            raise ConfigError(f"{where}: the secret of key '{key_id}' has {len(secret_bytes)} bytes, fewer than "
                              f'{MIN_SECRET_BYTES}')
        if key_id in keys:
            raise ConfigError(f"{where}: key id '{key_id}' is given twice")
        keys[key_id] = secret_bytes
    if not keys:
        raise ConfigError(f'feedback key file {path} holds no key')
    return keys


def readable_by_others(path) -> bool:
    """True when the key file's mode lets its group or others read it."""
    return bool(os.stat(Path(path).expanduser()).st_mode & (stat.S_IRGRP | stat.S_IROTH))


def canonical(fields: Mapping, stamp: int) -> bytes:
    """The bytes a MAC covers: the message's own fields (``auth`` left out) and ``stamp``,
    as ``json.dumps`` writes them with sorted keys and no blanks (ASCII, ``\\u`` escapes)."""
    signed = {key: value for key, value in fields.items() if key != 'auth'}
    signed['stamp'] = stamp
    return json.dumps(signed, sort_keys=True, separators=(',', ':')).encode('utf-8')


def mac(secret: bytes, fields: Mapping, stamp: int) -> str:
    return hmac.new(secret, canonical(fields, stamp), hashlib.sha256).hexdigest()


def sign(fields: Mapping, key_id: str, secret: bytes, stamp: int, scale: Sequence[float] | None = None) -> dict:
    """The feedback ``fields`` with the ``auth`` that key ``key_id`` gives them at ``stamp``
    (ROS time, ns): the payload to publish on stars/feedback. With the checkpoint's rating
    ``scale`` (low, high), a score outside it is not signed: OutOfScaleError."""
    if scale is not None and 'score' in fields:
        check_score(float(fields['score']), scale, 'feedback score')
    unsigned = {key: value for key, value in fields.items() if key != 'auth'}
    return {**unsigned, 'auth': {'key_id': key_id, 'stamp': int(stamp), 'mac': mac(secret, unsigned, stamp)}}


def from_key_file(path, max_age: Callable[[], float], logger) -> FeedbackAuthenticator | None:
    """The ranker's checks of signed feedback with the keys of ``path`` (None without one:
    ``logger`` warns that feedback is not authenticated). A key file that cannot be read
    raises ConfigError: the node does not start unprotected."""
    if not path:
        logger.warning('feedback_key_file is empty: feedback is not authenticated, anyone who reaches the '
                       'ROS domain can rate for any person (docs/security.md)')
        return None
    keys = load_keys(path)
    if readable_by_others(path):
        logger.warning(f'feedback key file {path} is readable by its group or others: chmod 600 it')
    logger.info(f'feedback is taken only when signed by a key of {path} ({", ".join(keys)})')
    return FeedbackAuthenticator(keys, max_age)


class FeedbackAuthenticator:
    """The ranker's checks of signed feedback and of the signed ratings peers share.

    Args:
        keys (Mapping): key id -> secret (``load_keys``).
        max_age (callable): ``feedback_max_age`` in seconds, read at each check (the
            parameter can change while the node runs).
    """

    def __init__(self, keys: Mapping[str, bytes], max_age: Callable[[], float]):
        self.keys, self._max_age = dict(keys), max_age
        self._taken = {}  # MAC -> (stamp, user id) of each feedback taken within the window
        self._by_stamp = []  # heap of (stamp, MAC), to let the oldest go
        self._forgotten_before = 0  # MACs of stamps before this (ns) are let go: such stamps are refused

    def check(self, payload: Mapping | None, now: int) -> str | None:
        """Why the stars/feedback message ``payload`` (as parsed) is refused at ``now`` (ROS
        time, ns), or None: it is taken, and its MAC is not taken again within the window."""
        auth, refusal = self._verify(payload)
        if refusal is not None:
            return refusal
        window = self._window()
        stamp, code = auth['stamp'], auth['mac']
        if now - stamp > window:
            return f'signed {(now - stamp) / 1e9:.3f} s ago, longer than feedback_max_age = {window / 1e9:g} s'
        if stamp - now > window:
            return f'stamped {(stamp - now) / 1e9:.3f} s in the future, more than feedback_max_age = {window / 1e9:g} s'
        horizon = now - window
        while self._by_stamp and self._by_stamp[0][0] < horizon:
            self._taken.pop(heapq.heappop(self._by_stamp)[1], None)
        self._forgotten_before = max(self._forgotten_before, horizon)
        if stamp < self._forgotten_before:
            return ('signed before the oldest MAC this node still remembers (feedback_max_age was widened since): '
                    'taken only when signed again')
        if code in self._taken:
            return f"a replay: a message with this MAC (key '{auth['key_id']}') was already taken"
        self._taken[code] = (stamp, payload.get('user_id'))
        heapq.heappush(self._by_stamp, (stamp, code))
        return None

    def remember(self, signed_messages) -> None:
        """Count the MACs of feedback taken before (the state store's ratings after a restart)
        as taken, so replaying it within the window is refused."""
        for message in signed_messages:
            auth = message.get('auth') if isinstance(message, Mapping) else None
            if isinstance(auth, Mapping) and type(auth.get('stamp')) is int and isinstance(auth.get('mac'), str):
                self._taken[auth['mac']] = (auth['stamp'], message.get('user_id'))
                heapq.heappush(self._by_stamp, (auth['stamp'], auth['mac']))

    def forget_person(self, user_id: str) -> int:
        """Let go of the MACs of ``user_id``'s feedback (a forget): the replay memory keeps
        nothing of them. A replay of it is refused as theirs (the tombstone) instead; how
        many went."""
        gone = [code for code, (_, person) in self._taken.items() if person == user_id]
        for code in gone:
            del self._taken[code]  # its heap entry finds nothing when its time comes
        return len(gone)

    def verify(self, payload: Mapping | None) -> str | None:
        """Why ``payload`` (a fleet forget, which stays valid without age) is refused, or
        None: it carries a well-formed ``auth`` of a known key whose MAC matches."""
        return self._verify(payload)[1]

    def signing_key(self) -> tuple[str, bytes]:
        """(key id, secret) this node signs with: the key file's first key (while keys
        rotate, peers that have not got the new key yet still check it)."""
        key_id = next(iter(self.keys))
        return key_id, self.keys[key_id]

    def check_rating(self, user_id: str, rating) -> str | None:
        """Why a peer's rating of ``user_id`` (``foldin.Rating``) is refused, or None: it
        must carry the signed feedback it was folded in from, that feedback must verify and
        name the same person, score, action and scene, the rating's id must be its MAC, and
        the peer must have received it within ``feedback_max_age`` of its signing."""
        signed = rating.feedback
        if signed is None:
            return f"rating '{rating.rating_id}' carries no signed feedback"
        auth, refusal = self._verify(signed)
        if refusal is not None:
            return f"rating '{rating.rating_id}': {refusal}"
        window = self._window()
        mismatch = (
            'its id is not its MAC' if rating.rating_id != auth['mac'] else
            f"its feedback is of user '{signed['user_id']}'" if signed['user_id'] != user_id else
            'its score is not its feedback\'s' if rating.score != signed['score'] else  # no float(): it may overflow
            'its action is not its feedback\'s' if 'action' in signed and rating.action != signed['action'] else
            'its scene id is not its feedback\'s' if rating.scene_id not in (None, signed['scene_id']) else
            'it was received further than feedback_max_age from its signing'
            if abs(rating.stamp - auth['stamp']) > window else None)
        return None if mismatch is None else f"rating '{rating.rating_id}': {mismatch}"

    def _window(self) -> int:
        return int(self._max_age() * 1e9)

    def _verify(self, payload) -> tuple[dict | None, str | None]:
        """(its auth, None) when ``payload`` carries a well-formed ``auth`` of a known key
        whose MAC matches (compared in constant time); else (None, why not)."""
        auth = payload.get('auth') if isinstance(payload, Mapping) else None
        if auth is None:
            return None, 'not signed: with feedback_key_file set, feedback needs "auth": {"key_id", "stamp", "mac"}'
        if not isinstance(auth, Mapping) or set(auth) != AUTH_FIELDS:
            return None, 'malformed auth: it must be an object of exactly "key_id", "stamp" and "mac"'
        key_id, stamp, code = auth['key_id'], auth['stamp'], auth['mac']
        if not isinstance(key_id, str) or not isinstance(code, str) or not MAC.fullmatch(code) \
                or type(stamp) is not int or not 0 <= stamp <= MAX_STAMP:
            return None, ('malformed auth: key_id must be text, stamp ROS time in ns (a non-negative integer), '
                          'mac 64 lowercase hexadecimal digits')
        secret = self.keys.get(key_id)
        if secret is None:
            return None, f"unknown key id '{key_id[:64]}'"
        if not hmac.compare_digest(mac(secret, payload, stamp), code):
            return None, f"wrong MAC for key '{key_id}'"
        return auth, None
