"""A person's state, with one owner: the ratings a person gave and the model solved from them
(``person``: the types, and the check of a score against the checkpoint's rating scale), and
the SQLite store that keeps them across restarts (``store``: people, ratings, peers' ratings
and the journal of accepted feedback, written by its own thread; ``schema``: its tables;
``rows``: what a write changes; ``reader``: reading without holding it; ``locking``: one
holder; ``legacy`` and ``migration``: what earlier versions kept). The owner of people
(``personalisation.online.Personalisation``) writes a person only through ``PersonWriter``'s
methods; nothing here imports personalisation, the recording or ROS."""
from concurrent.futures import Future
from pathlib import Path
from typing import Callable, Protocol, Sequence

from stars_ros.state.person import (Deferred, Rating, UserModel, check_ratings, check_score, loaded,
                                    scene_digest)
from stars_ros.state.forgotten import Forgotten, mentions
from stars_ros.errors import StoreLockedError
from stars_ros.state.reader import StoreReader, committed_feedback, forgotten_in, open_reader
from stars_ros.state.schema import DATABASE, Person, PersonUpdate
from stars_ros.state.store import StateStore


class PersonWriter(Protocol):
    """What personalisation may do to the store: the narrow interface ``StateStore`` gives it."""

    path: Path
    folder: Path

    def write_person(self, update: PersonUpdate | None, feedback: Sequence[tuple[dict, str]] = ()) -> int: ...

    def forget_person(self, user_id: str) -> int: ...

    def erase_person(self, user_id: str) -> Future: ...

    def erase_older(self, cutoff: int) -> Future: ...

    def keep_tombstone(self, tag: str) -> int: ...

    def when_committed(self, sequence: int, callback: Callable[[], None]) -> None: ...

    def known_people(self) -> set: ...

    def forgotten(self) -> Forgotten: ...

    def set_fingerprint(self, fingerprint: str) -> None: ...

    def load(self, fingerprint: str) -> tuple[list, str | None]: ...

    def signed_feedback(self) -> list: ...

    def encodings(self, scenes: Sequence, fingerprint: str) -> dict: ...


__all__ = ['DATABASE', 'Deferred', 'Forgotten', 'Person', 'PersonUpdate', 'PersonWriter', 'Rating', 'StateStore',
           'StoreLockedError', 'StoreReader', 'UserModel', 'check_ratings', 'check_score', 'committed_feedback',
           'forgotten_in', 'loaded', 'mentions', 'open_reader', 'scene_digest']
