"""Robot placements of a scene: as candidate scenes, as one batch for the encoders, and
which of them the robot can take at all.

A placement puts the robot at (x, y) metres of the scene's frame (SocNav1 axes: +x to the
robot's right, +y ahead), keeping its heading, or turned by ``heading`` (radians,
counter-clockwise, REP 103's sense). ``placed_scene`` is the candidate scene the ranker is
given for it (``~/rank_candidates``): ``scene_source.move_robot`` of the shift, which moves
everything the other way and rounds positions to hundredths of a centimetre; with a heading,
everything also turns the other way about the robot (orientations too).

``featurise_placements`` gives what ``featurise`` gives each placed scene, for many
placements at once: the scene's layout (nodes, edges) is every placement's, so only the
geometry columns change, computed as arrays over the placements, the rounding included
(``hundredths``: Python's ``round(v, 2)``, to the bit).

``valid_placements``: inside the room, and not inside a person, an object or a wall. SocNav1's
scene generator (gnns4hri/SocNav1) made a person a 40 × 20 cm shape and an object a 40 × 40 cm
square; their covering discs are the footprints here. Walls are segments in the data: a wall
is taken to be ``WALL_THICKNESS`` thick.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from stars_ros.data.scene_graph import CENTIMETRES_PER_METRE, NODE_TYPES, SceneGraph, featurise
from stars_ros.data.scene_source import move_robot
from stars_ros.errors import SceneGraphError

PERSON_RADIUS = 0.20  # m: covers the generator's 40 × 20 cm person
OBJECT_RADIUS = 0.20 * math.sqrt(2.0)  # m: covers its 40 × 40 cm object
WALL_THICKNESS = 0.10  # m
COORDINATE_LIMIT = 100000  # cm: msg_schemas/scene_graph.schema.json's bound on a placed scene's numbers


@dataclass(frozen=True)
class SceneBatch(Sequence):
    """Scenes of one layout: features ``x`` [scenes, nodes, features] over one ``edge_index``
    [2, edges] and ``edge_type`` [edges]. A sequence of their ``SceneGraph`` for encoders
    that take scenes one by one; ``stacked`` for those that take them side by side."""

    x: np.ndarray
    edge_index: np.ndarray
    edge_type: np.ndarray

    def __len__(self) -> int:
        return self.x.shape[0]

    def __getitem__(self, k: int) -> SceneGraph:
        return SceneGraph(self.x[k], self.edge_index, self.edge_type)

    def stacked(self) -> tuple:
        """(x [scenes × nodes, features], node_starts [scenes + 1], edge_index [2, scenes × edges]):
        the scenes as one disjoint graph, scene after scene, as ``compiled_gat`` stacks a list."""
        scenes, nodes, features = self.x.shape
        starts = np.arange(scenes + 1, dtype=np.int64) * nodes
        edges = (self.edge_index[:, None, :] + starts[None, :-1, None]).reshape(2, -1)
        return self.x.reshape(scenes * nodes, features), starts, edges


def hundredths(values) -> np.ndarray:
    """Python's ``round(v, 2)`` of each of ``values`` (float64), to the bit: v·100 rounded to
    the nearest integer, ties to even, decided on the exact product (its rounding error found
    by Dekker's split), divided by 100."""
    values = np.asarray(values, dtype=np.float64)
    scaled = values * 100.0
    split = values * 134217729.0  # 2^27 + 1: high keeps the upper 26 bits of each value
    high = split - (split - values)
    error = (high * 100.0 - scaled) + (values - high) * 100.0  # values·100 = scaled + error, exactly
    nearest = np.rint(scaled)
    tie = (np.abs(scaled - nearest) == 0.5) & (error != 0.0)  # not a tie once the error is counted
    return np.where(tie, np.floor(scaled) + (error > 0.0), nearest) / 100.0


def _placed(x, y, dx, dy, heading: float | None) -> tuple:
    """Points (x, y) cm seen from the robot placed at (dx, dy) cm and turned by ``heading``."""
    u, v = x - dx, y - dy
    if heading is not None:
        c, s = math.cos(heading), math.sin(heading)
        u, v = c * u + s * v, c * v - s * u
    return hundredths(u), hundredths(v)


def placed_scene(scene: dict, x: float, y: float, heading: float | None = None) -> dict:
    """The candidate scene of the robot placed at (``x``, ``y``) metres (see the module docstring)."""
    dx, dy = x * CENTIMETRES_PER_METRE, y * CENTIMETRES_PER_METRE
    if heading is None:
        return move_robot(scene, dx, dy)
    turn = math.degrees(heading)
    out = {k: v for k, v in scene.items() if k not in ('identifier', 'score')}
    for key in ('humans', 'objects'):
        entities = scene.get(key) or []
        px, py = _placed(np.array([e['xPos'] for e in entities], dtype=np.float64),
                         np.array([e['yPos'] for e in entities], dtype=np.float64), dx, dy, heading)
        out[key] = [{**e, 'xPos': float(u), 'yPos': float(v), 'orientation': e['orientation'] - turn}
                    for e, u, v in zip(entities, px, py)]
    room = np.array(scene['room'], dtype=np.float64)
    out['room'] = [[float(u), float(v)] for u, v in zip(*_placed(room[:, 0], room[:, 1], dx, dy, heading))]
    return out


def _geometry(x, y, sin_o, cos_o, size) -> np.ndarray:
    """``scene_graph.GEOMETRY_FEATURES`` [placements, points, 8] of points (x, y) m [placements, points]."""
    distance = np.hypot(x, y)
    away = distance > 0
    safe = np.where(away, distance, 1.0)
    bearing = np.where(away, x / safe, 0.0), np.where(away, y / safe, 0.0)
    columns = np.broadcast_arrays(x, y, distance, *bearing, sin_o, cos_o, size)
    return np.stack(columns, axis=-1)


def _segments(ax, ay, bx, by) -> np.ndarray:
    """Geometry of the segments a → b (walls, interactions): mid-point, direction, length."""
    dx, dy = bx - ax, by - ay
    direction = np.arctan2(dx, dy)
    return _geometry((ax + bx) / 2, (ay + by) / 2, np.sin(direction), np.cos(direction), np.hypot(dx, dy))


def _room_points(scene: dict) -> np.ndarray:
    """The room polygon [points, 2] cm as ``featurise`` reads it (a closing point dropped)."""
    room = [(float(x), float(y)) for x, y in scene['room']]
    return np.array(room[:-1] if len(room) > 1 and room[0] == room[-1] else room)


def featurise_placements(scene: dict, x, y, heading: float | None = None) -> SceneBatch:
    """``featurise(placed_scene(scene, x[k], y[k], heading))`` for every k of ``x``, ``y``
    (metres), as one ``SceneBatch``. SceneGraphError as ``featurise`` raises it, or for
    placements that move a number beyond the schema's bound."""
    layout = featurise(scene)
    dx = np.asarray(x, dtype=np.float64)[:, None] * CENTIMETRES_PER_METRE
    dy = np.asarray(y, dtype=np.float64)[:, None] * CENTIMETRES_PER_METRE
    entities = list(scene.get('humans') or ()) + list(scene.get('objects') or ())
    ex, ey, orientation = (np.array([e[key] for e in entities], dtype=np.float64)
                           for key in ('xPos', 'yPos', 'orientation'))
    if heading is not None:
        orientation = orientation - math.degrees(heading)
    room = _room_points(scene)
    px, py = _placed(ex, ey, dx, dy, heading)
    rx, ry = _placed(room[:, 0], room[:, 1], dx, dy, heading)
    if max(np.abs(v).max(initial=0.0) for v in (px, py, rx, ry, orientation)) > COORDINATE_LIMIT:
        raise SceneGraphError(f"a placement moves a number beyond the schema's ±{COORDINATE_LIMIT}")
    px, py, rx, ry = (v / CENTIMETRES_PER_METRE for v in (px, py, rx, ry))
    sum_x, sum_y, twice_area = 0.0, 0.0, 0.0  # summed in featurise's order: point after point
    for k in range(room.shape[0]):
        sum_x, sum_y = sum_x + rx[:, k], sum_y + ry[:, k]
        following = (k + 1) % room.shape[0]
        twice_area = twice_area + (rx[:, k] * ry[:, following] - ry[:, k] * rx[:, following])
    walls = room.shape[0]
    blocks = [_geometry(sum_x[:, None] / walls, sum_y[:, None] / walls, 0.0, 1.0,
                        np.sqrt(0.5 * np.abs(twice_area))[:, None])]
    radians = np.radians(orientation)
    blocks.append(_geometry(px, py, np.sin(radians), np.cos(radians), 0.0))
    blocks.append(_segments(rx, ry, np.roll(rx, -1, axis=1), np.roll(ry, -1, axis=1)))
    index = {e['id']: k for k, e in enumerate(entities)}
    pairs = sorted({(min(s, t), max(s, t)) for s, t, _ in scene.get('links') or () if s != t})
    if pairs:
        a, b = np.array([index[p] for p, _ in pairs]), np.array([index[q] for _, q in pairs])
        blocks.append(_segments(px[:, a], py[:, a], px[:, b], py[:, b]))
    features = np.empty((len(dx), *layout.x.shape), dtype=np.float32)
    features[:] = layout.x
    features[:, 1:, len(NODE_TYPES):] = np.concatenate(blocks, axis=1)
    return SceneBatch(features, layout.edge_index, layout.edge_type)


def _inside(polygon: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Whether points (x, y) lie inside ``polygon`` [points, 2] (even–odd rule)."""
    inside = np.zeros(x.shape, dtype=bool)
    for (x0, y0), (x1, y1) in zip(polygon, np.roll(polygon, -1, axis=0)):
        if y0 == y1:
            continue  # a horizontal edge crosses no horizontal ray
        crosses = (y0 > y) != (y1 > y)
        inside ^= crosses & (x < x0 + (y - y0) * (x1 - x0) / (y1 - y0))
    return inside


def _segment_distance(polygon: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Distance from points (x, y) to the nearest edge of the closed ``polygon`` [points, 2]."""
    nearest = np.full(x.shape, np.inf)
    for (x0, y0), (x1, y1) in zip(polygon, np.roll(polygon, -1, axis=0)):
        dx, dy = x1 - x0, y1 - y0
        length = dx * dx + dy * dy
        t = np.clip(((x - x0) * dx + (y - y0) * dy) / length, 0.0, 1.0) if length > 0 else 0.0
        nearest = np.minimum(nearest, np.hypot(x - (x0 + t * dx), y - (y0 + t * dy)))
    return nearest


def valid_placements(scene: dict, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Whether the robot can be placed at each (x, y) metres: inside the room, at least
    ``WALL_THICKNESS`` / 2 from every wall, ``PERSON_RADIUS`` from every person's centre and
    ``OBJECT_RADIUS`` from every object's."""
    room = _room_points(scene) / CENTIMETRES_PER_METRE
    valid = _inside(room, x, y) & (_segment_distance(room, x, y) >= WALL_THICKNESS / 2)
    for key, radius in (('humans', PERSON_RADIUS), ('objects', OBJECT_RADIUS)):
        for entity in scene.get(key) or ():
            cx, cy = entity['xPos'] / CENTIMETRES_PER_METRE, entity['yPos'] / CENTIMETRES_PER_METRE
            valid &= np.hypot(x - cx, y - cy) >= radius
    return valid
