"""StarsRecommender.placement_map: every cell is what ranking its placement as a candidate scene
gives (score and score_sd, to 1e-6), for a trained person, a folded-in one and a stranger, on
generated scenes with small models and on 20 real SocNav1 scenes with the packaged GAT; the
invalid cells are exactly those a hand-written geometry check finds; bad requests are refused
with their kind."""
import math

import numpy as np
import pytest

from stars_ros import StarsRecommender
from stars_ros.data.placements import OBJECT_RADIUS, PERSON_RADIUS, WALL_THICKNESS, placed_scene
from stars_ros.data.scene_source import read_scenes
from stars_ros.errors import BadMapRequest, StarsError
from stars_ros.resources import resolve_checkpoint

STRANGER = 'someone new'


def ranked_cells(recommender, user, scene, placement_map) -> tuple:
    """(score, score_sd) [rows, cols] of each valid cell ranked as a candidate scene (NaN elsewhere)."""
    x, y = placement_map.centres()
    cells = np.argwhere(placement_map.valid)
    candidates = [placed_scene(scene, x[i, j], y[i, j], placement_map.heading) for i, j in cells]
    labels = [f'{i},{j}' for i, j in cells]
    ranked = recommender.rank_scenes(user, candidates, labels=labels, uncertainty=True)
    score, score_sd = np.full(placement_map.shape, np.nan), np.full(placement_map.shape, np.nan)
    for entry in ranked:
        i, j = map(int, entry.name.split(','))
        score[i, j], score_sd[i, j] = entry.score, entry.score_sd
    return score, score_sd


def assert_map_is_the_ranking(recommender, user, scene, **grid):
    placement_map = recommender.placement_map(user, scene, **grid)
    assert placement_map.valid.any()
    score, score_sd = ranked_cells(recommender, user, scene, placement_map)
    np.testing.assert_allclose(placement_map.score, score, rtol=0, atol=1e-6)  # NaN where invalid, in both
    np.testing.assert_allclose(placement_map.score_sd, score_sd, rtol=0, atol=1e-6)
    return placement_map


def people(recommender, scenes) -> tuple:
    """A trained person, one folded in from five ratings, and a stranger."""
    action = recommender.actions[0]
    recommender.fold_in('folded', [(scene, action, 0.2 + 0.1 * k) for k, scene in enumerate(scenes[:5])])
    return recommender.users[0], 'folded', STRANGER


@pytest.mark.parametrize('checkpoint', ['tiny_checkpoint', 'tiny_base_stranger_checkpoint'])
def test_every_cell_is_its_placement_ranked_as_a_candidate(request, checkpoint, synthetic_scenes):
    recommender = StarsRecommender.load(request.getfixturevalue(checkpoint))
    for user in people(recommender, synthetic_scenes[20:]):
        for k, scene in enumerate(synthetic_scenes[:4]):
            assert_map_is_the_ranking(recommender, user, scene, size=3.0, resolution=0.25,
                                      heading=None if k % 2 else 0.4 * k)


def test_the_grid_is_centred_on_the_robot(tiny_checkpoint, synthetic_scenes):
    placement_map = StarsRecommender.load(tiny_checkpoint).placement_map(None, synthetic_scenes[0], 2.0, 0.5)
    assert placement_map.shape == (4, 4) and placement_map.origin == (-1.0, -1.0)
    assert placement_map.resolution == 0.5
    x, y = placement_map.centres()
    assert x[0].tolist() == [-0.75, -0.25, 0.25, 0.75] and (y[:, 0] == x[0]).all()  # rows go along y
    assert (x[2] == x[0]).all() and (y[1] == -0.25).all()
    assert np.isnan(placement_map.score[~placement_map.valid]).all()
    assert np.isfinite(placement_map.score[placement_map.valid]).all()


NAN, INF = float('nan'), float('inf')


