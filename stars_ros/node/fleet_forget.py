"""Fleet forget: a ranker that forgot a person tells its peers on stars/forget_person, and a
peer forgets them too. ROS-free; ``RankerCore`` sends and takes in the messages.

The message names the person by ``forgotten.fleet_tag``, not by their id: HMAC-SHA256 under
the fleet's feedback key (the key file's first key; the message is signed by it as feedback
is), SHA-256 without keys, over a random salt and the id. A peer computes the tag of every id
it holds (memory, the state store's people and journal) and forgets those that match
through its own forget path; it keeps the tag as a fleet tombstone either way, so a model of
that person arriving later is refused even where they were never met. docs/privacy.md says
what an eavesdropper learns.
"""
from __future__ import annotations

import os
from typing import Iterable

from stars_ros import feedback_auth, messages
from stars_ros.errors import BadMessage
from stars_ros.state.forgotten import fleet_tag, fleet_tombstone

SALT_BYTES = 16


def forget_message(user_id: str, origin: str, authenticator, stamp: int) -> dict:
    """The stars/forget_person message of ``user_id`` from the ranker ``origin``; signed at
    ``stamp`` (ROS time, ns) by ``authenticator``'s signing key, unsigned without one."""
    salt = os.urandom(SALT_BYTES)
    if authenticator is None:
        return {'tag': fleet_tag(None, salt, user_id), 'salt': salt.hex(), 'origin': origin}
    key_id, secret = authenticator.signing_key()
    fields = {'tag': fleet_tag(secret, salt, user_id), 'salt': salt.hex(), 'origin': origin}
    return feedback_auth.sign(fields, key_id, secret, stamp)


def parse_forget_message(text, max_bytes: int, authenticator) -> dict:
    """A peer's stars/forget_person message, checked: its schema, and with feedback keys its
    signature (a forget has no age: a replay only forgets again whom it forgot). BadMessage
    (``schema``, ``auth``, ...) says why not."""
    import fastjsonschema

    payload = messages.load_json(text, max_bytes)
    try:
        messages.validator('forget_person')(payload)
    except fastjsonschema.JsonSchemaValueException as error:
        raise BadMessage('schema', f"forget_person message invalid: {error.message.removeprefix('data')}") from None
    if authenticator is not None:
        refusal = authenticator.verify(payload)
        if refusal is not None:
            raise BadMessage('auth', f'forget_person message refused: {refusal}')
    return payload



def _key(payload: dict, authenticator) -> tuple[str, bytes | None]:
    if authenticator is None or 'auth' not in payload:
        return '', None
    key_id = payload['auth']['key_id']
    return key_id, authenticator.keys[key_id]


def named_in(payload: dict, known: Iterable[str], authenticator) -> list:
    """The ids of ``known`` the checked message ``payload`` names."""
    _, key = _key(payload, authenticator)
    salt = bytes.fromhex(payload['salt'])
    return sorted(user_id for user_id in known if fleet_tag(key, salt, user_id) == payload['tag'])


def tombstone_of(payload: dict, authenticator) -> str:
    """The fleet tombstone the checked message ``payload`` leaves (``forgotten.fleet_tombstone``)."""
    key_id, _ = _key(payload, authenticator)
    return fleet_tombstone(key_id, payload['salt'], payload['tag'])
