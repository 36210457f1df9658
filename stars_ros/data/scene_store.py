"""Featurised scenes kept as contiguous tensors, so a training batch is gathered by indexing.

Ratings share scenes, so training encodes each distinct scene of a batch once: the
stores only ever receive the unique scene indices of a batch.
"""
from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np
import torch

from stars_ros.data.scene_graph import SceneGraph


class GraphBatch(NamedTuple):
    """Graphs of one batch laid side by side (PyG convention).

    ``root`` holds the index of each graph's robot node (its first node).
    """

    x: torch.Tensor
    edge_index: torch.Tensor
    edge_type: torch.Tensor
    batch: torch.Tensor
    root: torch.Tensor
    num_graphs: int

    def to(self, device) -> 'GraphBatch':
        """The batch on ``device`` (the store stays on the CPU; training moves each batch)."""
        return GraphBatch(self.x.to(device), self.edge_index.to(device), self.edge_type.to(device),
                          self.batch.to(device), self.root.to(device), self.num_graphs)


def _ranges(starts: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    """Concatenate ``arange(s, s + c)`` for every (s, c) pair without a Python loop."""
    total = int(counts.sum())
    offsets = torch.cumsum(counts, 0) - counts
    return torch.repeat_interleave(starts - offsets, counts, output_size=total) + torch.arange(total)


class GraphStore:
    """All featurised graphs of a dataset; ``batch(indices)`` collates a subset."""

    kind = 'graph'

    def __init__(self, graphs: Sequence[SceneGraph]):
        if not graphs:
            raise ValueError('GraphStore needs at least one graph')
        self._set(x=torch.from_numpy(np.concatenate([g.x for g in graphs])),
                  edge_index=torch.from_numpy(np.concatenate([g.edge_index for g in graphs], axis=1)),
                  edge_type=torch.from_numpy(np.concatenate([g.edge_type for g in graphs])),
                  node_counts=torch.tensor([g.num_nodes for g in graphs]),
                  edge_counts=torch.tensor([g.edge_index.shape[1] for g in graphs]))

    def _set(self, x, edge_index, edge_type, node_counts, edge_counts):
        self.x, self.edge_index, self.edge_type = x, edge_index, edge_type
        self.node_counts, self.edge_counts = node_counts, edge_counts
        self.node_starts = torch.cumsum(node_counts, 0) - node_counts
        self.edge_starts = torch.cumsum(edge_counts, 0) - edge_counts

    def save(self, path) -> None:
        torch.save({'x': self.x, 'edge_index': self.edge_index, 'edge_type': self.edge_type,
                    'node_counts': self.node_counts, 'edge_counts': self.edge_counts}, path)

    @classmethod
    def load(cls, path) -> 'GraphStore':
        store = cls.__new__(cls)
        store._set(**torch.load(path, weights_only=True))
        return store

    @classmethod
    def concatenate(cls, stores: Sequence['GraphStore']) -> 'GraphStore':
        """One store of the graphs of ``stores``, in order (row indices of the second start
        after the first's last): a data set extended by new scenes keeps its rows."""
        store = cls.__new__(cls)
        store._set(x=torch.cat([s.x for s in stores]), edge_index=torch.cat([s.edge_index for s in stores], 1),
                   edge_type=torch.cat([s.edge_type for s in stores]),
                   node_counts=torch.cat([s.node_counts for s in stores]),
                   edge_counts=torch.cat([s.edge_counts for s in stores]))
        return store

    def __len__(self) -> int:
        return len(self.node_counts)

    @property
    def feature_dim(self) -> int:
        return self.x.shape[1]

    def scene(self, index: int) -> SceneGraph:
        """Row ``index`` as the featurised graph it was stored from (``Predictor.score`` takes it)."""
        nodes = slice(int(self.node_starts[index]), int(self.node_starts[index] + self.node_counts[index]))
        edges = slice(int(self.edge_starts[index]), int(self.edge_starts[index] + self.edge_counts[index]))
        return SceneGraph(self.x[nodes].numpy(), self.edge_index[:, edges].numpy(), self.edge_type[edges].numpy())

    def batch(self, indices: torch.Tensor) -> GraphBatch:
        node_counts = self.node_counts[indices]
        edge_counts = self.edge_counts[indices]
        nodes = _ranges(self.node_starts[indices], node_counts)
        edges = _ranges(self.edge_starts[indices], edge_counts)
        new_starts = torch.cumsum(node_counts, 0) - node_counts
        shift = torch.repeat_interleave(new_starts, edge_counts)
        graph_of_node = torch.repeat_interleave(torch.arange(len(indices)), node_counts)
        return GraphBatch(x=self.x[nodes], edge_index=self.edge_index[:, edges] + shift,
                          edge_type=self.edge_type[edges], batch=graph_of_node,
                          root=new_starts, num_graphs=len(indices))


class TabularStore:
    """Scene feature rows (one per scene); ``batch(indices)`` returns a float tensor."""

    kind = 'tabular'

    def __init__(self, features: np.ndarray, feature_names: Sequence[str]):
        self.features = torch.as_tensor(np.asarray(features, dtype=np.float32))
        self.feature_names = tuple(feature_names)

    @classmethod
    def concatenate(cls, stores: Sequence['TabularStore']) -> 'TabularStore':
        """One store of the rows of ``stores``, in order, named as the first names its columns."""
        return cls(torch.cat([s.features for s in stores]).numpy(), stores[0].feature_names)

    def __len__(self) -> int:
        return self.features.shape[0]

    @property
    def feature_dim(self) -> int:
        return self.features.shape[1]

    def scene(self, index: int) -> np.ndarray:
        """Row ``index``'s features [features] (float32), as ``Predictor.score`` takes a scene."""
        return self.features[index].numpy()

    def batch(self, indices: torch.Tensor) -> torch.Tensor:
        return self.features[indices]