@pytest.mark.parametrize('user, grid, kind, message', [
    ('a', {'size': 40.0, 'resolution': 0.125}, 'too_large', '320 cells a side; a map has at most 256'),
    ('a', {'size': 8.0, 'resolution': 1e-300}, 'too_large', 'at most 256'),
    ('a', {'size': NAN}, 'non_finite', 'size is nan'),
    ('a', {'resolution': INF}, 'non_finite', 'resolution is inf'),
    ('a', {'heading': NAN}, 'non_finite', 'heading is nan'),
    ('a', {'resolution': 0.0}, 'schema', 'must be positive'),
    ('a', {'size': 'big'}, 'schema', 'size must be a number'),
    ('x' * 257, {}, 'schema', 'user id of 257 characters; at most 256'),
])
def test_bad_requests_are_refused_with_their_kind(tiny_checkpoint, synthetic_scenes, user, grid, kind,
                                                   message):
    recommender = StarsRecommender.load(tiny_checkpoint)
    with pytest.raises(BadMapRequest, match=message) as refused:
        recommender.placement_map(user, synthetic_scenes[0], **grid)
    assert refused.value.kind == kind and isinstance(refused.value, StarsError)


def test_bad_scenes_are_refused_with_their_kind(tiny_checkpoint, synthetic_scenes):
    recommender = StarsRecommender.load(tiny_checkpoint)
    scene = synthetic_scenes[0]
    for bad, kind in [({**scene, 'room': [[NAN, 0], [100, 0], [0, 100]]}, 'non_finite'),
                      ('00001 A', 'schema'),  # an id: the map needs the scene's content
                      ({**scene, 'room': [[0, 0], [100, 0]]}, 'scene_graph'),
                      ({key: value for key, value in scene.items() if key != 'room'}, 'scene_graph')]:
        with pytest.raises(BadMapRequest) as refused:
            recommender.placement_map('a', bad, 2.0, 0.5)
        assert refused.value.kind == kind, bad


def _inside(polygon, x, y) -> bool:
    """Winding number of the polygon around (x, y), by hand."""
    winding = 0
    for (x0, y0), (x1, y1) in zip(polygon, polygon[1:] + polygon[:1]):
        side = (x1 - x0) * (y - y0) - (x - x0) * (y1 - y0)
        if y0 <= y < y1 and side > 0:
            winding += 1
        elif y1 <= y < y0 and side < 0:
            winding -= 1
    return winding != 0


def _to_segment(x, y, a, b) -> float:
    (ax, ay), (bx, by) = a, b
    length = (bx - ax) ** 2 + (by - ay) ** 2
    t = 0.0 if length == 0 else min(1.0, max(0.0, ((x - ax) * (bx - ax) + (y - ay) * (by - ay)) / length))
    return math.hypot(x - ax - t * (bx - ax), y - ay - t * (by - ay))


def where_the_robot_can_be(scene, x, y) -> bool:
    """Inside the room's polygon, and not inside a wall, a person or an object (metres)."""
    room = [(px / 100, py / 100) for px, py in scene['room']]
    room = room[:-1] if room[0] == room[-1] else room
    if not _inside(room, x, y):
        return False
    if any(_to_segment(x, y, a, b) < WALL_THICKNESS / 2 for a, b in zip(room, room[1:] + room[:1])):
        return False
    footprints = (('humans', PERSON_RADIUS), ('objects', OBJECT_RADIUS))
    return not any(math.hypot(x - e['xPos'] / 100, y - e['yPos'] / 100) < radius
                   for key, radius in footprints for e in scene[key])


@pytest.mark.slow
@pytest.mark.socnav1
def test_maps_of_20_socnav1_scenes_are_their_placements_ranked(socnav1_root):
    """Packaged GAT, 12 × 12 cells over 6 m (reaching beyond the room: walls and people
    included), every other scene with the robot turned."""
    recommender = StarsRecommender.load(resolve_checkpoint(''))
    lines = read_scenes(socnav1_root / 'raw' / 'b.jsonl')
    scenes = [scene for scene in lines[::50] if scene['humans'] or scene['objects']][:20]
    assert len(scenes) == 20
    known, folded, stranger = people(recommender, lines[1::50])
    assert known == 'a' and not recommender.predictor.knows_user(stranger)
    for k, scene in enumerate(scenes):
        heading = None if k % 2 else 0.3 * k - 2.5
        for user in (known, folded, stranger):
            placement_map = assert_map_is_the_ranking(recommender, user, scene, size=6.0, resolution=0.5,
                                                      heading=heading)
        x, y = placement_map.centres()
        expected = [[where_the_robot_can_be(scene, x[i, j], y[i, j]) for j in range(12)] for i in range(12)]
        assert placement_map.valid.tolist() == expected
        assert 0 < placement_map.valid.sum() < placement_map.valid.size  # the grid reaches beyond the room
