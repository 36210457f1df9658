"""What the owner of people holds on its way out of the node: the user models whose ratings
the state store has committed, waiting for the executor to send them, and the people whose
erase runs, whose models are held back and dropped and whose messages no bag may keep."""
from __future__ import annotations

import collections
import dataclasses
from typing import Callable

from stars_ros.state import mentions


@dataclasses.dataclass
class _Erasing:
    """One person whose erase runs: how many erases, how to find them in a message, and
    how many of their models were held back meanwhile."""

    runs: int
    named: Callable[[bytes], bool]
    held: int = 0


class Outgoing:
    """Committed models to send (``committed``, from the store's thread) and the erases running."""

    def __init__(self):
        self._committed = collections.deque()  # (user, stars/user_model payload) whose ratings are committed
        self._erasing = {}  # user -> _Erasing

    def __bool__(self) -> bool:
        return bool(self._committed)

    def committed(self, user_id: str, payload: str) -> None:
        """A model whose ratings are committed (the store's thread): sent at the next ``take``."""
        self._committed.append((user_id, payload))

    def take(self) -> list:
        """The payloads to send now; a model of someone being erased is held back, then dropped."""
        ready = []
        while self._committed:
            user_id, payload = self._committed.popleft()
            if user_id in self._erasing:
                self._erasing[user_id].held += 1
            else:
                ready.append(payload)
        return ready

    def erase_begins(self, user_id: str) -> None:
        erasing = self._erasing.setdefault(user_id, _Erasing(0, mentions(user_id)))
        erasing.runs += 1

    def erase_ends(self, user_id: str) -> int:
        """One erase of ``user_id`` ended: their models committed meanwhile are dropped; how many."""
        waiting = [entry for entry in list(self._committed) if entry[0] == user_id]
        for entry in waiting:
            self._committed.remove(entry)
        erasing = self._erasing.get(user_id)
        held = 0 if erasing is None else erasing.held
        if erasing is not None:
            erasing.held, erasing.runs = 0, erasing.runs - 1
            if erasing.runs <= 0:
                del self._erasing[user_id]
        return len(waiting) + held

    def being_erased(self, user_id: str) -> bool:
        return user_id in self._erasing

    def names_someone_erased(self, data: bytes) -> bool:
        """True when ``data`` names a person whose erase runs."""
        return any(erasing.named(data) for erasing in list(self._erasing.values()))
