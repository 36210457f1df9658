"""A generated multi-action crowd data set with the shape of MannersDB+, in the generic format.

None ships with the project, so the tabular path is checked on one made here: hundreds of
raters, hundreds of scenes described by a few dozen features, 9 actions, integer scores
1–5 and about 14 raters per scene. A score is

    3 + spread · (s_ia + (t_u ⊙ z_i)ᵀ v_a + b_u + m_ui + ε),   z_i = tanh(W x_i)

rounded and clipped to 1–5: ``s_ia`` the scene's appropriateness of action a (a nonlinear
function of its features), ``t_u`` a person's tastes, which interact with the scene's latent
factors ``z_i`` through each action's loadings ``v_a``, ``b_u`` a person's leniency, ``m_ui``
their mood on that scene (one offset shared by every action they rate there) and ``ε`` rater
noise. Raters differ in how many scenes they rate (a gamma-distributed activity). The mood
is why a protocol row must be an example: a test rating's siblings in training would reveal
it. Everything follows from ``seed``. It checks that the path behaves; it is not a benchmark
to tune on.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

ACTIONS = ('vacuum', 'mop', 'carry_warm_food', 'carry_cold_food', 'carry_drinks', 'carry_small_objects',
           'carry_big_objects', 'clean_table', 'start_conversation')


@dataclass(frozen=True)
class CrowdShape:
    """Sizes and effect strengths (z-units before the 1–5 mapping)."""

    users: int = 400
    scenes: int = 600
    features: int = 29  # columns of scenes.csv
    raters_per_scene: int = 14
    latent: int = 6  # scene factors z_i that tastes interact with
    taste: float = 0.6  # sd of t_u
    leniency: float = 0.35  # sd of b_u
    mood: float = 0.3  # sd of m_ui
    noise: float = 0.35  # sd of ε
    spread: float = 1.1  # z-units to points of the 1–5 scale


def generate(shape: CrowdShape = CrowdShape(), seed: int = 0) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(annotations with columns user, scene, action, score; scenes with scene + features)."""
    rng = np.random.default_rng(seed)
    n_actions = len(ACTIONS)
    binary = shape.features // 3
    x = np.concatenate([rng.normal(size=(shape.scenes, shape.features - binary)),
                        rng.integers(0, 2, size=(shape.scenes, binary)).astype(float)], axis=1)
    w = rng.normal(size=(shape.features, shape.latent)) / np.sqrt(shape.features) * 1.5
    z = np.tanh(x @ w)                                                   # [scenes, latent]
    appropriateness = z @ rng.normal(size=(shape.latent, n_actions)) * 0.8 + rng.normal(0, 0.3, n_actions)
    loadings = rng.normal(size=(shape.latent, n_actions)) / np.sqrt(shape.latent)
    tastes = rng.normal(0, shape.taste, size=(shape.users, shape.latent))
    leniency = rng.normal(0, shape.leniency, size=shape.users)
    activity = rng.gamma(1.5, size=shape.users)
    rows = []
    for scene in range(shape.scenes):
        raters = rng.choice(shape.users, size=shape.raters_per_scene, replace=False, p=activity / activity.sum())
        rated = rng.random((len(raters), n_actions)) < 0.9  # a few actions left unrated
        rated[np.arange(len(raters)), rng.integers(0, n_actions, len(raters))] = True
        for k, user in enumerate(raters):
            mood = rng.normal(0, shape.mood)
            latent = appropriateness[scene] + (tastes[user] * z[scene]) @ loadings + leniency[user] + mood
            noisy = latent + rng.normal(0, shape.noise, n_actions)
            scores = np.clip(np.rint(3 + shape.spread * noisy), 1, 5).astype(int)
            rows += [(f'u{user:03d}', f's{scene:03d}', ACTIONS[a], scores[a]) for a in np.flatnonzero(rated[k])]
    annotations = pd.DataFrame(rows, columns=['user', 'scene', 'action', 'score'])
    scenes = pd.DataFrame(np.round(x, 4), columns=[f'f{j:02d}' for j in range(shape.features)])
    scenes.insert(0, 'scene', [f's{i:03d}' for i in range(shape.scenes)])
    return annotations, scenes


def write(root, shape: CrowdShape = CrowdShape(), seed: int = 0) -> Path:
    """Write ``annotations.csv`` and ``scenes.csv`` under ``root`` (created); returns it."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    annotations, scenes = generate(shape, seed)
    annotations.to_csv(root / 'annotations.csv', index=False)
    scenes.to_csv(root / 'scenes.csv', index=False)
    return root
