"""Turn a JSON scene (SocNav1 line format) into a typed graph for the GNN encoders.

Nodes, in this order: robot (always index 0), room, humans, objects, walls (one per
segment of the room polygon) and interactions (one per unordered ``interact`` pair).

Node features (``NODE_FEATURES``), all in the robot's frame (origin at the robot, +y ahead):

* one-hot node type (6 columns);
* ``x``, ``y``: position in metres (SocNav1 stores centimetres; walls and interactions
  use their mid-point, the room its vertex centroid);
* ``distance``: distance to the robot in metres;
* ``sin_bearing``, ``cos_bearing``: direction of the position seen from the robot, measured
  from straight ahead (+y); zero for the robot itself;
* ``sin_orientation``, ``cos_orientation``: heading of humans and objects (degrees in the
  JSON), direction of a wall segment, direction from one interactant to the other;
* ``size``: wall length (m), square root of the room's area (m), distance between the two
  interactants (m); 0 for the robot, humans and objects.

Edges are typed (``RELATIONS``) and stored in both directions with the same type, so
relational encoders (RGCN) see what links what.
"""
from __future__ import annotations

import functools
import math
import re
from dataclasses import dataclass

import numpy as np

from stars_ros.errors import SceneGraphError

NODE_TYPES = ('robot', 'room', 'human', 'object', 'wall', 'interaction')
GEOMETRY_FEATURES = ('x', 'y', 'distance', 'sin_bearing', 'cos_bearing',
                     'sin_orientation', 'cos_orientation', 'size')
NODE_FEATURES = tuple(f'is_{t}' for t in NODE_TYPES) + GEOMETRY_FEATURES
RELATIONS = ('robot-room', 'robot-human', 'robot-object', 'robot-wall',
             'room-human', 'room-object', 'room-wall',
             'interaction-human', 'interaction-object')
CENTIMETRES_PER_METRE = 100.0
TOPOLOGIES_KEPT = 256  # scene layouts whose edges featurise keeps
FEATURISER_VERSION = 1  # bump whenever features or edges change: it keys the feature cache


@dataclass(frozen=True)
class SceneGraph:
    """A featurised scene: ``x`` [nodes, features], ``edge_index`` [2, edges], ``edge_type`` [edges]."""

    x: np.ndarray
    edge_index: np.ndarray
    edge_type: np.ndarray

    @property
    def num_nodes(self) -> int:
        return self.x.shape[0]


def validate_scene(scene) -> None:
    """Raise SceneGraphError naming the first place where ``scene`` breaks the schema.

    Uses the compiled validator the node uses for its messages (same schema file, about
    40x faster than jsonschema), so featurisation adds little to a request's latency.
    """
    import fastjsonschema

    from stars_ros.messages import validator

    try:
        validator('scene_graph')(scene)
    except fastjsonschema.JsonSchemaValueException as error:
        name = error.name or 'data'
        where = re.sub(r'\[(\d+)\]', r'/\1', name[len('data'):]).replace('.', '/').strip('/') or '<root>'
        detail = error.message[len(name):].strip() if error.message.startswith(name) else error.message
        raise SceneGraphError(f'scene graph invalid at {where}: {detail}') from None


def _geometry_row(x: float, y: float, orientation: float, size: float) -> list:
    """Geometry columns of a point (x, y) in metres, as ``GEOMETRY_FEATURES``."""
    distance = math.hypot(x, y)
    if distance > 0:
        return [x, y, distance, x / distance, y / distance, math.sin(orientation), math.cos(orientation), size]
    return [x, y, 0.0, 0.0, 0.0, math.sin(orientation), math.cos(orientation), size]


def _checked_entities(items) -> list:
    """(id, x m, y m, orientation rad) of the humans or objects of a scene."""
    entities = []
    for entity in items or ():
        values = (entity['xPos'], entity['yPos'], entity['orientation'])
        if not all(math.isfinite(v) for v in values):
            raise SceneGraphError('scene graph holds a non-finite number (NaN or infinity)')
        entities.append((entity['id'], values[0] / CENTIMETRES_PER_METRE, values[1] / CENTIMETRES_PER_METRE,
                         math.radians(values[2])))
    return entities


