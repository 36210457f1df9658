import json
import math

import numpy as np
import pytest

from stars_ros.errors import SceneGraphError
from stars_ros.data.scene_graph import NODE_FEATURES, NODE_TYPES, RELATIONS, featurise, validate_scene

SQUARE_ROOM = [[-200, -200], [200, -200], [200, 400], [-200, 400], [-200, -200]]


def scene(**changes):
    base = {'identifier': 't', 'score': 50, 'robot': {'id': 0},
            'humans': [{'id': 1, 'xPos': 100, 'yPos': 0, 'orientation': 90},
                       {'id': 2, 'xPos': 0, 'yPos': 200, 'orientation': 180}],
            'objects': [{'id': 3, 'xPos': -100, 'yPos': 100, 'orientation': 0}],
            'links': [[1, 2, 'interact'], [2, 1, 'interact'], [2, 3, 'interact']],
            'room': SQUARE_ROOM}
    base.update(changes)
    return base


def column(name):
    return NODE_FEATURES.index(name)


def test_nodes_in_documented_order_with_one_hot_types():
    graph = featurise(scene())
    # robot, room, 2 humans, 1 object, 4 walls (closed polygon), 2 interactions (1-2 deduplicated, 2-3)
    expected = ['robot', 'room', 'human', 'human', 'object'] + ['wall'] * 4 + ['interaction'] * 2
    types = [NODE_TYPES[k] for k in graph.x[:, :len(NODE_TYPES)].argmax(1)]
    assert types == expected
    assert graph.x.shape == (11, len(NODE_FEATURES))


def test_geometry_in_metres_relative_to_robot():
    x = featurise(scene()).x
    human = x[2]  # (100 cm, 0 cm) facing 90 degrees
    assert human[column('x')] == pytest.approx(1.0)
    assert human[column('y')] == pytest.approx(0.0)
    assert human[column('distance')] == pytest.approx(1.0)
    assert human[column('sin_bearing')] == pytest.approx(1.0)   # straight to the right
    assert human[column('cos_bearing')] == pytest.approx(0.0, abs=1e-6)
    assert human[column('sin_orientation')] == pytest.approx(1.0)
    ahead = x[3]  # (0, 200 cm): straight ahead at 2 m
    assert ahead[column('distance')] == pytest.approx(2.0)
    assert ahead[column('cos_bearing')] == pytest.approx(1.0)
    room = x[1]
    assert room[column('size')] == pytest.approx(math.sqrt(4.0 * 6.0))  # 4 m x 6 m room
    first_wall = x[5]  # (-2,-2) -> (2,-2): 4 m long, mid-point (0,-2)
    assert first_wall[column('size')] == pytest.approx(4.0)
    assert first_wall[column('y')] == pytest.approx(-2.0)
    interaction = x[9]  # humans 1 and 2: (1,0) and (0,2)
    assert interaction[column('size')] == pytest.approx(math.sqrt(5))
    assert interaction[column('x')] == pytest.approx(0.5)
    robot = x[0]
    assert robot[column('distance')] == 0 and robot[column('cos_orientation')] == 1


def test_edges_typed_and_symmetric():
    graph = featurise(scene())
    pairs = set(zip(graph.edge_index[0].tolist(), graph.edge_index[1].tolist(), graph.edge_type.tolist()))
    assert all((t, s, r) in pairs for s, t, r in pairs)
    assert (0, 1, RELATIONS.index('robot-room')) in pairs
    assert (9, 2, RELATIONS.index('interaction-human')) in pairs
    assert (10, 4, RELATIONS.index('interaction-object')) in pairs
    assert set(graph.edge_type.tolist()) == set(range(len(RELATIONS)))


def test_featurisation_is_deterministic():
    first, second = featurise(scene()), featurise(json.loads(json.dumps(scene())))
    assert np.array_equal(first.x, second.x)
    assert np.array_equal(first.edge_index, second.edge_index)


