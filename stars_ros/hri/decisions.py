"""A ranking the robot can act on, and what it learns from acting, without ROS.

**Decision.** For each stars/ranking of a scene the bridge sent, the first entry is the
choice: a placement becomes a navigation goal (``goal``: the placement's offset in the
robot's frame, composed with the robot's pose in the navigation frame), an action is named
with its ``score`` and ``score_sd``. **Abstain rule:** when the ranking carries
``p_first_is_best`` (personalised models) and it is below ``abstain_below``, the robot
abstains: the decision says so and no goal is sent. Without ``p_first_is_best`` (a model that
gives no uncertainty) the first entry is taken.

**Implicit outcomes.** When the robot reports what it did (``stars/executed``) for a person,
their engagement over the next ``window`` seconds is the outcome: disengaging (DISENGAGING,
DISENGAGED, or no longer tracked) within the window is ``disengaged``, still engaged at its
end is ``stayed``. The outcome goes to the ranker as feedback marked ``"implicit": true``
whose score is the rating scale's top (stayed) or bottom (disengaged), which the fold-in
treats as a Bernoulli observation with its own, larger noise (``personalisation.foldin``). An
anonymous person's outcome is dropped (counted), never sent: their id must not be stored. So
is, under store_policy 'consented' (``may_store``), the outcome of a recognised person not on
the consent list when the robot acts or when the outcome is known.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

from stars_ros.hri.people import DISENGAGED, DISENGAGING, People
from stars_ros.hri.poses import Pose, compose
from stars_ros.hri.scene import placement_offset


@dataclass(frozen=True)
class Decision:
    """What to do about one ranking: ``choice`` (an action or a placement label), its
    ``score``, ``score_sd`` and the ranking's ``p_first_is_best`` (None when not given);
    ``abstain`` with ``reason``; ``goal`` (a Pose in the navigation frame) for a placement
    the robot is to move to; ``scores``: (choice, score) of every entry of the ranking (for
    the goal policy's hysteresis)."""

    scene_id: str
    user_id: str | None
    kind: str  # 'action' or 'candidate'
    choice: str
    score: float
    score_sd: float | None
    p_first_is_best: float | None
    abstain: bool
    reason: str
    goal: Pose | None = None
    scores: tuple = ()

    def to_json(self) -> dict:
        out = {'scene_id': self.scene_id, 'user_id': self.user_id, self.kind: self.choice, 'score': self.score,
               'score_sd': self.score_sd, 'p_first_is_best': self.p_first_is_best, 'abstain': self.abstain,
               'reason': self.reason}
        if self.goal is not None:
            out['goal'] = {'x': self.goal.x, 'y': self.goal.y, 'yaw': self.goal.yaw}
        return out


def decide(ranking: dict, abstain_below: float, robot_in_goal_frame: Pose | None) -> Decision:
    """The decision about a stars/ranking payload (see the module docstring).
    ``robot_in_goal_frame``: the robot's pose in the navigation frame (None: unknown, then a
    placement cannot be a goal and the robot abstains, saying why)."""
    if not 0.0 <= abstain_below <= 1.0:
        raise ValueError(f'abstain_below must be in [0, 1], got {abstain_below}')
    first = ranking['ranking'][0]
    kind = 'candidate' if 'candidate' in first else 'action'
    p_best = ranking.get('p_first_is_best')
    common = dict(scene_id=ranking['scene_id'], user_id=ranking.get('user_id'), kind=kind, choice=first[kind],
                  score=float(first['score']), score_sd=first.get('score_sd'), p_first_is_best=p_best,
                  scores=tuple((entry[kind], float(entry['score'])) for entry in ranking['ranking']))
    if p_best is not None and p_best < abstain_below:
        return Decision(**common, abstain=True,
                        reason=f'p_first_is_best {p_best:.3f} < abstain_below {abstain_below}: not sure enough')
    if kind == 'action':
        return Decision(**common, abstain=False, reason='best action')
    if robot_in_goal_frame is None:
        return Decision(**common, abstain=True, reason="the robot's pose in the navigation frame is unknown")
    x, y = placement_offset(first['candidate'])
    goal = compose(robot_in_goal_frame, Pose(x, y, 0.0, robot_in_goal_frame.stamp))
    return Decision(**common, abstain=False, reason='best placement', goal=goal)


@dataclass
class Executed:
    """An action the robot took for a person, waiting for its outcome until ``deadline`` (ns);
    ``recognised``: the person was not anonymous when last seen tracked."""

    person_id: str
    scene_id: str
    kind: str
    choice: str
    deadline: int
    recognised: bool


class ImplicitOutcomes:
    """Actions waiting for their outcome (see the module docstring).

    Args:
        people (People): engagement and identities.
        window (float): seconds an outcome is watched for.
        scale (tuple): (lowest, highest) score of the model's rating scale.
        now (callable): the clock, ns.
        may_store (callable): whether a user id may reach the ranker (``node.consent.Consent.allows``).
    """

    def __init__(self, people: People, window: float, scale: tuple, now: Callable[[], int],
                 may_store: Callable[[str], bool] = lambda user_id: True):
        if not window > 0:
            raise ValueError(f'the outcome window must be positive, got {window}')
        low, high = (float(v) for v in scale)
        if not (math.isfinite(low) and math.isfinite(high) and low < high):
            raise ValueError(f'the rating scale must be two finite numbers, lowest first, got {scale}')
        self.people, self.window_ns, self.scale, self._now = people, int(window * 1e9), (low, high), now
        self.may_store = may_store
        self.waiting: list[Executed] = []
        self.dropped_anonymous = 0
        self.dropped_unconsented = 0

    def executed(self, person_id: str, scene_id: str, kind: str, choice: str) -> None:
        """The robot did ``choice`` (an action or a candidate) in ``scene_id`` for ``person_id``;
        for a recognised person who may not be stored nothing is watched (counted)."""
        if kind not in ('action', 'candidate'):
            raise ValueError(f"kind must be 'action' or 'candidate', got '{kind}'")
        person_id = self.people.canonical(person_id)
        recognised = not self.people.is_anonymous(person_id)
        if recognised and not self.may_store(person_id):
            self.dropped_unconsented += 1
            return
        self.waiting.append(Executed(person_id, scene_id, kind, choice, self._now() + self.window_ns, recognised))

    def drop_unconsented(self) -> None:
        """Let go at once of the outcomes waiting for recognised people who may no longer be
        stored (the consent list changed), counted: nothing of theirs is kept to be sent."""
        kept = [item for item in self.waiting if not item.recognised or self.may_store(item.person_id)]
        self.dropped_unconsented += len(self.waiting) - len(kept)
        self.waiting = kept

    def resolve(self) -> list:
        """Feedback payloads (stars/feedback) of the outcomes known now; the others wait. A
        person who left the tracked set disengaged; whether they were recognised is what
        was known while they were tracked."""
        now, out, still = self._now(), [], []
        for item in self.waiting:
            tracked = self.people.canonical(item.person_id) in self.people.members()
            if tracked:
                item.person_id = self.people.canonical(item.person_id)
                item.recognised = not self.people.is_anonymous(item.person_id)
            level = self.people.level(item.person_id) if tracked else DISENGAGED
            if level in (DISENGAGING, DISENGAGED):
                stayed = False
            elif now >= item.deadline:
                stayed = True
            else:
                still.append(item)
                continue
            if not item.recognised:
                self.dropped_anonymous += 1
                continue
            if not self.may_store(item.person_id):
                self.dropped_unconsented += 1
                continue
            out.append({'user_id': item.person_id, 'scene_id': item.scene_id, item.kind: item.choice,
                        'score': self.scale[1] if stayed else self.scale[0], 'implicit': True})
        self.waiting = still
        return out
