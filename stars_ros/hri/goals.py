"""When a decision becomes a navigation goal, without ROS.

A navigation stack drives to the goal it was given and replans when it gets another. A goal
re-sent with a new stamp at every ranking makes it replan without end; one given in a frame
that moves with the robot ("0.5 m ahead" of wherever the robot is now) makes it drive on for
ever. So ``GoalPolicy`` sends a goal only when the decision changes:

* the first goal, for the person served now or for nobody (another person's goal was
  cancelled as they stopped being served), or the first after an abstain ended,
* another placement is best, and it beats the placement of the goal followed now by more
  than ``hysteresis`` in the same ranking (two near-equal placements do not alternate), and
  its goal lies more than ``position_tolerance`` m or ``yaw_tolerance`` rad from that goal.

An abstain, or the served person leaving, cancels the goal followed (a navigation action is
then cancelled; a goal topic has nothing to send). A decision about a scene sent while
someone else was served than now (a ranking that was on its way as the served person left or
changed) sends nothing, and after the served person left, a goal for nobody at the place of
the one cancelled is not sent again: it would be the goal just cancelled, for nobody. Goals are compared in the
navigation
frame, which the bridge requires to be one that does not move with the robot (``map``,
``odom``) unless a goal in the robot's frame is asked for (``robot_frame_goal_refusal``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from stars_ros.hri.decisions import Decision
from stars_ros.hri.poses import Pose

ROBOT_FRAMES = ('base_link', 'base_footprint')  # REP 105's frames attached to the robot


@dataclass(frozen=True)
class GoalSettings:
    """``position_tolerance`` metres and ``yaw_tolerance`` radians under which two goals are
    the same place; ``hysteresis``: by how much (score) another placement must beat the one
    followed to replace it."""

    position_tolerance: float = 0.25
    yaw_tolerance: float = 0.35
    hysteresis: float = 0.05

    def __post_init__(self):
        for name in ('position_tolerance', 'yaw_tolerance', 'hysteresis'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f'{name} must be a finite number >= 0, got {value}')


@dataclass(frozen=True)
class GoalStep:
    """What to do now: ``send`` a goal (a Pose in the navigation frame) or None, ``cancel``
    the goal followed, and why (``reason``)."""

    send: Pose | None = None
    cancel: bool = False
    reason: str = ''


@dataclass(frozen=True)
class Followed:
    """The goal the robot follows now: for whom, which placement, where."""

    person_id: str | None
    choice: str
    goal: Pose


def robot_frame_goal_refusal(goal_frame: str, base_frame: str, allowed: bool) -> str | None:
    """Why a goal in ``goal_frame`` cannot be sent (None: it can): a frame that moves with
    the robot (``base_frame``, base_link, base_footprint) turns "0.5 m ahead" into a goal that
    is never reached, unless ``allowed`` (an explicit opt-in)."""
    if allowed or (goal_frame != base_frame and goal_frame not in ROBOT_FRAMES):
        return None
    return (f"goal_frame '{goal_frame}' moves with the robot: a navigation stack given '0.5 m ahead' in it drives "
            "on without end. Set goal_frame to a frame that does not move with the robot (map or odom, REP 105), "
            'or set goal_in_robot_frame:=true if your controller takes goals in the robot\'s frame')


class GoalPolicy:
    """Turns each decision into a ``GoalStep`` (see the module docstring)."""

    def __init__(self, settings: GoalSettings = GoalSettings()):
        self.settings = settings
        self.followed: Followed | None = None
        self.served: str | None = None  # the person served now (``on_served``)
        self.left: Followed | None = None  # the goal cancelled as its person left, until another is sent

    def on_decision(self, decision: Decision, person_id: str | None) -> GoalStep:
        """The step for ``decision``, about a scene sent while ``person_id`` was served."""
        if person_id != self.served:
            return GoalStep(reason=f'the scene was sent while {_who(person_id)} was served, not '
                                   f'{_who(self.served)}: no goal')
        if decision.abstain or decision.goal is None:
            return self._cancel(f'abstain: {decision.reason}' if decision.abstain else f'no goal: {decision.reason}')
        followed = self.followed
        if followed is None:  # ``on_served`` cancelled another person's
            left = self.left
            if left is not None and self._same_place(decision.goal, left.goal):
                return GoalStep(reason=f"'{decision.choice}' is where the goal cancelled as {_who(left.person_id)} "
                                       'left was: not sent again')
            reason = 'first goal'
        elif decision.choice == followed.choice:
            return GoalStep(reason=f"'{decision.choice}' is still best")
        else:
            held = dict(decision.scores).get(followed.choice)
            if held is not None and decision.score - held <= self.settings.hysteresis:
                return GoalStep(reason=f"'{decision.choice}' beats '{followed.choice}' by {decision.score - held:.3f}"
                                f' <= hysteresis {self.settings.hysteresis}: goal kept')
            if self._same_place(decision.goal, followed.goal):
                self.followed = Followed(person_id, decision.choice, followed.goal)
                return GoalStep(reason=f"'{decision.choice}' is where the goal followed is: goal kept")
            reason = f"another placement: '{decision.choice}' instead of '{followed.choice}'"
        self.followed, self.left = Followed(person_id, decision.choice, decision.goal), None
        return GoalStep(send=decision.goal, reason=reason)

    def on_served(self, person_id: str | None) -> GoalStep:
        """The served person is now ``person_id`` (None: nobody): a goal for someone else is cancelled."""
        self.served = person_id
        if person_id is not None:
            self.left = None
        if self.followed is not None and self.followed.person_id != person_id:
            if person_id is None:
                self.left = self.followed
            return self._cancel(f'{_who(self.followed.person_id)} is no longer served')
        return GoalStep()

    def _cancel(self, reason: str) -> GoalStep:
        had_goal, self.followed = self.followed is not None, None
        return GoalStep(cancel=had_goal, reason=reason)

    def _same_place(self, a: Pose, b: Pose) -> bool:
        turn = abs(math.atan2(math.sin(a.yaw - b.yaw), math.cos(a.yaw - b.yaw)))
        return math.hypot(a.x - b.x, a.y - b.y) <= self.settings.position_tolerance and \
            turn <= self.settings.yaw_tolerance


def _who(person_id: str | None) -> str:
    return 'nobody' if person_id is None else f"'{person_id}'"
