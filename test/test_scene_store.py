"""Scene stores joined into one keep every scene's rows: a batch of the joined store equals
the batch of the store the scenes came from."""
import numpy as np
import torch

from stars_ros.data.scene_graph import SceneGraph
from stars_ros.data.scene_store import GraphStore, TabularStore


def _graph(nodes: int, seed: int) -> SceneGraph:
    rng = np.random.default_rng(seed)
    edges = np.array([np.arange(1, nodes), np.zeros(nodes - 1, dtype=np.int64)])  # every node -> the robot
    return SceneGraph(rng.normal(size=(nodes, 3)).astype(np.float32), edges, rng.integers(0, 2, nodes - 1))


def _same(one, other):
    for name in ('x', 'edge_index', 'edge_type', 'batch', 'root'):
        assert torch.equal(getattr(one, name), getattr(other, name)), name
    assert one.num_graphs == other.num_graphs


def test_concatenated_graph_stores_batch_as_their_parts():
    first, second = GraphStore([_graph(3, 0), _graph(5, 1)]), GraphStore([_graph(2, 2), _graph(4, 3), _graph(6, 4)])
    joined = GraphStore.concatenate([first, second])
    assert len(joined) == 5 and joined.feature_dim == 3
    _same(joined.batch(torch.tensor([0, 1])), first.batch(torch.tensor([0, 1])))
    _same(joined.batch(torch.tensor([4, 2])), second.batch(torch.tensor([2, 0])))


def test_concatenated_tabular_stores_keep_rows_and_the_first_names():
    first = TabularStore(np.arange(6, dtype=np.float32).reshape(2, 3), ['a', 'b', 'c'])
    second = TabularStore(np.ones((1, 3), dtype=np.float32), [])
    joined = TabularStore.concatenate([first, second])
    assert joined.feature_names == ('a', 'b', 'c')
    assert torch.equal(joined.batch(torch.tensor([2, 0])), torch.tensor([[1.0, 1, 1], [0, 1, 2]]))
