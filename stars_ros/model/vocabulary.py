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
