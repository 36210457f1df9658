"""Folds of the evaluation protocol, and the nested subsets of its sparsity sweep.

A row of the protocol is an *example*: one user's ratings of one scene, every action
(``RatingData.examples``). Three protocols differ only in how examples are grouped into
folds: ``rows`` (random examples, as published), ``cold-scene`` (grouped by scene, so no
test scene is seen in training) and ``cold-user`` (grouped by annotator). Sweep samples
are drawn over whole examples, so an example's actions never straddle a split.
"""
from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

from stars_ros.data.ratings import RatingData

PROTOCOLS = ('rows', 'cold-scene', 'cold-user')
DEALS = ('largest_first', 'shuffled')  # how grouped_folds orders the groups it deals


class Fold(NamedTuple):
    """Row indices of one split: what is trained on, what is scored."""

    train: np.ndarray
    test: np.ndarray


def grouped_folds(rows: np.ndarray, groups: np.ndarray, k: int, seed, deal: str = 'largest_first') -> list[Fold]:
    """k folds of ``rows`` such that the rows of one group (``groups[row]``) share a fold.

    Groups are shuffled, then each is dealt to the fold with the fewest rows so far. With
    ``deal`` 'largest_first' they are dealt largest first, which balances the fold sizes when
    a few groups are large (annotators); the shuffle then only orders groups of equal size,
    so where every group's size differs (SocNav1's 12 annotators) the folds are the same
    under every seed. With 'shuffled' they are dealt in the shuffled order: new folds for
    each seed, sizes less even.
    """
    if deal not in DEALS:
        raise ValueError(f'deal must be one of {DEALS}, got {deal!r}')
    rows = np.asarray(rows)
    labels, inverse, counts = np.unique(np.asarray(groups)[rows], return_inverse=True, return_counts=True)
    if not 2 <= k <= len(labels):
        raise ValueError(f'cannot deal {len(labels)} groups into {k} folds')
    shuffled = np.random.default_rng(seed).permutation(len(labels))
    order = shuffled[np.argsort(-counts[shuffled], kind='stable')] if deal == 'largest_first' else shuffled
    fold_of_group = np.empty(len(labels), dtype=np.int64)
    sizes = np.zeros(k, dtype=np.int64)
    for group in order:
        target = int(np.argmin(sizes))
        fold_of_group[group] = target
        sizes[target] += counts[group]
    fold_of_row = fold_of_group[inverse.ravel()]
    return [Fold(np.sort(rows[fold_of_row != f]), np.sort(rows[fold_of_row == f])) for f in range(k)]


def fold_groups(data: RatingData, protocol: str) -> np.ndarray:
    """The group of every rating that a fold of ``protocol`` keeps together (see PROTOCOLS)."""
    if protocol == 'rows':
        return data.examples
    if protocol == 'cold-scene':
        return data.scenes
    if protocol == 'cold-user':
        return data.users
    raise ValueError(f"Could not resolve protocol '{protocol}' among choices {list(PROTOCOLS)}")


def make_folds(data: RatingData, protocol: str, k: int, seed, rows: np.ndarray | None = None,
               deal: str = 'largest_first') -> list[Fold]:
    """Folds of ``rows`` (all rows by default) for ``protocol``: examples, scenes or users
    never straddle a fold; ``deal`` as ``grouped_folds``."""
    rows = np.arange(len(data)) if rows is None else np.asarray(rows)
    return grouped_folds(rows, fold_groups(data, protocol), k, seed, deal)


def sweep_samples(pool: np.ndarray, fractions: Sequence[float], seed, groups: np.ndarray | None = None) -> dict:
    """Nested random subsets of ``pool`` (without replacement), sorted; fraction 1.0 is the
    pool. With ``groups`` (per rating, e.g. ``data.examples``) whole groups are sampled."""
    pool = np.asarray(pool)
    keys = pool if groups is None else np.asarray(groups)[pool]
    labels, inverse = np.unique(keys, return_inverse=True)
    rank = np.empty(len(labels), dtype=np.int64)
    rank[np.random.default_rng(seed).permutation(len(labels))] = np.arange(len(labels))
    rank_of_row = rank[inverse.ravel()]
    return {f: np.sort(pool[rank_of_row < max(1, int(round(f * len(labels))))]) for f in fractions}
