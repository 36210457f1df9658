"""Who is around and who is served, from ROS4HRI (REP 155) facts, without ROS.

The person manager says which ids are tracked (``/humans/persons/tracked``), and per id its
engagement (``engagement_status``), whether it is still ``anonymous``, its ``alias`` (this
id is now that one) and ``location_confidence``. ``People`` keeps the latest of each and
answers who is served:

* only a person whose engagement is ENGAGED is served;
* ties: a recognised person before an anonymous one, then the nearest to the robot, then
  the one engaged longest, then the smaller id (so the choice is deterministic);
* an alias is followed to the id it names (chains too), so a merged person is one person;
* an id that has not yet said ``anonymous: false`` counts as anonymous (privacy by default).

``anonymous`` and ``alias`` are latched facts that a person manager also publishes for people
it knows but does not track now: they are kept for untracked ids too (at most ``MAX_KNOWN``,
the oldest go) and hold once the id is tracked. Engagement and location confidence of an
untracked id are refused (``UntrackedPerson``).

An anonymous person is served under no user id: the ranker ranks for them with the
population prior, and nothing about them reaches its recording or state store. ``served``
returns the ``Served`` choice; ``Served.user_id`` is None for nobody or an anonymous person.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

from stars_ros.errors import UntrackedPerson

UNKNOWN, DISENGAGED, ENGAGING, ENGAGED, DISENGAGING = range(5)  # hri_msgs/EngagementLevel
ENGAGEMENT_NAMES = ('UNKNOWN', 'DISENGAGED', 'ENGAGING', 'ENGAGED', 'DISENGAGING')
MAX_ALIAS_CHAIN = 32  # longer chains (or cycles) are refused as bad input
MAX_KNOWN = 1000  # untracked ids whose latched facts (anonymous, alias) are kept for when they return


@dataclass
class Person:
    """What is known about one tracked id: engagement ``level`` and since when it has been
    ENGAGED (ns, None when not engaged), ``anonymous``, ``alias`` (the id this one now is) and
    ``confidence`` (location_confidence, None until told)."""

    level: int = UNKNOWN
    engaged_since: int | None = None
    anonymous: bool = True
    alias: str | None = None
    confidence: float | None = None


@dataclass(frozen=True)
class Served:
    """Whom the robot serves: ``person_id`` the canonical ROS4HRI id (None: no one engaged),
    ``anonymous`` whether that person is not yet recognised; ``user_id`` what goes on
    stars/user_id (None for nobody and for an anonymous person)."""

    person_id: str | None = None
    anonymous: bool = False

    @property
    def user_id(self) -> str | None:
        return None if self.person_id is None or self.anonymous else self.person_id

    def describe(self) -> str:
        if self.person_id is None:
            return 'nobody engaged: the ranker serves the population prior'
        if self.anonymous:
            return f"anonymous person '{self.person_id}': ranked with the population prior, nothing stored"
        return f"person '{self.person_id}'"


class People:
    """The latest ROS4HRI facts about people (see the module docstring).

    Args:
        now (callable): the clock, ns (ROS time in the node; a fake in tests).
    """

    def __init__(self, now: Callable[[], int]):
        self._now = now
        self.tracked: tuple = ()
        self._people: dict[str, Person] = {}
        self._known: dict[str, Person] = {}  # untracked ids' latched facts, oldest first

    # -- input ---------------------------------------------------------------------------
    def set_tracked(self, ids) -> tuple:
        """The ids now tracked; returns the ids that left (their state is dropped)."""
        ids = tuple(dict.fromkeys(str(i) for i in ids if str(i)))
        gone = tuple(i for i in self._people if i not in ids)
        for person_id in gone:
            person = self._people.pop(person_id)
            self._remember(person_id, Person(anonymous=person.anonymous, alias=person.alias))
        for person_id in ids:
            if person_id not in self._people:
                self._people[person_id] = self._known.pop(person_id, None) or Person()
        self.tracked = ids
        return gone

    def _remember(self, person_id: str, person: Person) -> None:
        self._known.pop(person_id, None)
        self._known[person_id] = person
        while len(self._known) > MAX_KNOWN:
            del self._known[next(iter(self._known))]

    def _latched(self, person_id: str) -> Person:
        """The record a latched fact goes to: the tracked person's, else the untracked id's."""
        person = self._people.get(person_id)
        if person is None:
            person = self._known.get(person_id) or Person()
            self._remember(person_id, person)
        return person

    def _person(self, person_id: str) -> Person:
        person = self._people.get(person_id)
        if person is None:
            raise UntrackedPerson(f"'{person_id}' is not in /humans/persons/tracked (ignored)")
        return person

    def set_engagement(self, person_id: str, level: int) -> None:
        if level not in range(len(ENGAGEMENT_NAMES)):
            raise ValueError(f"engagement level {level} of '{person_id}' is not one of hri_msgs/EngagementLevel's 0..4")
        person = self._person(person_id)
        if level == ENGAGED and person.engaged_since is None:
            person.engaged_since = self._now()
        elif level != ENGAGED:
            person.engaged_since = None
        person.level = level

    def set_anonymous(self, person_id: str, anonymous: bool) -> None:
        self._latched(person_id).anonymous = bool(anonymous)

    def set_alias(self, person_id: str, target: str) -> None:
        person = self._latched(person_id)
        target = str(target).strip() or None
        previous, person.alias = person.alias, target
        try:
            self.canonical(person_id)
        except ValueError:
            person.alias = previous
            raise

    def set_confidence(self, person_id: str, confidence: float) -> None:
        if not math.isfinite(confidence) or not 0.0 <= confidence <= 1.0:
            raise ValueError(f"location_confidence {confidence} of '{person_id}' is not in [0, 1]")
        self._person(person_id).confidence = float(confidence)

    # -- answers -------------------------------------------------------------------------
    def canonical(self, person_id: str) -> str:
        """The id ``person_id`` now is, following aliases; ValueError on a cycle."""
        seen = [person_id]
        while True:
            person = self._people.get(seen[-1])
            if person is None or person.alias is None:
                return seen[-1]
            if person.alias in seen or len(seen) > MAX_ALIAS_CHAIN:
                raise ValueError(f"alias cycle or chain over {MAX_ALIAS_CHAIN}: {' -> '.join([*seen, person.alias])}")
            seen.append(person.alias)

    def get(self, person_id: str) -> Person | None:
        return self._people.get(person_id)

    def members(self) -> dict:
        """canonical id -> the tracked ids that are that person (itself and its aliases)."""
        groups: dict[str, list] = {}
        for person_id in self.tracked:
            groups.setdefault(self.canonical(person_id), []).append(person_id)
        return groups

    def is_anonymous(self, person_id: str) -> bool:
        """A person is recognised when any id of theirs said ``anonymous: false``."""
        canonical = self.canonical(person_id)
        ids = self.members().get(canonical, [canonical])
        return all(self._people.get(i, Person()).anonymous for i in ids)

    def level(self, person_id: str) -> int:
        """The engagement of a person: the most engaged of their ids (an alias carries on)."""
        canonical = self.canonical(person_id)
        levels = [self._people[i].level for i in self.members().get(canonical, []) if i in self._people]
        return ENGAGED if ENGAGED in levels else max(levels, default=UNKNOWN)

    def engaged_since(self, person_id: str) -> int | None:
        canonical = self.canonical(person_id)
        times = [self._people[i].engaged_since for i in self.members().get(canonical, [])
                 if i in self._people and self._people[i].engaged_since is not None]
        return min(times, default=None)

    def served(self, distance: Callable[[str], float | None]) -> Served:
        """Whom to serve (the module docstring's rule); ``distance(person_id)`` is the
        person's distance to the robot in metres, None when their pose is unknown."""
        candidates = []
        for canonical in self.members():
            if self.level(canonical) != ENGAGED:
                continue
            d = distance(canonical)
            candidates.append((self.is_anonymous(canonical), math.inf if d is None else d,
                               self.engaged_since(canonical), canonical))
        if not candidates:
            return Served()
        anonymous, _, _, person_id = min(candidates)
        return Served(person_id, anonymous)
