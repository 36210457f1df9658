"""Robot placements (stars_ros.data.placements): Python's rounding to the bit, the placed scene
as the ranker's candidate, the batch featurised as featurise gives each placed scene, and the
placements the robot can take, checked by hand."""
import math

import numpy as np
import pytest

from stars_ros.data.placements import (OBJECT_RADIUS, PERSON_RADIUS, WALL_THICKNESS, featurise_placements,
                                       hundredths, placed_scene, valid_placements)
from stars_ros.data.scene_graph import featurise
from stars_ros.data.scene_source import move_robot, random_scene
from stars_ros.errors import SceneGraphError

SCENE = {'humans': [{'id': 1, 'xPos': 0.0, 'yPos': 100.0, 'orientation': 30.0}],
         'objects': [{'id': 2, 'xPos': -150.0, 'yPos': -100.0, 'orientation': 0.0}],
         'links': [[1, 2, 'interact']],
         'room': [[-300, -300], [300, -300], [300, 300], [-300, 300], [-300, -300]]}


def test_hundredths_rounds_as_python_does_to_the_bit():
    rng = np.random.default_rng(0)
    near_ties = rng.integers(-10**7, 10**7, 20000) / 1000 + 0.005
    known = np.array([2.675, 0.125, 0.375, 1.005, -2.675, -0.125, 0.0, -0.0, 1e-9, 99999.995])
    values = np.concatenate([rng.uniform(-1e5, 1e5, 20000), near_ties, known])
    ours = hundredths(values)
    assert [float(v) for v in ours] == [round(float(v), 2) for v in values]


def test_a_placement_keeping_the_heading_is_the_rankers_moved_robot():
    scene = random_scene(np.random.default_rng(1))
    assert placed_scene(scene, 0.5, -1.25) == move_robot(scene, 50.0, -125.0)


def test_turning_the_robot_left_turns_the_scene_right():
    turned = placed_scene(SCENE, 0.0, 0.0, math.pi / 2)
    person = turned['humans'][0]
    # what was ahead is now on the right
    assert (person['xPos'], person['yPos'], person['orientation']) == (100.0, 0.0, -60.0)
    assert turned['room'][0] == [-300.0, 300.0]


@pytest.mark.parametrize('heading', [None, 0.8, -2.9])
def test_the_batch_is_featurise_of_each_placed_scene(heading):
    rng = np.random.default_rng(2)
    for seed in range(20):
        scene = random_scene(np.random.default_rng(seed), max_humans=6, max_objects=3)
        x, y = rng.uniform(-3, 3, 7), rng.uniform(-3, 3, 7)
        batch = featurise_placements(scene, x, y, heading)
        for k in range(len(x)):
            graph = featurise(placed_scene(scene, x[k], y[k], heading))
            np.testing.assert_array_equal(batch[k].x, graph.x)
            np.testing.assert_array_equal(batch[k].edge_index, graph.edge_index)
            np.testing.assert_array_equal(batch[k].edge_type, graph.edge_type)


def test_the_batch_stacks_as_one_disjoint_graph():
    batch = featurise_placements(SCENE, np.array([0.0, 1.0]), np.array([0.0, 0.5]))
    x, starts, edges = batch.stacked()
    nodes = batch.x.shape[1]
    assert starts.tolist() == [0, nodes, 2 * nodes]
    np.testing.assert_array_equal(x[nodes:], batch.x[1])
    np.testing.assert_array_equal(edges[:, batch.edge_index.shape[1]:], batch.edge_index + nodes)


def test_placements_that_leave_the_schemas_range_are_refused():
    far = {**SCENE, 'room': [[99990, 0], [99999, 0], [99999, 10]]}
    with pytest.raises(SceneGraphError, match='beyond the schema'):
        featurise_placements(far, np.array([-1.0]), np.array([0.0]))


def test_valid_placements_by_hand():
    points = {(0.0, 0.0): True,  # the robot where it is
              (0.0, 1.0 - PERSON_RADIUS + 0.01): False, (0.0, 1.0 - PERSON_RADIUS - 0.01): True,  # the person
              (-1.5, -1.0 + OBJECT_RADIUS - 0.01): False, (-1.5, -1.0 + OBJECT_RADIUS + 0.01): True,
              (3.0 - WALL_THICKNESS / 2 + 0.01, 0.0): False, (3.0 - WALL_THICKNESS / 2 - 0.01, 0.0): True,
              (3.5, 0.0): False, (0.0, -3.2): False}  # outside the room
    x, y = np.array([p[0] for p in points]), np.array([p[1] for p in points])
    assert valid_placements(SCENE, x, y).tolist() == list(points.values())
