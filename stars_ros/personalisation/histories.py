"""The ratings a node keeps per person, bounded: its own feedback histories and, with fleet
sharing, its peers' ratings (``fleet.PeerRatings``). Both keep at most ``max_users`` people,
the one who rated least recently going first, and at most ``max_ratings`` ratings each; what
the bounds drop stays in the MCAP log, where the offline refit finds it. A person restored from the state store may
be held as ``Deferred``: their ratings are read the first time they are used, so a restart
reads people, not every rating. Thread-safe.
"""
from __future__ import annotations

import collections
import threading
from typing import Callable, Sequence

from stars_ros.state.person import Deferred, Rating


class BoundedUsers:
    """Per-person entries in least-recently-rated order, at most ``max_users`` people and
    ``max_ratings`` ratings each (subclasses say how a person's ratings are held)."""

    def __init__(self, max_ratings: int, max_users: int):
        if max_ratings < 1 or max_users < 1:
            raise ValueError('max_ratings and max_users must be positive')
        self.max_ratings, self.max_users = max_ratings, max_users
        self._users = collections.OrderedDict()  # user -> their ratings, least recently rated first
        self._lock = threading.Lock()
        self.after_read: Callable[[], None] = lambda: None  # called once a Deferred person is read

    def __len__(self) -> int:
        return len(self._users)

    def __contains__(self, user_id) -> bool:
        return user_id in self._users

    def users(self) -> list:
        """The people held, least recently rated first (their ratings are not read)."""
        with self._lock:
            return list(self._users)

    def _held(self, user_id: str):
        """``user_id``'s ratings as the subclass holds them, read now if Deferred; None when
        not held (lock held)."""
        held = self._users.get(user_id)
        if isinstance(held, Deferred):
            held = self._users[user_id] = self._holding(held.load())
            self._loaded(user_id)
            self.after_read()
        return held

    def _holding(self, ratings: list):
        return list(ratings)

    def _loaded(self, user_id: str) -> None:
        """Hook: a Deferred person was just read."""

    def _evict(self) -> list:
        """Drop the people who rated least recently beyond ``max_users`` (lock held); returns them."""
        evicted = []
        while len(self._users) > self.max_users:
            evicted.append(self._users.popitem(last=False)[0])
        return evicted


class FeedbackHistories(BoundedUsers):
    """The ratings each user's fold-in is solved from, bounded so a long-running node (and
    its state store) cannot grow without limit: the ``max_ratings`` most recent ratings per
    user and the ``max_users`` users who rated most recently. What the bounds drop stays in
    the MCAP log, where the offline refit finds it. Thread-safe.

    A user's ratings are numbered in arrival order; ``dropped(user)`` counts how many of
    the oldest are gone, so ``absorb`` can remove "the first n ratings" a refit consumed
    even when some of them were already trimmed.
    """

    def __init__(self, max_ratings: int, max_users: int):
        super().__init__(max_ratings, max_users)
        self._dropped = {}

    def add(self, user_id: str, rating: Rating) -> list:
        """Append ``rating``; returns the users evicted to make room (their fold-in ends)."""
        with self._lock:
            if self._held(user_id) is None:
                self._users[user_id] = []
            self._users[user_id].append(rating)
            self._users.move_to_end(user_id)
            self._trim(user_id)
            return self._evict()

    def ratings(self, user_id: str) -> list:
        with self._lock:
            return list(self._held(user_id) or ())

    def dropped(self, user_id: str) -> int:
        with self._lock:
            return self._dropped.get(user_id, 0)

    def drop(self, user_id: str) -> int:
        """Forget ``user_id``'s history (a person erased); returns how many ratings it held."""
        with self._lock:
            held = self._users.pop(user_id, None)
            self._dropped.pop(user_id, None)
            return len(held.load()) if isinstance(held, Deferred) else len(held or ())

    def discard(self, user_id: str, unusable: Sequence[Rating]) -> None:
        """Remove ratings that cannot be folded in (they count as dropped)."""
        with self._lock:
            kept = [r for r in self._held(user_id) or () if r not in unusable]
            if user_id in self._users:
                self._dropped[user_id] = self._dropped.get(user_id, 0) + len(self._users[user_id]) - len(kept)
                self._users[user_id] = kept

    def absorb(self, counts: dict) -> list:
        """Forget the first ``counts[user]`` ratings each user ever gave here (a refit holds
        them now); returns the users who still have ratings, to be re-solved."""
        with self._lock:
            for user_id, count in counts.items():
                if self._held(user_id) is not None:
                    skip = max(0, int(count) - self._dropped.get(user_id, 0))
                    self._dropped[user_id] = self._dropped.get(user_id, 0) + min(skip, len(self._users[user_id]))
                    self._users[user_id] = self._users[user_id][skip:]
            for user_id in [u for u, r in self._users.items() if not r]:
                del self._users[user_id]
                self._dropped.pop(user_id, None)
            return list(self._users)

    def set_limits(self, max_ratings: int, max_users: int) -> list:
        """New bounds, applied now; returns the users evicted."""
        with self._lock:
            self.max_ratings, self.max_users = max_ratings, max_users
            for user_id in list(self._users):
                if self._held(user_id) is not None:
                    self._trim(user_id)
            return self._evict()

    def snapshot(self) -> dict:
        """user -> (ratings, dropped), least recently rated first (every Deferred one read)."""
        with self._lock:
            return {u: (list(self._held(u)), self._dropped.get(u, 0)) for u in list(self._users)}

    def restore(self, state: dict) -> list:
        """Add users from ``snapshot()``-shaped ``state``, whose ratings may be Deferred
        (the state store's); returns the users evicted by the bounds."""
        with self._lock:
            for user_id, (ratings, dropped) in state.items():
                self._users[user_id] = ratings if isinstance(ratings, Deferred) else list(ratings)
                self._users.move_to_end(user_id)
                self._dropped[user_id] = int(dropped)
                if not isinstance(ratings, Deferred):
                    self._trim(user_id)
            return self._evict()

    def _loaded(self, user_id: str) -> None:
        self._trim(user_id)  # the bound may be lower than when they were stored

    def _trim(self, user_id):
        extra = len(self._users[user_id]) - self.max_ratings
        if extra > 0:
            del self._users[user_id][:extra]
            self._dropped[user_id] = self._dropped.get(user_id, 0) + extra

    def _evict(self) -> list:
        evicted = super()._evict()
        for user_id in evicted:
            self._dropped.pop(user_id, None)
        return evicted
