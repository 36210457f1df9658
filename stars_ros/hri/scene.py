"""The scene the ranker sees, built from tracked people, without ROS.

Every tracked person (one per canonical id: aliases merged) whose frame ``person_<id>`` has a
pose in the robot's ``base_frame`` becomes a human of the scene, unless

* the pose is older than ``max_age`` seconds (``stale``),
* their ``location_confidence`` is below ``min_confidence`` (``low_confidence``; a person
  who never said is kept), or
* there is no pose at all (``no_pose``: the frame never arrived) or only a non-finite one
  (``non_finite``);

a merged person's pose is their own frame's when it is fresh, else the freshest of their
aliases' frames;

each left-out person is counted by that reason (the bridge reports the counts on
/diagnostics). Interactions: every two members of a group (``/humans/interactions/groups``)
and every two people who gaze at each other (``/humans/interactions/gazing`` both ways), each
fact kept for ``max_age`` seconds. Objects and the room are fixed, in ``base_frame``
(parameters). The scene's ids carry no ROS4HRI id: objects are 1..k, then humans in the
order of their ids, so nothing in a scene names a person.

The scene goes to the ranker in SocNav1 format through ``data.frames.to_socnav``, the one
conversion between REP 103 metres and that format. Candidates: ``placements`` > 0 ranks that
many robot placements (``data.scene_source.PLACEMENTS``: stay, 50 cm left, right, back,
ahead, then 100 cm left, right, back, in the robot's frame), else the model's actions.
"""
from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field
from typing import Callable

from stars_ros.data import frames
from stars_ros.data import scene_source
from stars_ros.data.scene_source import PLACEMENTS
from stars_ros.hri.people import People
from stars_ros.hri.poses import Pose, PoseSource

LEFT_OUT_REASONS = ('stale', 'low_confidence', 'no_pose', 'non_finite')
DEFAULT_ROOM = ((5.0, 5.0), (-5.0, 5.0), (-5.0, -5.0), (5.0, -5.0), (5.0, 5.0))  # 10 m square around the robot


def person_frame(person_id: str) -> str:
    """The TF frame REP 155 gives a person."""
    return f'person_{person_id}'


def placement_offset(label: str) -> tuple:
    """(x, y) metres (REP 103, robot's frame) of placement ``label`` of ``PLACEMENTS``."""
    for name, dx, dy in PLACEMENTS:
        if name == label:
            return frames.to_rep103(dx, dy)
    raise ValueError(f"unknown placement '{label}'; known: {[p[0] for p in PLACEMENTS]}")


@dataclass(frozen=True)
class SceneSettings:
    """How scenes are built (see the module docstring); metres and seconds."""

    base_frame: str = 'base_link'
    max_age: float = 0.5
    min_confidence: float = 0.5
    objects: tuple = ()
    room: tuple = DEFAULT_ROOM
    placements: int = 6

    def __post_init__(self):
        if not self.max_age > 0:
            raise ValueError(f'max_age must be positive, got {self.max_age}')
        if not 0.0 <= self.min_confidence <= 1.0:
            raise ValueError(f'min_confidence must be in [0, 1], got {self.min_confidence}')
        if len(self.room) < 3:
            raise ValueError(f'the room needs at least 3 corners, got {len(self.room)}')
        if not 0 <= self.placements <= len(PLACEMENTS):
            raise ValueError(f'placements must be in 0..{len(PLACEMENTS)}, got {self.placements}')


@dataclass(frozen=True)
class BuiltScene:
    """A scene built now: the REP 103 scene, the ids of the people in it (in entity order,
    for distances and for what changed), the left-out ids by reason, and their positions."""

    scene: frames.Rep103Scene
    people: tuple
    left_out: dict = field(default_factory=dict)
    positions: dict = field(default_factory=dict)

    @property
    def signature(self) -> tuple:
        """What counts as a change of scene: who is in it and who interacts."""
        return self.people, self.scene.interactions


