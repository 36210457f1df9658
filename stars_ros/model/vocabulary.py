"""The ids behind a model's rows, and the row of an id it never saw.

Kept apart from the torch model so that serving (``model.serving``) and the node's logic
read vocabularies without importing training.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

UNKNOWN = -1  # the row of an id not seen in training: scored with zero rows


class Vocabulary:
    """Ids in row order: the rows of one embedding table (users, or scene items).

    ``row(key)`` and ``rows(keys)`` give UNKNOWN (-1) for an id the table lacks (and for
    None), which the model scores with zero rows; ``extended`` appends new ids after the
    old ones, so existing rows keep their index."""

    def __init__(self, keys=()):
        self.keys = tuple(keys)
        self._rows = {key: row for row, key in enumerate(self.keys)}

    def __len__(self) -> int:
        return len(self.keys)

    def __contains__(self, key) -> bool:
        return key in self._rows

    def row(self, key) -> int:
        return self._rows.get(key, UNKNOWN) if key is not None else UNKNOWN

    def rows(self, keys: Sequence) -> np.ndarray:
        return np.array([self.row(key) for key in keys], dtype=np.int64)

    def extended(self, keys: Sequence) -> 'Vocabulary':
        return Vocabulary(self.keys + tuple(k for k in dict.fromkeys(keys) if k not in self._rows))


class Rows:
    """The ids behind a model's rows and what it clips to, as a fitted model (training's
    ``fitted.FittedModel``) and its serving form (``serving.ServedModel``) both hold them:
    ``user_vocabulary``, ``scene_vocabulary`` and ``rating_scale`` (lowest, highest; None:
    unbounded)."""

    user_vocabulary: Vocabulary
    scene_vocabulary: Vocabulary
    rating_scale: tuple | None

    @property
    def users(self) -> tuple:
        return self.user_vocabulary.keys

    @property
    def scene_keys(self) -> tuple:
        return self.scene_vocabulary.keys

    def clip(self, scores: np.ndarray) -> np.ndarray:
        """``scores`` limited to the rating scale of the training data (when it has one)."""
        if self.rating_scale is None:
            return scores
        return np.minimum(np.maximum(scores, self.rating_scale[0]), self.rating_scale[1])  # np.clip's, without
        # its wrappers' cost per request
