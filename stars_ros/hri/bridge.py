"""The ROS4HRI bridge's logic, without ROS: facts in, the ranker's JSON messages out.

``stars_ros.ros.hri_bridge`` subscribes to the REP 155 topics and calls the ``on_*`` methods
with plain values; ``tick`` (on a timer) returns what to publish: the served user id when
it changed, a scene request when one is due (every ``1 / rate`` s, and at once when who is
in the scene, who interacts or who is served changed), and the implicit outcomes known now.
``on_ranking`` turns a ranking of a scene the bridge sent into a ``Decision``. Bad input
(an id not tracked, a non-finite pose, a frame that never arrives, a malformed message) is
counted by kind in ``problems`` and never stops the bridge.

**What is kept, and for how long.** In memory only, nothing on disk: the latest facts about
each tracked person (dropped when they leave ``/humans/persons/tracked``), groups and gazes
(ignored after ``max_age``), the served person of the last ``SENT_SCENES`` scenes sent (to
credit an executed action to them) and actions waiting for their outcome (at most
``outcome_window`` s). The ranker stores feedback (and implicit outcomes) of recognised
people only: the bridge never sends an anonymous person's id, drops their feedback and their
outcomes (counted: ``anonymous_dropped``), and an alias to a recognised id starts storing
from then on; nothing from before the alias is sent.

**Consent** (``store_policy``, ``consent_file`` and stars/consent, as the ranker's:
``node.consent``). Under 'consented' the feedback and implicit outcomes of a recognised person
not on the consent list are not sent either: dropped and counted as kind ``consent``; no
report names them (an outcome waiting for someone taken off the list is dropped when
the list changes). Their scenes still go out under their user id: the ranker ranks them as a
stranger and keeps nothing of them.
"""
from __future__ import annotations

import collections
import json
import math
from dataclasses import dataclass
from typing import Callable

from stars_ros import messages
from stars_ros.errors import UntrackedPerson
from stars_ros.hri.decisions import Decision, ImplicitOutcomes, decide
from stars_ros.hri.people import People, Served
from stars_ros.hri.poses import PoseSource
from stars_ros.hri.scene import (BuiltScene, Interactions, SceneSettings, build_scene, person_frame,
                                 scene_request)
from stars_ros.node.consent import Consent
from stars_ros.node.diagnostics import Problems

SENT_SCENES = 1000  # scenes whose served person is remembered for stars/executed


@dataclass(frozen=True)
class BridgeSettings:
    """The bridge's parameters (``docs/hri.md``): ``scene`` how scenes are built; ``rate``
    scenes a second; ``goal_frame`` the navigation frame of placement goals ('' =
    ``base_frame``); ``abstain_below`` the abstain rule's threshold on p_first_is_best;
    ``outcome_window`` seconds an action's outcome is watched; ``rating_scale`` the model's
    (lowest, highest) score; ``scene_prefix`` the scene ids' prefix; ``store_policy`` and
    ``consent_file`` whose feedback may be sent (``node.consent``)."""

    scene: SceneSettings = SceneSettings()
    rate: float = 2.0
    goal_frame: str = ''
    abstain_below: float = 0.5
    outcome_window: float = 5.0
    rating_scale: tuple = (0.0, 1.0)
    scene_prefix: str = 'hri-'
    store_policy: str = 'all'
    consent_file: str = ''

    def __post_init__(self):
        if not self.rate > 0:
            raise ValueError(f'rate must be positive, got {self.rate}')
        if not 0.0 <= self.abstain_below <= 1.0:
            raise ValueError(f'abstain_below must be in [0, 1], got {self.abstain_below}')

    @property
    def navigation_frame(self) -> str:
        return self.goal_frame or self.scene.base_frame


@dataclass(frozen=True)
class Outputs:
    """What one ``tick`` gives: ``user_id`` (None: unchanged; '' nobody), ``scene`` (a
    stars/scene payload or None) and ``feedback`` (implicit outcomes, stars/feedback payloads)."""

    user_id: str | None = None
    scene: dict | None = None
    feedback: tuple = ()