class Interactions:
    """The latest groups and gazes, each fact forgotten ``max_age`` s after its stamp."""

    def __init__(self):
        self._groups: dict[str, tuple] = {}  # group id -> (members, stamp)
        self._gazes: dict[tuple, int] = {}  # (sender, receiver) -> stamp

    def set_group(self, group_id: str, members, stamp: int) -> None:
        members = tuple(dict.fromkeys(str(m) for m in members if str(m)))
        if len(members) < 2:
            self._groups.pop(group_id, None)  # a group that dissolved
        else:
            self._groups[group_id] = (members, stamp)

    def set_gaze(self, sender: str, receiver: str, stamp: int) -> None:
        self._gazes[(sender, receiver)] = stamp
        if len(self._gazes) > 10000:  # bounded: the oldest go
            for key in sorted(self._gazes, key=self._gazes.get)[:5000]:
                del self._gazes[key]

    def pairs(self, now: int, max_age_ns: int, canonical: Callable[[str], str]) -> set:
        """Unordered pairs of canonical ids that interact now."""
        found = set()
        for members, stamp in self._groups.values():
            if now - stamp <= max_age_ns:
                ids = sorted({canonical(m) for m in members})
                found.update((a, b) for k, a in enumerate(ids) for b in ids[k + 1:])
        for (sender, receiver), stamp in self._gazes.items():
            back = self._gazes.get((receiver, sender))
            if back is not None and now - stamp <= max_age_ns and now - back <= max_age_ns:
                a, b = sorted((canonical(sender), canonical(receiver)))
                if a != b:
                    found.add((a, b))
        return found


def build_scene(people: People, poses: PoseSource, interactions: Interactions, settings: SceneSettings,
                now: int) -> BuiltScene:
    """The scene of the people tracked now (see the module docstring)."""
    max_age_ns = int(settings.max_age * 1e9)
    left_out = collections.defaultdict(list)
    kept: dict[str, Pose] = {}
    for canonical, ids in sorted(people.members().items()):
        confidences = [people.get(i).confidence for i in ids if people.get(i).confidence is not None]
        if confidences and max(confidences) < settings.min_confidence:
            left_out['low_confidence'].append(canonical)
            continue
        looked_up = [(i == canonical, p) for i in dict.fromkeys([canonical, *ids])
                     if (p := poses.lookup(settings.base_frame, person_frame(i))) is not None]
        found = [(own, p) for own, p in looked_up if all(math.isfinite(v) for v in (p.x, p.y, p.yaw))]
        if not found:
            left_out['non_finite' if looked_up else 'no_pose'].append(canonical)
            continue
        pose = max(found, key=lambda found_pose: (now - found_pose[1].stamp <= max_age_ns, *found_pose[0:1],
                                                  found_pose[1].stamp))[1]
        if now - pose.stamp > max_age_ns:
            left_out['stale'].append(canonical)
            continue
        kept[canonical] = pose
    first_human = len(settings.objects) + 1
    entity = {person_id: first_human + k for k, person_id in enumerate(kept)}
    humans = tuple(frames.Entity(entity[i], p.x, p.y, p.yaw) for i, p in kept.items())
    objects = tuple(frames.Entity(1 + k, *o) for k, o in enumerate(settings.objects))
    links = []
    for a, b in sorted(interactions.pairs(now, max_age_ns, people.canonical)):
        if a in entity and b in entity:
            links += [(entity[a], entity[b]), (entity[b], entity[a])]
    scene = frames.Rep103Scene(humans=humans, objects=objects, room=tuple(settings.room), interactions=tuple(links))
    return BuiltScene(scene, tuple(kept), dict(left_out), {i: (p.x, p.y) for i, p in kept.items()})


def scene_request(scene_id: str, built: BuiltScene, placements: int, user_id: str | None = None) -> dict:
    """The stars/scene payload (``msg_schemas/scene_request.schema.json``) of a built scene:
    ``placements`` robot placements as candidate scenes, or (0) the model's actions."""
    return scene_source.scene_request(scene_id, frames.to_socnav(built.scene), user_id, placements)