def test_a_kept_layout_gives_each_scene_its_own_positions_and_arrays():
    """Scenes of one layout share featurise's kept edges, not its arrays: a scene moved
    gets its own geometry, and changing one graph's arrays changes no later graph."""
    first = featurise(scene())
    moved = scene(humans=[{'id': 1, 'xPos': -50, 'yPos': 300, 'orientation': 10},
                          {'id': 2, 'xPos': 20, 'yPos': 100, 'orientation': -90}])
    second = featurise(moved)
    assert np.array_equal(first.edge_index, second.edge_index) and np.array_equal(first.edge_type, second.edge_type)
    assert second.x[2, column('x')] == pytest.approx(-0.5) and first.x[2, column('x')] == pytest.approx(1.0)
    for graph in (first, second):
        graph.x[:] = 7.0
        graph.edge_index[:] = 0
        graph.edge_type[:] = 0
    again = featurise(scene())
    assert again.x[0, column('cos_orientation')] == 1.0 and again.x[:, :len(NODE_TYPES)].sum() == again.num_nodes
    assert sorted(set(again.edge_type.tolist())) == list(range(len(RELATIONS)))
    def links_of(graph):
        return set(zip(graph.edge_index[0].tolist(), graph.edge_index[1].tolist(), graph.edge_type.tolist()))
    other_pairs = featurise(scene(links=[[1, 3, 'interact'], [2, 3, 'interact']]))  # same counts, other pairs
    object_link = (9, 4, RELATIONS.index('interaction-object'))  # interaction 1-3 (node 9) to the object
    assert object_link in links_of(other_pairs) and object_link not in links_of(again)


def test_open_polygon_and_no_humans_are_fine():
    graph = featurise(scene(room=SQUARE_ROOM[:-1], humans=[], links=[]))
    assert graph.num_nodes == 1 + 1 + 1 + 4  # robot, room, object, walls


def test_unknown_fields_allowed():
    featurise(scene(extra={'anything': 1}, humans=[{'id': 1, 'xPos': 0, 'yPos': 50, 'orientation': 0, 'v': 2}],
                    links=[]))


@pytest.mark.parametrize('bad, message', [
    ({'room': [[0, 0], [1, 1]]}, 'room'),
    ({'humans': [{'id': 1, 'xPos': 0, 'yPos': 0}]}, 'orientation'),
    ({'humans': [{'id': 1, 'xPos': 'far', 'yPos': 0, 'orientation': 0}]}, 'humans/0/xPos'),
    ({'humans': [{'id': k, 'xPos': 0, 'yPos': 0, 'orientation': 0} for k in range(5000)], 'links': []}, 'humans'),
    ({'links': [[1, 2, 'hug']]}, 'links/0/2'),
    ({'humans': [{'id': 1, 'xPos': 1e9, 'yPos': 0, 'orientation': 0}], 'links': []}, 'xPos'),
])
def test_schema_violations_are_named(bad, message):
    with pytest.raises(SceneGraphError, match=message):
        featurise(scene(**bad))


def test_empty_scene_refused():
    with pytest.raises(SceneGraphError, match='humans'):
        validate_scene({})


@pytest.mark.parametrize('bad, message', [
    ({'humans': [{'id': 1, 'xPos': float('nan'), 'yPos': 0, 'orientation': 0}], 'links': []}, 'non-finite'),
    ({'links': [[1, 9, 'interact']]}, 'link'),
    ({'objects': [{'id': 1, 'xPos': 0, 'yPos': 0, 'orientation': 0}]}, 'repeats'),
    ({'room': [[0, 0], [100, 0], [0, 0]]}, '3 distinct'),
])
def test_semantic_errors(bad, message):
    with pytest.raises(SceneGraphError, match=message):
        featurise(scene(**bad))


@pytest.mark.socnav1
def test_every_socnav1_scene_featurises(socnav1):
    # load_dataset featurised every distinct scene; check the store is consistent
    assert len(socnav1.store) == len(socnav1.scene_keys)
    assert np.isfinite(socnav1.store.x.numpy()).all()
    assert int(socnav1.store.node_counts.min()) >= 2 + 3
