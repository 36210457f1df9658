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

import math
import re
from dataclasses import dataclass

import numpy as np

from .errors import SceneGraphError

NODE_TYPES = ('robot', 'room', 'human', 'object', 'wall', 'interaction')
GEOMETRY_FEATURES = ('x', 'y', 'distance', 'sin_bearing', 'cos_bearing',
                     'sin_orientation', 'cos_orientation', 'size')
NODE_FEATURES = tuple(f'is_{t}' for t in NODE_TYPES) + GEOMETRY_FEATURES
RELATIONS = ('robot-room', 'robot-human', 'robot-object', 'robot-wall',
             'room-human', 'room-object', 'room-wall',
             'interaction-human', 'interaction-object')
CENTIMETRES_PER_METRE = 100.0
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

    from .messages import validator

    try:
        validator('scene_graph')(scene)
    except fastjsonschema.JsonSchemaValueException as error:
        name = error.name or 'data'
        where = re.sub(r'\[(\d+)\]', r'/\1', name[len('data'):]).replace('.', '/').strip('/') or '<root>'
        detail = error.message[len(name):].strip() if error.message.startswith(name) else error.message
        raise SceneGraphError(f'scene graph invalid at {where}: {detail}') from None


def _entities(items):
    if not items:
        return np.zeros((0, 3)), []
    table = np.array([[e['xPos'], e['yPos'], e['orientation']] for e in items], dtype=np.float64)
    ids = [e['id'] for e in items]
    return table, ids


def _geometry(xy, orientation_rad, size):
    """Geometry columns for points ``xy`` [n, 2] in metres."""
    distance = np.hypot(xy[:, 0], xy[:, 1])
    safe = np.where(distance > 0, distance, 1.0)
    sin_bearing = np.where(distance > 0, xy[:, 0] / safe, 0.0)
    cos_bearing = np.where(distance > 0, xy[:, 1] / safe, 0.0)
    return np.column_stack([xy, distance, sin_bearing, cos_bearing,
                            np.sin(orientation_rad), np.cos(orientation_rad), size])


def featurise(scene: dict, validate: bool = True) -> SceneGraph:
    """Build the typed graph of ``scene``; deterministic for a given input.

    Raises:
        SceneGraphError: the scene breaks the schema, holds non-finite numbers, repeats an
            id or links ids that are not humans or objects of the scene.
    """
    if validate:
        validate_scene(scene)
    humans, human_ids = _entities(scene.get("humans"))
    objects, object_ids = _entities(scene.get("objects"))
    room = np.asarray(scene['room'], dtype=np.float64)
    if not (np.isfinite(humans).all() and np.isfinite(objects).all() and np.isfinite(room).all()):
        raise SceneGraphError('scene graph holds a non-finite number (NaN or infinity)')
    ids = human_ids + object_ids
    if len(set(ids)) != len(ids):
        raise SceneGraphError('scene graph repeats a human or object id')

    if len(room) > 1 and np.array_equal(room[0], room[-1]):
        room = room[:-1]  # closed polygon: the first point is repeated last
    if len(room) < 3:
        raise SceneGraphError('room polygon needs at least 3 distinct points')
    room_m = room / CENTIMETRES_PER_METRE
    wall_start, wall_end = room_m, np.roll(room_m, -1, axis=0)
    wall_vec = wall_end - wall_start
    shoelace = 0.5 * abs(np.dot(room_m[:, 0], np.roll(room_m[:, 1], -1))
                         - np.dot(room_m[:, 1], np.roll(room_m[:, 0], -1)))

    index_of = {entity_id: 2 + k for k, entity_id in enumerate(ids)}
    pairs = set()
    for source, target, _ in scene.get('links') or []:
        if source not in index_of or target not in index_of:
            raise SceneGraphError(f'link [{source}, {target}] refers to an id that is not a human or object')
        if source != target:
            pairs.add((min(source, target), max(source, target)))
    pairs = sorted(pairs)

    n_h, n_o, n_w, n_i = len(humans), len(objects), len(room_m), len(pairs)
    counts = (1, 1, n_h, n_o, n_w, n_i)
    node_type = np.repeat(np.arange(len(NODE_TYPES)), counts)

    entity_xy = np.concatenate([humans[:, :2], objects[:, :2]]) / CENTIMETRES_PER_METRE
    entity_orientation = np.radians(np.concatenate([humans[:, 2], objects[:, 2]]))
    if n_i:
        a = entity_xy[[index_of[p[0]] - 2 for p in pairs]]
        b = entity_xy[[index_of[p[1]] - 2 for p in pairs]]
        link_vec = b - a
        interaction_xy = (a + b) / 2
    else:
        link_vec = interaction_xy = np.zeros((0, 2))

    geometry = np.concatenate([
        np.zeros((1, len(GEOMETRY_FEATURES))) + _robot_geometry(),
        _geometry(room_m.mean(axis=0, keepdims=True), np.zeros(1), np.array([math.sqrt(shoelace)])),
        _geometry(entity_xy, entity_orientation, np.zeros(n_h + n_o)),
        _geometry((wall_start + wall_end) / 2, np.arctan2(wall_vec[:, 0], wall_vec[:, 1]),
                  np.hypot(wall_vec[:, 0], wall_vec[:, 1])),
        _geometry(interaction_xy, np.arctan2(link_vec[:, 0], link_vec[:, 1]),
                  np.hypot(link_vec[:, 0], link_vec[:, 1])),
    ])
    x = np.concatenate([np.eye(len(NODE_TYPES))[node_type], geometry], axis=1).astype(np.float32)

    human_nodes = np.arange(2, 2 + n_h)
    object_nodes = np.arange(2 + n_h, 2 + n_h + n_o)
    wall_nodes = np.arange(2 + n_h + n_o, 2 + n_h + n_o + n_w)
    interaction_nodes = np.arange(2 + n_h + n_o + n_w, 2 + n_h + n_o + n_w + n_i)
    is_object = set(object_ids)
    links_h = [(interaction_nodes[k], index_of[e]) for k, p in enumerate(pairs) for e in p if e not in is_object]
    links_o = [(interaction_nodes[k], index_of[e]) for k, p in enumerate(pairs) for e in p if e in is_object]
    groups = [
        ([0], [1]),
        (np.zeros(n_h, int), human_nodes), (np.zeros(n_o, int), object_nodes), (np.zeros(n_w, int), wall_nodes),
        (np.ones(n_h, int), human_nodes), (np.ones(n_o, int), object_nodes), (np.ones(n_w, int), wall_nodes),
        tuple(np.array(links_h, dtype=int).reshape(-1, 2).T),
        tuple(np.array(links_o, dtype=int).reshape(-1, 2).T),
    ]
    sources = np.concatenate([np.asarray(g[0], dtype=np.int64) for g in groups])
    targets = np.concatenate([np.asarray(g[1], dtype=np.int64) for g in groups])
    types = np.repeat(np.arange(len(RELATIONS)), [len(g[0]) for g in groups])
    edge_index = np.stack([np.concatenate([sources, targets]), np.concatenate([targets, sources])])
    edge_type = np.concatenate([types, types])
    return SceneGraph(x=x, edge_index=edge_index, edge_type=edge_type)


def _robot_geometry():
    """The robot sits at the origin facing +y: orientation 0, no bearing, no size."""
    row = np.zeros(len(GEOMETRY_FEATURES))
    row[GEOMETRY_FEATURES.index('cos_orientation')] = 1.0
    return row
