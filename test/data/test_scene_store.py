"""Scene stores (stars_ros.data.scene_store): a batch gathers the scenes asked for, in order,
with their nodes and edges renumbered; a saved store loads back the same; stores joined into
one keep every scene's rows: a batch of the joined store equals the batch of the store the
scenes came from."""
import numpy as np
import pytest
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


def _numbered(nodes: int, first: int) -> SceneGraph:
    """A graph whose node features are its node numbers ``first``, ``first + 1``, … (one
    column) and whose edges run from every node to its robot, with edge type = source node."""
    edges = np.array([np.arange(1, nodes), np.zeros(nodes - 1, dtype=np.int64)])
    return SceneGraph(np.arange(first, first + nodes, dtype=np.float32)[:, None], edges, np.arange(1, nodes))


def test_a_batch_gathers_the_graphs_asked_for_in_their_order_and_renumbers_their_nodes():
    store = GraphStore([_numbered(2, 0), _numbered(3, 10), _numbered(4, 20)])
    assert len(store) == 3 and store.feature_dim == 1 and store.kind == 'graph'
    assert store.node_starts.tolist() == [0, 2, 5] and store.edge_starts.tolist() == [0, 1, 3]
    batch = store.batch(torch.tensor([2, 0]))
    assert batch.x[:, 0].tolist() == [20, 21, 22, 23, 0, 1]
    assert batch.batch.tolist() == [0, 0, 0, 0, 1, 1] and batch.root.tolist() == [0, 4] and batch.num_graphs == 2
    assert batch.edge_index.tolist() == [[1, 2, 3, 5], [0, 0, 0, 4]]  # graph 0's edge 1 -> 0 now 5 -> 4
    assert batch.edge_type.tolist() == [1, 2, 3, 1]
    twice = store.batch(torch.tensor([1, 1]))
    assert twice.x[:, 0].tolist() == [10, 11, 12] * 2 and twice.edge_index.tolist() == [[1, 2, 4, 5], [0, 0, 3, 3]]


def test_a_saved_store_loads_back_the_same_batches(tmp_path):
    store = GraphStore([_numbered(3, 0), _numbered(2, 5)])
    store.save(tmp_path / 'store.pt')
    loaded = GraphStore.load(tmp_path / 'store.pt')
    _same(loaded.batch(torch.tensor([1, 0])), store.batch(torch.tensor([1, 0])))


def test_an_empty_graph_store_is_refused():
    with pytest.raises(ValueError, match='at least one graph'):
        GraphStore([])


def test_a_tabular_batch_is_the_rows_asked_for():
    store = TabularStore(np.arange(12).reshape(4, 3), ['a', 'b', 'c'])
    assert (len(store), store.feature_dim, store.kind) == (4, 3, 'tabular')
    assert store.batch(torch.tensor([3, 0, 3])).tolist() == [[9, 10, 11], [0, 1, 2], [9, 10, 11]]
    assert store.batch(torch.tensor([0])).dtype == torch.float32
