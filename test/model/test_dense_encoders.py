"""The serving form of every graph backbone (GAT's compiled kernel, the dense numpy form
for the others) computes what its PyG form (what training runs) computes."""
import numpy as np
import pytest
import torch

from stars_ros.model.encoders import BACKBONES, encoder_class, resolve_encoder
from stars_ros.data.scene_graph import NODE_FEATURES, RELATIONS, SceneGraph, featurise
from stars_ros.data.scene_source import random_scene
from stars_ros.data.scene_store import GraphStore
from stars_ros.model.serving_forms import dense_graphs

GRAPH_BACKBONES = sorted(name for name in BACKBONES if encoder_class(name).input_kind == 'graph')
OPTIONS = {'gat': [{'heads': 4}, {'heads': 1}], 'rgcn': [{}, {'num_bases': 3}]}


def _case_list():
    for name in GRAPH_BACKBONES:
        for options in OPTIONS.get(name, [{}]):
            yield pytest.param(name, options,
                               id=f"{name}-{'-'.join(f'{k}{v}' for k, v in options.items()) or 'default'}")


CASES = list(_case_list())


def _encoder(name, options, seed=0):
    torch.manual_seed(seed)
    encoder = resolve_encoder(name, len(NODE_FEATURES), 16, hidden=32, layers=3, **options).eval()
    with torch.no_grad():  # move every parameter off its initial value (GIN's eps starts at 0, biases too)
        for parameter in encoder.parameters():
            parameter.add_(0.1 * torch.randn_like(parameter))
    return encoder


def _pyg(encoder, graphs):
    with torch.no_grad():
        return encoder(GraphStore(graphs).batch(torch.arange(len(graphs)))).numpy()


@pytest.mark.parametrize('name, options', CASES)
def test_serving_equals_pyg_on_random_scenes(name, options):
    rng = np.random.default_rng(1)
    graphs = [featurise(random_scene(rng)) for _ in range(40)]
    encoder = _encoder(name, options)
    sparse = _pyg(encoder, graphs)
    serving = encoder.serving_form()
    together = serving(graphs)  # graphs of different sizes in one batch
    alone = np.concatenate([serving([g]) for g in graphs])
    assert sparse.shape == together.shape == (40, 16) and together.dtype == np.float32
    assert np.allclose(together, sparse, atol=1e-5, rtol=1e-4), np.abs(together - sparse).max()
    assert np.allclose(alone, sparse, atol=1e-5, rtol=1e-4)


@pytest.mark.socnav1
@pytest.mark.parametrize('name, options', CASES)
def test_serving_equals_pyg_on_socnav1_scenes(name, options, socnav1):
    store = socnav1.store
    chosen = torch.from_numpy(np.random.default_rng(2).choice(len(store), 64, replace=False))
    batch = store.batch(chosen)
    counts = store.node_counts[chosen].tolist()
    starts = np.cumsum([0] + counts[:-1])
    edge_counts = store.edge_counts[chosen].tolist()
    edge_starts = np.cumsum([0] + edge_counts[:-1])
    graphs = [_graph(batch, start, count, edge_start, edge_count)
              for start, count, edge_start, edge_count in zip(starts, counts, edge_starts, edge_counts)]
    encoder = _encoder(name, options, seed=3)
    with torch.no_grad():
        sparse = encoder(batch).numpy()
    serving = encoder.serving_form()(graphs)
    assert np.allclose(serving, sparse, atol=1e-5, rtol=1e-4), np.abs(serving - sparse).max()


@pytest.mark.parametrize('name, options', CASES)
def test_serving_form_counts_parallel_edges_and_serves_a_lone_robot(name, options):
    rng = np.random.default_rng(7)
    features = rng.normal(size=(3, len(NODE_FEATURES))).astype(np.float32)
    parallel = SceneGraph(x=features, edge_index=np.array([[1, 1, 1, 2, 0], [0, 0, 0, 1, 2]]),
                          edge_type=np.array([0, 0, 2, 1, 4]))
    lone = SceneGraph(x=features[:1], edge_index=np.zeros((2, 0), dtype=np.int64), edge_type=np.zeros(0,
                                                                                                      dtype=np.int64))
    encoder = _encoder(name, options, seed=4)
    for graphs in ([parallel], [lone], [parallel, lone]):
        serving = encoder.serving_form()(graphs)
        sparse = _pyg(encoder, graphs)
        assert np.allclose(serving, sparse, atol=1e-5, rtol=1e-4), np.abs(serving - sparse).max()