def featurise(scene: dict, validate: bool = True) -> SceneGraph:
    """Build the typed graph of ``scene``; deterministic for a given input.

    Plain Python over the few dozen nodes of a scene, one array at the end: numpy's fixed
    cost per call made a vectorised version several times slower at this size.

    Raises:
        SceneGraphError: the scene breaks the schema, holds non-finite numbers, repeats an
            id or links ids that are not humans or objects of the scene.
    """
    if validate:
        validate_scene(scene)
    humans = _checked_entities(scene.get('humans'))
    objects = _checked_entities(scene.get('objects'))
    room = [(float(x), float(y)) for x, y in scene['room']]
    if not all(math.isfinite(x) and math.isfinite(y) for x, y in room):
        raise SceneGraphError('scene graph holds a non-finite number (NaN or infinity)')
    ids = [e[0] for e in humans] + [e[0] for e in objects]
    if len(set(ids)) != len(ids):
        raise SceneGraphError('scene graph repeats a human or object id')
    if len(room) > 1 and room[0] == room[-1]:
        room = room[:-1]  # closed polygon: the first point is repeated last
    if len(room) < 3:
        raise SceneGraphError('room polygon needs at least 3 distinct points')
    room = [(x / CENTIMETRES_PER_METRE, y / CENTIMETRES_PER_METRE) for x, y in room]

    index_of = {entity_id: 2 + k for k, entity_id in enumerate(ids)}
    pairs = set()
    for source, target, _ in scene.get('links') or []:
        if source not in index_of or target not in index_of:
            raise SceneGraphError(f'link [{source}, {target}] refers to an id that is not a human or object')
        if source != target:
            pairs.add((min(source, target), max(source, target)))
    pairs = sorted(pairs)

    n_h, n_o, n_w = len(humans), len(objects), len(room)
    area = 0.5 * abs(sum(x0 * y1 - y0 * x1 for (x0, y0), (x1, y1) in zip(room, room[1:] + room[:1])))
    geometry = [[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0],  # the robot: origin, facing +y
                _geometry_row(sum(x for x, _ in room) / n_w, sum(y for _, y in room) / n_w, 0.0, math.sqrt(area))]
    geometry += [_geometry_row(x, y, orientation, 0.0) for _, x, y, orientation in humans + objects]
    for (x0, y0), (x1, y1) in zip(room, room[1:] + room[:1]):
        dx, dy = x1 - x0, y1 - y0
        geometry.append(_geometry_row((x0 + x1) / 2, (y0 + y1) / 2, math.atan2(dx, dy), math.hypot(dx, dy)))
    entities = humans + objects
    for first, second in pairs:
        _, xa, ya, _ = entities[index_of[first] - 2]
        _, xb, yb, _ = entities[index_of[second] - 2]
        dx, dy = xb - xa, yb - ya
        geometry.append(_geometry_row((xa + xb) / 2, (ya + yb) / 2, math.atan2(dx, dy), math.hypot(dx, dy)))
    one_hot, edge_index, edge_type = _topology(n_h, n_o, n_w, tuple((index_of[a], index_of[b]) for a, b in pairs))
    x = one_hot.copy()
    x[:, len(NODE_TYPES):] = geometry
    return SceneGraph(x=x, edge_index=edge_index.copy(), edge_type=edge_type.copy())


@functools.lru_cache(maxsize=TOPOLOGIES_KEPT)
def _topology(n_h: int, n_o: int, n_w: int, pairs: tuple) -> tuple:
    """(x [nodes, features], only its one-hot types set; edge_index; edge_type) of a scene
    of ``n_h`` humans, ``n_o`` objects, ``n_w`` walls and interactions ``pairs`` (node
    indices): what ``featurise`` gives every scene of that layout. Kept, since a robot's
    scenes change their positions far more often than who is in them; callers copy."""
    n_i = len(pairs)
    counts = (1, 1, n_h, n_o, n_w, n_i)
    x = np.zeros((sum(counts), len(NODE_FEATURES)), dtype=np.float32)
    x[np.arange(len(x)), np.repeat(np.arange(len(NODE_TYPES)), counts)] = 1.0
    first_h, first_o, first_w, first_i = 2, 2 + n_h, 2 + n_h + n_o, 2 + n_h + n_o + n_w
    humans_, objects_, walls = range(first_h, first_o), range(first_o, first_w), range(first_w, first_i)
    links_h = [(first_i + k, n) for k, pair in enumerate(pairs) for n in pair if n < first_o]
    links_o = [(first_i + k, n) for k, pair in enumerate(pairs) for n in pair if n >= first_o]
    groups = [[(0, 1)], [(0, n) for n in humans_], [(0, n) for n in objects_], [(0, n) for n in walls],
              [(1, n) for n in humans_], [(1, n) for n in objects_], [(1, n) for n in walls], links_h, links_o]
    forward = [edge for group in groups for edge in group]
    types = [relation for relation, group in enumerate(groups) for _ in group]
    edges = np.array(forward, dtype=np.int64).reshape(-1, 2).T
    return x, np.concatenate([edges, edges[::-1]], axis=1), np.array(types + types, dtype=np.int64)


def entity_nodes(scene: dict) -> list:
    """(id, kind, node index) of each removable entity of ``scene`` in ``featurise``'s node
    order: the room ('room'), humans and objects (their own ids), walls ('wall-k', segment k
    of the polygon) and interactions ('a-b', the sorted pair). The robot is not one: it is
    where the scene is seen from."""
    humans = [entity['id'] for entity in scene.get('humans') or ()]
    objects = [entity['id'] for entity in scene.get('objects') or ()]
    room = [tuple(point) for point in scene['room']]
    walls = len(room) - 1 if len(room) > 1 and room[0] == room[-1] else len(room)
    pairs = sorted({(min(s, t), max(s, t)) for s, t, _ in scene.get('links') or () if s != t})
    entities = [('room', 'room')] + [(i, 'human') for i in humans] + [(i, 'object') for i in objects]
    entities += [(f'wall-{k}', 'wall') for k in range(walls)] + [(f'{a}-{b}', 'interaction') for a, b in pairs]
    return [(entity_id, kind, node) for node, (entity_id, kind) in enumerate(entities, 1)]


def without_node(graph: SceneGraph, node: int) -> SceneGraph:
    """``graph`` with ``node`` and every edge touching it removed (later nodes move up one)."""
    keep = (graph.edge_index != node).all(axis=0)
    edge_index = graph.edge_index[:, keep]
    return SceneGraph(x=np.delete(graph.x, node, axis=0), edge_index=edge_index - (edge_index > node),
                      edge_type=graph.edge_type[keep])
