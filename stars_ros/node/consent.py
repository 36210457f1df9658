"""Consent before storing (``store_policy``): whom the ranker and the bridge may store.

With ``store_policy`` 'all' everyone is. With 'consented' only the people on the consent
list are: the ids of ``consent_file`` (read at start) and those of the latest stars/consent
message (latched; each replaces the one before). Everyone else is ranked as a stranger and
nothing of them is kept (docs/privacy.md). ROS-free.
"""
from __future__ import annotations

from pathlib import Path

from stars_ros import messages
from stars_ros.errors import BadMessage, ConfigError

POLICIES = ('all', 'consented')


def read_consent_file(path) -> frozenset:
    """The ids of a consent file: one a line, blank lines and lines starting with # aside."""
    path = Path(path).expanduser()
    try:
        lines = path.read_text(encoding='utf-8').splitlines()
    except (OSError, UnicodeDecodeError) as error:
        raise ConfigError(f'consent_file {path} cannot be read: {error}') from None
    return frozenset(line.strip() for line in lines if line.strip() and not line.strip().startswith('#'))


class Consent:
    """Whether a person may be stored (``allows``).

    Args:
        policy (str): ``store_policy``, 'all' or 'consented' (ConfigError otherwise).
        path (str): ``consent_file``; '' for none.
    """

    def __init__(self, policy: str, path: str = ''):
        if policy not in POLICIES:
            raise ConfigError(f"store_policy is '{policy}'; it must be one of {', '.join(POLICIES)}")
        self.restricted = policy == 'consented'
        self.from_file = read_consent_file(path) if path and self.restricted else frozenset()
        self.from_topic = frozenset()

    def allows(self, user_id) -> bool:
        """True when ``user_id``'s data may be stored, learned and shared (None: nobody to store)."""
        return not self.restricted or user_id in self.from_file or user_id in self.from_topic

    def accept(self, text: str, max_bytes: int = messages.DEFAULT_MAX_BYTES) -> int:
        """A stars/consent message replaces the list the topic gave; how many it names.
        BadMessage, and the list as it was, when it is not one."""
        import fastjsonschema

        payload = messages.load_json(text, max_bytes)
        try:
            messages.validator('consent')(payload)
        except fastjsonschema.JsonSchemaValueException as error:
            raise BadMessage('schema', f"consent message invalid: {error.message.removeprefix('data')}") from None
        self.from_topic = frozenset(payload['consented'])
        return len(self.from_topic)
