"""A generated rating data set in the SocNav1 format: scene graphs rated by a dozen people.

SocNav1 cannot ship with the project, so the graph path (loader, featurisation, training,
serving) can be tried, and is tested, on one made here: ``write(root)`` lays out
``root/raw/<annotator>.jsonl`` as SocNav1 does, one scene a line (msg_schemas/
scene_graph.schema.json, robot frame, centimetres) with an ``identifier`` and a 0–100
``score``, and ``load_dataset(root)`` reads it like the real thing.

Scenes come from ``scene_source.random_scene`` (small rooms, a few people and objects) and
are drawn in pairs that share a numeric prefix, ``"00007 A"`` and ``"00007 B"``, as in
SocNav1. A score is

    100 · clip(0.62 + 0.25 · comfort_i − 0.1 · crowding_i · (1 + t_u) + b_u + ε, 0, 1)

rounded: ``comfort_i = tanh(nearest_i − 1.5)`` with ``nearest_i`` the distance (m) from the
robot to the closest person (6 m when there is none), ``crowding_i`` the number of people
within 3 m divided by 3, ``t_u`` how much a person minds crowds, ``b_u`` their leniency and
``ε`` rater noise. Every person rates at least ``min_ratings`` scenes, the rest follow a
gamma-distributed activity, and a scene is rated by up to a few people. As in SocNav1, one
identifier (the last person's last scene's) carries two different scene contents, rated by
different people. Everything follows from ``seed``. It checks that the paths behave; it is
not a benchmark.
"""
from __future__ import annotations

import json
import math
import string
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stars_ros.data.scene_source import random_scene


@dataclass(frozen=True)
class SocNavShape:
    """Sizes and effect strengths (on the [0, 1] scale before the 0–100 mapping)."""

    users: int = 12
    scene_pairs: int = 160  # "NNNNN A" and "NNNNN B" share a prefix
    ratings: int = 520
    min_ratings: int = 25  # per person
    max_humans: int = 5
    max_objects: int = 2
    taste: float = 0.6  # sd of t_u, how much a person minds crowds
    leniency: float = 0.06  # sd of b_u
    noise: float = 0.04  # sd of ε


def annotators(count: int) -> list:
    """SocNav1's annotator names: ``a``, ``b``, … (``u12``, … beyond 26)."""
    return [string.ascii_lowercase[k] if k < 26 else f'u{k}' for k in range(count)]


def scene_factors(scene: dict) -> tuple:
    """(comfort, crowding) of a scene, the two things the planted raters care about."""
    distances = [math.hypot(h['xPos'], h['yPos']) / 100.0 for h in scene.get('humans') or ()]
    comfort = math.tanh(min(distances, default=6.0) - 1.5)
    return comfort, sum(d < 3.0 for d in distances) / 3.0


def generate(shape: SocNavShape = SocNavShape(), seed: int = 0) -> dict:
    """Annotator -> the scenes they rated, each a SocNav1 line (a dict with identifier and score)."""
    if shape.users * shape.min_ratings > shape.ratings:
        raise ValueError(f'{shape.users} users x {shape.min_ratings} ratings exceed {shape.ratings} ratings')
    rng = np.random.default_rng(seed)
    pool = []
    for pair in range(shape.scene_pairs):
        for variant in 'AB':
            scene = random_scene(rng, shape.max_humans, shape.max_objects)
            pool.append({'identifier': f'{pair:05d} {variant}', **scene})
    names = annotators(shape.users)
    tastes = rng.normal(0, shape.taste, shape.users)
    leniency = rng.normal(0, shape.leniency, shape.users)
    activity = rng.gamma(1.5, size=shape.users)
    counts = shape.min_ratings + rng.multinomial(shape.ratings - shape.users * shape.min_ratings,
                                                 activity / activity.sum())
    if counts.max() > len(pool):
        raise ValueError(f'a person would rate {counts.max()} scenes of {len(pool)}')

    def rated(scene, user):
        comfort, crowding = scene_factors(scene)
        value = (0.62 + 0.25 * comfort - 0.1 * crowding * (1 + tastes[user]) + leniency[user]
                 + rng.normal(0, shape.noise))
        return {**scene, 'score': int(round(100 * min(max(value, 0.0), 1.0)))}

    lines = {}
    for user, name in enumerate(names):
        chosen = rng.choice(len(pool), size=counts[user], replace=False)
        lines[name] = [rated(pool[k], user) for k in chosen]
    twin = {'identifier': lines[names[-1]][-1]['identifier'], **random_scene(rng, shape.max_humans, shape.max_objects)}
    stranger_to_it = next(user for user, name in enumerate(names)
                          if all(s['identifier'] != twin['identifier'] for s in lines[name]))
    lines[names[stranger_to_it]].append(rated(twin, stranger_to_it))
    return lines


def write(root, shape: SocNavShape = SocNavShape(), seed: int = 0) -> Path:
    """Write ``raw/<annotator>.jsonl`` under ``root`` (created); returns ``root``."""
    raw = Path(root) / 'raw'
    raw.mkdir(parents=True, exist_ok=True)
    for name, scenes in generate(shape, seed).items():
        (raw / f'{name}.jsonl').write_text(''.join(json.dumps(scene) + '\n' for scene in scenes))
    return Path(root)
