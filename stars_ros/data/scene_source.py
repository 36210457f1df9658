"""Scenes to feed the ranker: SocNav1-format JSONL lines, random plausible scenes, and
alternative robot placements of a scene (candidate scenes for a one-action navigation model).

ROS-free, shared by the scene_publisher node, the demo, the benchmark and the tests.
Coordinates follow msg_schemas/scene_graph.schema.json: robot frame, centimetres, degrees.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from stars_ros.errors import DataError


def socnav1_root() -> Path:
    """Where SocNav1 is read from by default: ``STARS_SOCNAV1_ROOT``, else
    ``../shared/datasets/socnav1`` beside the repository. The one place that says so (the
    offline programs, the demo and the tests take their default from here)."""
    default = Path(__file__).resolve().parents[3] / 'shared' / 'datasets' / 'socnav1'
    return Path(os.environ.get('STARS_SOCNAV1_ROOT') or default)


def read_scenes(path) -> list:
    """The scenes of a JSONL file, one JSON object a line (SocNav1 lines as they are)."""
    path = Path(path)
    scenes = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            scene = json.loads(line)
        except ValueError as error:
            raise DataError(f'{path}:{number}: not valid JSON ({error})') from None
        if not isinstance(scene, dict):
            raise DataError(f'{path}:{number}: expected a JSON object')
        scenes.append(scene)
    if not scenes:
        raise DataError(f'{path}: no scenes')
    return scenes


def random_scene(rng: np.random.Generator, max_humans: int = 8, max_objects: int = 3) -> dict:
    """A plausible SocNav1-like scene: a room of 4 to 8 corners around the robot, people
    and objects inside it, some of them interacting."""
    corners = int(rng.integers(4, 9))
    angles = np.sort(rng.uniform(0, 2 * math.pi, corners))
    radii = rng.uniform(250, 700, corners)
    room = [[round(float(r * math.sin(a)), 2), round(float(r * math.cos(a)), 2)] for a, r in zip(angles, radii)]
    room.append(list(room[0]))
    reach = 0.8 * float(radii.min())

    def entity(entity_id):
        angle, distance = rng.uniform(0, 2 * math.pi), rng.uniform(40, reach)
        return {'id': entity_id, 'xPos': round(float(distance * math.sin(angle)), 2),
                'yPos': round(float(distance * math.cos(angle)), 2),
                'orientation': round(float(rng.uniform(-180, 180)), 1)}

    n_humans, n_objects = int(rng.integers(0, max_humans + 1)), int(rng.integers(0, max_objects + 1))
    humans = [entity(1 + k) for k in range(n_humans)]
    objects = [entity(1 + n_humans + k) for k in range(n_objects)]
    links = []
    for k in range(0, n_humans - 1, 2):
        if rng.random() < 0.5:
            a, b = humans[k]['id'], humans[k + 1]['id']
            links += [[a, b, 'interact'], [b, a, 'interact']]
    for obj in objects:
        if humans and rng.random() < 0.5:
            links.append([humans[int(rng.integers(len(humans)))]['id'], obj['id'], 'interact'])
    return {'robot': {'id': 0}, 'humans': humans, 'objects': objects, 'links': links, 'room': room}


def move_robot(scene: dict, dx: float, dy: float) -> dict:
    """The same scene seen from the robot moved by (dx, dy) cm in its own frame (+y ahead),
    keeping its heading: every position shifts by (-dx, -dy), orientations stay."""
    def moved(entity):
        return {**entity, 'xPos': round(entity['xPos'] - dx, 2), 'yPos': round(entity['yPos'] - dy, 2)}

    out = {k: v for k, v in scene.items() if k not in ('identifier', 'score')}
    out['humans'] = [moved(h) for h in scene.get('humans') or []]
    out['objects'] = [moved(o) for o in scene.get('objects') or []]
    out['room'] = [[round(x - dx, 2), round(y - dy, 2)] for x, y in scene['room']]
    return out


PLACEMENTS = (('stay', 0.0, 0.0), ('left_50cm', -50.0, 0.0), ('right_50cm', 50.0, 0.0),
              ('back_50cm', 0.0, -50.0), ('ahead_50cm', 0.0, 50.0), ('left_100cm', -100.0, 0.0),
              ('right_100cm', 100.0, 0.0), ('back_100cm', 0.0, -100.0))


def placement_candidates(scene: dict, count: int) -> list:
    """``count`` candidate scenes (``{'candidate': label, 'graph': scene}``): the robot where it
    is, then moved sideways, back or ahead (see ``PLACEMENTS``)."""
    if not 1 <= count <= len(PLACEMENTS):
        raise ValueError(f'count must be between 1 and {len(PLACEMENTS)}')
    return [{'candidate': label, 'graph': move_robot(scene, dx, dy)} for label, dx, dy in PLACEMENTS[:count]]


def scene_request(scene_id: str, scene: dict, user_id: str | None = None, placements: int = 0) -> dict:
    """A /stars/scene payload: rank the model's actions in ``scene`` or, with ``placements``,
    rank that many robot placements against each other."""
    request = {'scene_id': scene_id}
    if user_id:
        request['user_id'] = user_id
    if placements:
        request['candidates'] = placement_candidates(scene, placements)
    else:
        request['graph'] = scene
    return request
