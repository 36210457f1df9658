"""Scene sources for the companion nodes (stars_ros.data.scene_source): the JSONL reader and
what it refuses, random scenes, the robot moved within a scene, placement candidates and
the scene requests built from them."""
import json
import math

import numpy as np
import pytest

from stars_ros.data.scene_graph import NODE_FEATURES, featurise, validate_scene
from stars_ros.data.scene_source import (PLACEMENTS, move_robot, placement_candidates, random_scene, read_scenes,
                                         scene_request)
from stars_ros.errors import DataError

SCENE = {'identifier': '00001 A', 'score': 40, 'robot': {'id': 0},
         'humans': [{'id': 1, 'xPos': 100.0, 'yPos': 0.0, 'orientation': 90.0}],
         'objects': [{'id': 2, 'xPos': -50.0, 'yPos': 200.0, 'orientation': 0.0}],
         'links': [[1, 2, 'interact']], 'room': [[-300, -300], [300, -300], [300, 300], [-300, 300], [-300, -300]]}


def test_read_scenes_takes_one_object_a_line_and_skips_blank_lines(tmp_path):
    path = tmp_path / 'scenes.jsonl'
    path.write_text(json.dumps(SCENE) + '\n\n   \n' + json.dumps({**SCENE, 'identifier': '00001 B'}) + '\n')
    assert [s['identifier'] for s in read_scenes(path)] == ['00001 A', '00001 B']
    assert read_scenes(path)[0] == SCENE  # the line as it is, extra fields included


@pytest.mark.parametrize('text, message', [
    (json.dumps(SCENE) + '\n{"humans": \n', r'scenes.jsonl:2: not valid JSON'),
    ('\n' + json.dumps([SCENE]) + '\n', r'scenes.jsonl:2: expected a JSON object'),
    ('\n \n', r'scenes.jsonl: no scenes'),
])
def test_read_scenes_names_the_file_and_line_it_refuses(tmp_path, text, message):
    path = tmp_path / 'scenes.jsonl'
    path.write_text(text)
    with pytest.raises(DataError, match=message):
        read_scenes(path)


def test_random_scenes_follow_the_schema_and_the_seed():
    scenes = [random_scene(np.random.default_rng(seed), max_humans=4, max_objects=2) for seed in range(50)]
    assert random_scene(np.random.default_rng(3), 4, 2) == scenes[3]
    assert scenes[3] != scenes[4]
    for scene in scenes:
        validate_scene(scene)
        featurise(scene)
        room = scene['room']
        assert room[0] == room[-1] and 4 <= len(room) - 1 <= 8
        reach = 0.8 * min(math.hypot(x, y) for x, y in room)
        entities = scene['humans'] + scene['objects']
        assert len(scene['humans']) <= 4 and len(scene['objects']) <= 2
        assert sorted(e['id'] for e in entities) == list(range(1, len(entities) + 1))
        assert all(40 - 0.01 <= math.hypot(e['xPos'], e['yPos']) <= reach + 0.01 for e in entities)
        ids = {e['id'] for e in entities}
        assert all(a in ids and b in ids and kind == 'interact' for a, b, kind in scene['links'])
    assert {len(s['humans']) for s in scenes} == set(range(5))  # every count up to the maximum occurs


def test_moving_the_robot_shifts_everything_else_the_other_way():
    moved = move_robot(SCENE, 100.0, -50.0)  # 1 m right, 0.5 m back
    assert moved['humans'] == [{'id': 1, 'xPos': 0.0, 'yPos': 50.0, 'orientation': 90.0}]
    assert moved['objects'] == [{'id': 2, 'xPos': -150.0, 'yPos': 250.0, 'orientation': 0.0}]
    assert moved['room'][0] == [-400.0, -250.0] and len(moved['room']) == len(SCENE['room'])
    assert 'identifier' not in moved and 'score' not in moved and moved['links'] == SCENE['links']
    assert SCENE['humans'][0]['xPos'] == 100.0  # the original is untouched
    human = featurise(moved).x[2]
    assert human[NODE_FEATURES.index('distance')] == pytest.approx(0.5)  # (0, 50 cm): straight ahead
    assert human[NODE_FEATURES.index('cos_bearing')] == pytest.approx(1.0)
    back = move_robot(moved, -100.0, 50.0)
    assert back['humans'] == SCENE['humans'] and back['room'] == [[float(x), float(y)] for x, y in SCENE['room']]


def test_placement_candidates_start_where_the_robot_is():
    candidates = placement_candidates(SCENE, 3)
    assert [c['candidate'] for c in candidates] == ['stay', 'left_50cm', 'right_50cm']
    assert candidates[0]['graph'] == move_robot(SCENE, 0.0, 0.0)
    assert candidates[1]['graph']['humans'][0]['xPos'] == 150.0  # the robot 50 cm left: the person further right
    assert [c['candidate'] for c in placement_candidates(SCENE, len(PLACEMENTS))] == [p[0] for p in PLACEMENTS]
    for count in (0, len(PLACEMENTS) + 1):
        with pytest.raises(ValueError, match='count must be between 1 and'):
            placement_candidates(SCENE, count)


def test_scene_requests_rank_actions_or_placements():
    assert scene_request('s', SCENE) == {'scene_id': 's', 'graph': SCENE}
    assert scene_request('s', SCENE, user_id='ann') == {'scene_id': 's', 'user_id': 'ann', 'graph': SCENE}
    request = scene_request('s', SCENE, placements=2)
    assert set(request) == {'scene_id', 'candidates'} and request['candidates'] == placement_candidates(SCENE, 2)