def test_the_gat_kernel_warm_up_compiles_what_every_request_uses():
    """A batch, a lone robot or float64 features must not compile a new signature on a request."""
    from stars_ros.model.compiled_gat import _gat_encode
    serving = _encoder('gat', {'heads': 4}).serving_form()  # compiles (or loads) at construction
    signatures = list(_gat_encode.signatures)
    rng = np.random.default_rng(8)
    graphs = [featurise(random_scene(rng)) for _ in range(3)]
    lone = SceneGraph(x=np.zeros((1, len(NODE_FEATURES))), edge_index=np.zeros((2, 0), dtype=np.int32),
                      edge_type=np.zeros(0, dtype=np.int64))
    for batch in (graphs[:1], graphs, [lone], [lone, graphs[0]]):
        serving(batch)
    assert list(_gat_encode.signatures) == signatures


def test_gat_attention_rows_far_apart_are_normalised_each_by_its_own_maximum():
    """Attention logits hundreds apart: the kernel shifts each row's softmax by that row's
    maximum, as PyG's softmax does, so no row underflows to 0/0."""
    encoder = _encoder('gat', {'heads': 4})
    with torch.no_grad():
        for conv in encoder.convs:
            conv.att_dst.mul_(3000.0)  # targets' logits hundreds apart
    graphs = [featurise(random_scene(np.random.default_rng(6))) for _ in range(8)]
    sparse = _pyg(encoder, graphs)
    assert np.isfinite(sparse).all()
    serving = encoder.serving_form()(graphs)
    assert np.allclose(serving, sparse, atol=1e-4, rtol=1e-4), np.abs(serving - sparse).max()


@pytest.mark.parametrize('name', ['gat', 'gcn'])
def test_serving_forms_are_snapshots_of_the_weights(name):
    encoder = _encoder(name, {})
    graphs = [featurise(random_scene(np.random.default_rng(5)))]
    serving = encoder.serving_form()
    before = serving(graphs)
    with torch.no_grad():
        encoder.project.weight.add_(1.0)
    assert np.array_equal(serving(graphs), before)
    assert not np.allclose(encoder.serving_form()(graphs), before)


def _graph(batch, start, count, edge_start, edge_count):
    from stars_ros.data.scene_graph import SceneGraph
    edges = slice(edge_start, edge_start + edge_count)
    return SceneGraph(x=batch.x[start:start + count].numpy(),
                      edge_index=(batch.edge_index[:, edges] - start).numpy(),
                      edge_type=batch.edge_type[edges].numpy())


def test_dense_graphs_layout():
    rng = np.random.default_rng(4)
    small, large = sorted((featurise(random_scene(rng)) for _ in range(2)), key=lambda g: g.num_nodes)
    dense = dense_graphs([small, large], len(RELATIONS))
    n = large.num_nodes
    assert dense.x.shape == (2, n, len(NODE_FEATURES)) and dense.mask.shape == (2, n)
    assert dense.mask[0].sum() == small.num_nodes and dense.mask[1].all()
    assert np.array_equal(dense.x[0, small.num_nodes:], np.zeros((n - small.num_nodes, len(NODE_FEATURES))))
    source, target = small.edge_index
    assert dense.adjacency[0, target[0], source[0]] == 1
    assert dense.adjacency[0].sum() == small.edge_index.shape[1]
    assert np.array_equal(dense.relation_adjacency.sum(1), dense.adjacency)
    assert dense_graphs([small]).relation_adjacency is None


def test_dense_graphs_count_parallel_edges_per_relation():
    graph = SceneGraph(x=np.zeros((3, len(NODE_FEATURES)), dtype=np.float32),
                       edge_index=np.array([[1, 1, 1, 2], [0, 0, 0, 1]]), edge_type=np.array([0, 0, 2, 1]))
    dense = dense_graphs([graph], len(RELATIONS))
    assert dense.adjacency[0, 0, 1] == 3 and dense.adjacency[0, 1, 2] == 1 and dense.adjacency.sum() == 4
    assert dense.relation_adjacency[0, 0, 0, 1] == 2 and dense.relation_adjacency[0, 2, 0, 1] == 1
    assert dense.relation_adjacency[0, 1, 1, 2] == 1 and dense.relation_adjacency.sum() == 4
