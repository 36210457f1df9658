"""Fleet sharing: rankers on one ROS domain share what they learn about a person.

With ``fleet_sharing`` on, a ranker publishes each user model it solves on stars/user_model
together with the ratings it solved it from (each with the rated scene's content, its id,
stamp and origin), takes in its peers' messages on the same topic (remap it to one
fleet-wide topic when robots live in namespaces), and solves each user from the union of
the ratings it holds: its own and its peers'.

Why ratings, not the "freshest" model: two robots that fold in the same person at the same
time each hold a model the other lacks, and no clock orders them. Ratings, keyed by id,
form a grow-only set: merging is order-free, a duplicate changes nothing, and the union
decides the model. ``solve_set`` orders the union by (stamp, id) and keeps the most recent
``max_ratings``; the fold-in encodes each rated scene on its own (``FoldIn``'s
``scene_by_scene``), so robots holding the same ratings solve the same model to the last
bit (same checkpoint, same build). A robot re-publishes only when its union grew, so the
exchange stops once everyone holds the same ratings.

ROS-free: ``Personalisation`` keeps a ``PeerRatings`` and the node only carries messages.
"""
from __future__ import annotations

import uuid
from typing import Iterable, Sequence

from stars_ros.state import Deferred, Rating
from stars_ros.personalisation.histories import BoundedUsers


def new_rating_id() -> str:
    return uuid.uuid4().hex


def solve_set(own: Sequence[Rating], peers: Iterable[Rating], max_ratings: int) -> list:
    """The ratings a user's model is solved from: own and peer ratings, each id once,
    ordered by (stamp, id), the most recent ``max_ratings``."""
    union = {r.rating_id: r for r in peers}
    union.update((r.rating_id, r) for r in own)
    return sorted(union.values(), key=lambda r: (r.stamp, r.rating_id))[-max_ratings:]


class PeerRatings(BoundedUsers):
    """The ratings peers shared, per user (rating id -> Rating): the most recent
    ``max_ratings`` by stamp, of the ``max_users`` users who rated most recently."""

    def known(self, user_id: str) -> set:
        with self._lock:
            return set(self._held(user_id) or ())

    def ratings(self, user_id: str) -> list:
        with self._lock:
            return list((self._held(user_id) or {}).values())

    def add(self, user_id: str, ratings: Sequence[Rating]) -> list:
        """Keep ``ratings`` (their ids are new); returns the users evicted to make room."""
        with self._lock:
            kept = self._held(user_id)
            if kept is None:
                kept = self._users[user_id] = {}
            kept.update((r.rating_id, r) for r in ratings)
            self._users.move_to_end(user_id)
            self._trim(user_id)
            return self._evict()

    def restore(self, state: dict) -> list:
        """Add users {user: [Rating] or Deferred} (the state store's); returns those evicted."""
        with self._lock:
            for user_id, ratings in state.items():
                self._users[user_id] = ratings if isinstance(ratings, Deferred) else self._holding(ratings)
                self._users.move_to_end(user_id)
                if not isinstance(ratings, Deferred):
                    self._trim(user_id)
            return self._evict()

    def discard(self, user_id: str, ratings: Sequence[Rating]) -> None:
        with self._lock:
            for rating in ratings:
                (self._held(user_id) or {}).pop(rating.rating_id, None)

    def drop(self, user_id: str) -> None:
        with self._lock:
            self._users.pop(user_id, None)

    def snapshot(self) -> dict:
        """user -> [Rating], least recently rated user first (every Deferred one read)."""
        with self._lock:
            return {u: list(self._held(u).values()) for u in list(self._users)}

    def _holding(self, ratings: list) -> dict:
        return {r.rating_id: r for r in ratings}

    def _loaded(self, user_id: str) -> None:
        self._trim(user_id)

    def _trim(self, user_id: str) -> None:
        kept = self._users[user_id]
        if len(kept) > self.max_ratings:
            recent = sorted(kept.values(), key=lambda r: (r.stamp, r.rating_id))[-self.max_ratings:]
            self._users[user_id] = {r.rating_id: r for r in recent}
