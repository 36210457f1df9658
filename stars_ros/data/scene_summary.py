"""A fixed summary of a scene graph as a short feature row, for models that take a feature
vector rather than a graph (the myFM peer of ``evaluation.peers``).

Read off the featurised graph (``scene_graph``: robot's frame, metres, +y ahead), so it is
the same for every scene source. The columns (``SUMMARY_FEATURES``):

* ``humans``, ``objects``, ``walls``, ``interactions``: how many of each;
* ``nearest_human_distance`` (m), ``nearest_human_sin_bearing``, ``nearest_human_cos_bearing``
  (its direction from straight ahead): of the human nearest the robot;
* ``nearest_human_sin_orientation``, ``nearest_human_cos_orientation``: that human's heading
  (the JSON's ``orientation``, as the graph keeps it);
* ``nearest_object_distance`` (m), ``nearest_wall_distance`` (m, to a segment's mid-point);
* ``room_size``: the square root of the room's area (m).

A scene without humans (objects, walls) takes ``ABSENT_DISTANCE`` as the nearest distance and
zeros for the bearing and heading, so the count column says it is absent.
"""
from __future__ import annotations

import numpy as np

from stars_ros.data.scene_graph import NODE_FEATURES

SUMMARY_FEATURES = ('humans', 'objects', 'walls', 'interactions', 'nearest_human_distance',
                    'nearest_human_sin_bearing', 'nearest_human_cos_bearing', 'nearest_human_sin_orientation',
                    'nearest_human_cos_orientation',
                    'nearest_object_distance', 'nearest_wall_distance', 'room_size')
ABSENT_DISTANCE = 10.0  # metres: further than anything in a SocNav1 room
_COLUMN = {name: index for index, name in enumerate(NODE_FEATURES)}


def _of_type(x: np.ndarray, node_type: str) -> np.ndarray:
    return x[x[:, _COLUMN[f'is_{node_type}']] > 0.5]


def _nearest(nodes: np.ndarray):
    """The row of ``nodes`` nearest the robot, or None."""
    return None if len(nodes) == 0 else nodes[int(np.argmin(nodes[:, _COLUMN['distance']]))]


def summarise(x: np.ndarray) -> np.ndarray:
    """SUMMARY_FEATURES of one featurised scene graph's node features ``x`` [nodes, features]."""
    counts = [len(_of_type(x, t)) for t in ('human', 'object', 'wall', 'interaction')]
    human = _nearest(_of_type(x, 'human'))
    if human is None:
        human_part = [ABSENT_DISTANCE, 0.0, 0.0, 0.0, 0.0]
    else:
        human_part = [human[_COLUMN[name]] for name in ('distance', 'sin_bearing', 'cos_bearing', 'sin_orientation',
                                                         'cos_orientation')]
    distances = []
    for node_type in ('object', 'wall'):
        nearest = _nearest(_of_type(x, node_type))
        distances.append(ABSENT_DISTANCE if nearest is None else nearest[_COLUMN['distance']])
    rooms = _of_type(x, 'room')
    room_size = float(rooms[0, _COLUMN['size']]) if len(rooms) else 0.0
    return np.array([*counts, *human_part, *distances, room_size], dtype=np.float64)


def summarise_store(store) -> np.ndarray:
    """[scenes, len(SUMMARY_FEATURES)]: ``summarise`` of every scene of a GraphStore."""
    return np.stack([summarise(store.scene(i).x) for i in range(len(store))]) if len(store) else \
        np.zeros((0, len(SUMMARY_FEATURES)))

