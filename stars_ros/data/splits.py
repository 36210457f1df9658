"""The one way a share of examples is held out: whole examples (one person's ratings of one
scene, every action), chosen by a seeded permutation of their ids. The training split
(``model.training.split_rows``), the prior's held-out noise rows (``personalisation.prior``)
and known people's calibration rows (``evaluation.kshot``) all draw through it; folds are
``evaluation.folds``'."""
from __future__ import annotations

import numpy as np


def held_examples(examples: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Per rating of ``examples`` (each rating's example id): True where its example is one
    of ``count`` examples drawn by ``rng`` (a permutation of the distinct ids, its first
    ``count``). ``rng`` is not drawn on when ``count`` is 0."""
    if count <= 0:
        return np.zeros(len(examples), dtype=bool)
    return np.isin(examples, rng.permutation(np.unique(examples))[:count])
