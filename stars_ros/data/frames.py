"""The one conversion between the scene format (SocNav1) and REP 103.

SocNav1 scenes are in the robot's frame in centimetres with +y ahead and +x to the robot's
right (``docs/explanations.md``, "Scenes you can look at"); REP 103 is metres, x forward,
y left, z up. So a point (x, y) cm is (y / 100, −x / 100) m, and a heading of θ degrees
(SocNav1 faces (sin θ, −cos θ), so θ = 0 faces the robot) is the yaw θ + 180° in ROS.

The markers, the figures, the typed ROS interface and the ROS4HRI bridge all convert here,
so a scene drawn, ranked or built from tracked people means the same everywhere.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from stars_ros.data.scene_graph import CENTIMETRES_PER_METRE


def to_rep103(x_cm: float, y_cm: float) -> tuple:
    """A SocNav1 point (cm, +y ahead, +x right) in REP 103 metres (x forward, y left)."""
    return y_cm / CENTIMETRES_PER_METRE, -x_cm / CENTIMETRES_PER_METRE


def from_rep103(x_m: float, y_m: float) -> tuple:
    """A REP 103 point (metres, x forward, y left) in SocNav1 centimetres (+y ahead, +x right)."""
    return -y_m * CENTIMETRES_PER_METRE, x_m * CENTIMETRES_PER_METRE


def heading_yaw(degrees: float) -> float:
    """A SocNav1 orientation (degrees; the entity faces (sin θ, −cos θ)) as a REP 103 yaw in (−π, π]."""
    yaw = math.radians(degrees) + math.pi
    return math.atan2(math.sin(yaw), math.cos(yaw))


def yaw_heading(yaw: float) -> float:
    """A REP 103 yaw (radians) as a SocNav1 orientation in degrees, in (−180, 180]."""
    degrees = math.degrees(yaw) - 180.0
    return -((180.0 - degrees) % 360.0 - 180.0)


class Entity(NamedTuple):
    """A human or an object in REP 103: ``x``, ``y`` in metres, ``yaw`` in radians (a
    tuple: a typed request builds one per person, and a frozen dataclass took twice as long)."""

    id: int
    x: float
    y: float
    yaw: float = 0.0


@dataclass(frozen=True)
class Rep103Scene:
    """A scene in the robot's REP 103 frame: ``room`` a polygon of (x, y) metres (its
    consecutive points are the walls), ``interactions`` pairs of entity ids (human–human or
    human–object) that interact."""

    humans: tuple = ()
    objects: tuple = ()
    room: tuple = ()
    interactions: tuple = field(default_factory=tuple)


def to_socnav(scene: Rep103Scene, identifier: str | None = None) -> dict:
    """The SocNav1 scene dict (``msg_schemas/scene_graph.schema.json``) of a REP 103 scene."""
    def entity(e: Entity) -> dict:
        x, y = from_rep103(e.x, e.y)
        return {'id': int(e.id), 'xPos': x, 'yPos': y, 'orientation': yaw_heading(e.yaw)}
    out = {'humans': [entity(h) for h in scene.humans], 'objects': [entity(o) for o in scene.objects],
           'links': [[int(a), int(b), 'interact'] for a, b in scene.interactions],
           'room': [list(from_rep103(x, y)) for x, y in scene.room]}
    if identifier is not None:
        out['identifier'] = identifier
    return out


def from_socnav(scene: dict) -> Rep103Scene:
    """The REP 103 scene of a SocNav1 scene dict (inverse of ``to_socnav``)."""
    def entity(e: dict) -> Entity:
        return Entity(int(e['id']), *to_rep103(e['xPos'], e['yPos']), heading_yaw(e['orientation']))
    return Rep103Scene(humans=tuple(entity(h) for h in scene.get('humans') or ()),
                       objects=tuple(entity(o) for o in scene.get('objects') or ()),
                       room=tuple(to_rep103(*p) for p in scene.get('room') or ()),
                       interactions=tuple((int(a), int(b)) for a, b, *_ in scene.get('links') or ()))


def robot_pose_in(reference: dict, scene: dict) -> tuple:
    """(x cm, y cm, rotation rad) of ``scene``'s robot in ``reference``'s frame (SocNav1 axes):
    the least-squares rigid motion carrying the points both share (humans and objects by id,
    room corners by index when both rooms have as many) from ``scene`` onto ``reference``.
    With one shared point it is a shift; with none, the robot is where the reference's is."""
    def points(s):
        found = {('e', e['id']): (e['xPos'], e['yPos']) for e in (s.get('humans') or []) + (s.get('objects') or [])}
        if len(s['room']) == len(reference['room']):
            found.update({('r', k): tuple(p) for k, p in enumerate(s['room'])})
        return found
    ours, theirs = points(scene), points(reference)
    shared = [k for k in ours if k in theirs]
    if not shared:
        return 0.0, 0.0, 0.0
    a = np.array([ours[k] for k in shared], dtype=np.float64)
    b = np.array([theirs[k] for k in shared], dtype=np.float64)
    ca, cb = a.mean(0), b.mean(0)
    rotation = 0.0
    if len(shared) > 1:
        m = (a - ca).T @ (b - cb)
        rotation = math.atan2(m[0, 1] - m[1, 0], m[0, 0] + m[1, 1])
    c, s = math.cos(rotation), math.sin(rotation)
    shift = cb - np.array([[c, -s], [s, c]]) @ ca
    return float(shift[0]), float(shift[1]), rotation