class BridgeCore:
    """See the module docstring. ``poses`` is the pose seam, ``now`` the clock (ns). A bad
    ``store_policy`` or a ``consent_file`` that cannot be read raises ConfigError."""

    def __init__(self, settings: BridgeSettings, poses: PoseSource, now: Callable[[], int]):
        self.settings, self.poses, self._now = settings, poses, now
        self.consent = Consent(settings.store_policy, settings.consent_file)
        self.people = People(now)
        self.interactions = Interactions()
        self.outcomes = ImplicitOutcomes(self.people, settings.outcome_window, settings.rating_scale, now,
                                         self.consent.allows)
        self.problems = Problems()
        self.served = Served()
        self.last_scene: BuiltScene | None = None
        self._published_user: str | None = None  # what stars/user_id says now ('' nobody; None: never said)
        self._sent = collections.OrderedDict()  # scene_id -> Served when it was sent
        self._sequence = 0
        self._last_sent_at: int | None = None
        self._last_signature = None
        self.left_out_total = collections.Counter()

    def report(self, kind: str, detail: str) -> None:
        self.problems.add(kind, detail, 0.0)

    def served_kept(self) -> bool:
        """Whether what the served person says is relayed, so the ranker may keep it: they are
        recognised (not anonymous) and, under store_policy consented, on the consent list."""
        served = self.served
        return (served.person_id is not None and not served.anonymous
                and self.consent.allows(self.people.canonical(served.person_id)))

    def _who(self, person_id) -> str:
        """``person_id`` as a report of their feedback or outcome names them: not at all when
        they are not on the consent list (store_policy consented)."""
        if person_id is None or self.consent.allows(self.people.canonical(person_id)):
            return f"'{person_id}'"
        return 'a person not on the consent list'

    # -- ROS4HRI facts -------------------------------------------------------------------
    def on_tracked(self, ids) -> None:
        self.people.set_tracked(ids)

    def on_person(self, field: str, person_id: str, value) -> None:
        """A per-person fact: ``field`` is engagement_status, anonymous, alias or
        location_confidence."""
        setter = {'engagement_status': self.people.set_engagement, 'anonymous': self.people.set_anonymous,
                  'alias': self.people.set_alias, 'location_confidence': self.people.set_confidence}[field]
        try:
            setter(person_id, value)
        except UntrackedPerson as error:
            self.report('untracked', f'{field}: {error}')
        except ValueError as error:
            self.report('bad_value', str(error))

    def on_group(self, group_id: str, members, stamp: int) -> None:
        unknown = [m for m in members if m not in self.people.tracked]
        if unknown:
            self.report('unknown_id', f"group '{group_id}' names ids not tracked: {unknown} (they are left out)")
        self.interactions.set_group(group_id, [m for m in members if m not in unknown], stamp)

    def on_gaze(self, sender: str, receiver: str, stamp: int) -> None:
        unknown = [i for i in (sender, receiver) if i not in self.people.tracked]
        if unknown:
            self.report('unknown_id', f'gaze {sender} -> {receiver} names ids not tracked: {unknown} (ignored)')
            return
        self.interactions.set_gaze(sender, receiver, stamp)

    def on_transform_problem(self, detail: str) -> None:
        self.report('non_finite_pose', detail)

    # -- the robot's side ----------------------------------------------------------------
    def on_executed(self, text: str) -> None:
        """stars/executed: ``{"scene_id", "action" or "candidate", "person_id"?}`` (the
        person defaults to whoever was served when the scene was sent)."""
        try:
            payload = messages.load_json(text)
            messages.check('executed', payload)
        except messages.BadMessage as error:
            self.report('bad_executed', f'stars/executed refused (msg_schemas/executed.schema.json): {error}')
            return
        scene_id, person_id = payload['scene_id'], payload.get('person_id')
        kind = 'candidate' if 'candidate' in payload else 'action'
        choice = payload[kind]
        if person_id is None:
            served = self._sent.get(scene_id)
            if served is None:
                self.report('bad_executed', f"stars/executed for scene '{scene_id}', which this bridge did not send "
                            '(or no longer remembers), names no person_id: ignored')
                return
            person_id = served.person_id
        if person_id is None or self.people.canonical(person_id) not in self.people.members():
            self.report('untracked', f'stars/executed for {self._who(person_id)}, who is not tracked: no outcome to '
                        'watch')
            return
        dropped = self.outcomes.dropped_unconsented
        self.outcomes.executed(person_id, scene_id, kind, choice)
        if self.outcomes.dropped_unconsented > dropped:
            self.report('consent', 'stars/executed for a person not on the consent list (store_policy consented): '
                        'no outcome watched, none sent')

    def on_person_feedback(self, text: str) -> dict | None:
        """Relay explicit feedback keyed by ROS4HRI person id (``{"person_id", "scene_id",
        "action" or "candidate", "score"}``) to stars/feedback under the person's user id;
        None (counted) when the person is anonymous or the message is bad."""
        try:
            payload = json.loads(text)
            if not isinstance(payload, dict):
                raise TypeError('not a JSON object')
            person_id = payload.pop('person_id')
            if not isinstance(person_id, str):
                raise TypeError('person_id must be a string')
            payload['user_id'] = self.people.canonical(person_id)
            messages.parse_feedback(json.dumps(payload))
        except (ValueError, KeyError, TypeError, messages.BadMessage) as error:
            self.report('bad_feedback', f'person feedback refused: {type(error).__name__}: {error}')
            return None
        if payload['user_id'] not in self.people.members() or self.people.is_anonymous(payload['user_id']):
            self.report('anonymous_dropped', f'feedback of {self._who(person_id)} dropped: not a recognised tracked '
                        'person')
            return None
        if not self.consent.allows(payload['user_id']):  # the report does not name them
            self.report('consent', 'feedback of a person not on the consent list (store_policy consented): '
                        'dropped, not relayed')
            return None
        return payload

    def on_consent(self, text: str) -> int | None:
        """A stars/consent message: the list it gives replaces the topic's last one, and the
        outcomes waiting for people no longer on the list are dropped; how many it names. A
        bad one is reported (None) and the list stays as it was."""
        try:
            count = self.consent.accept(text)
        except messages.BadMessage as error:
            self.report(error.kind, f'stars/consent refused: {error}; the consent list stays as it was')
            return None
        dropped = self.outcomes.dropped_unconsented
        self.outcomes.drop_unconsented()
        if self.outcomes.dropped_unconsented > dropped:
            self.report('consent', f'{self.outcomes.dropped_unconsented - dropped} implicit outcomes waiting for '
                        'people no longer on the consent list dropped, not sent')
        return count

    def on_ranking(self, text: str, robot_in_goal_frame) -> Decision | None:
        """The decision about a stars/ranking of a scene this bridge sent (None for others)."""
        try:
            ranking = json.loads(text)
            if not isinstance(ranking, dict) or ranking.get('scene_id') not in self._sent:
                return None
            return decide(ranking, self.settings.abstain_below, robot_in_goal_frame)
        except (ValueError, KeyError, TypeError, IndexError, AttributeError) as error:
            self.report('bad_ranking', f'ranking not understood: {type(error).__name__}: {error}')
            return None

    # -- the timer -----------------------------------------------------------------------
    def distance(self, person_id: str) -> float | None:
        pose = self.poses.lookup(self.settings.scene.base_frame, person_frame(person_id))
        if pose is None or not all(math.isfinite(v) for v in (pose.x, pose.y)):
            return None
        return math.hypot(pose.x, pose.y)

    def sent_for(self, scene_id: str) -> Served | None:
        """Whom the bridge served when it sent scene ``scene_id`` (None: not sent, or forgotten)."""
        return self._sent.get(scene_id)

    def tick(self, send_scene: bool = True) -> Outputs:
        """What to publish now; ``send_scene`` False holds scenes back (the ranker is not up)."""
        now = self._now()
        self.served = self.people.served(self.distance)
        user_id = self.served.user_id or ''
        changed_user = user_id != self._published_user
        if changed_user:
            self._published_user = user_id
        built = build_scene(self.people, self.poses, self.interactions, self.settings.scene, now)
        due = self._last_sent_at is None or now - self._last_sent_at >= 1e9 / self.settings.rate
        changed = changed_user or built.signature != self._last_signature
        scene = None
        if send_scene and built.people and (due or changed):
            scene = self._request(built, now)
        if scene is not None or (self.last_scene is not None and built.left_out != self.last_scene.left_out):
            for reason, ids in built.left_out.items():  # counted per scene sent (or change), not per tick
                self.left_out_total[reason] += len(ids)
                self.report(reason, f'left out of the scene ({reason}): {ids}')
        self.last_scene = built
        dropped, refused = self.outcomes.dropped_anonymous, self.outcomes.dropped_unconsented
        feedback = tuple(self.outcomes.resolve())
        if self.outcomes.dropped_anonymous > dropped:
            self.report('anonymous_dropped', f'{self.outcomes.dropped_anonymous - dropped} implicit outcomes of '
                        'anonymous people dropped, not sent')
        if self.outcomes.dropped_unconsented > refused:
            self.report('consent', f'{self.outcomes.dropped_unconsented - refused} implicit outcomes of people not '
                        'on the consent list (store_policy consented) dropped, not sent')
        return Outputs(user_id if changed_user else None, scene, feedback)

    def _request(self, built: BuiltScene, now: int) -> dict:
        self._sequence += 1
        scene_id = f'{self.settings.scene_prefix}{self._sequence}'
        self._sent[scene_id] = self.served
        while len(self._sent) > SENT_SCENES:
            self._sent.popitem(last=False)
        self._last_sent_at, self._last_signature = now, built.signature
        return scene_request(scene_id, built, self.settings.scene.placements, self.served.user_id)
