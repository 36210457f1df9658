"""Every graph backbone's serving form, built from its weights alone (a state dict as
float32 arrays), so a checkpoint is served without torch-geometric or the training modules.

Serving scores one or a few scenes of ~20 nodes, where each tensor operation's fixed cost
(PyG's per-call bookkeeping, torch's dispatch, nn.Module calls) is the whole cost, so every
backbone has exactly one numpy serving form:

- the dense backbones (GCN, GIN, GraphSAGE, GGNN, RGCN) run a padded dense batch: each
  says which matrix its layers multiply by (``_STRUCTURES``, computed once per batch) and
  how one convolution reads its weights (``_CONVOLUTIONS``);
- GAT runs the whole encoder compiled into one call (``compiled_gat``).

The weights are named as PyG's modules name them (``convs.0.lin.weight``: what
``graph.GraphEncoder.state_dict`` holds and a checkpoint stores under ``encoder.``), and
``graph.GraphEncoder.serving_form`` builds its form here too, so the node and training's
checks share one form; ``test/model/test_dense_encoders.py`` checks each against PyG.
Both rely on what ``featurise`` guarantees: no self loops.
"""
from __future__ import annotations

from typing import Callable, Mapping, NamedTuple, Sequence

import numpy as np

from stars_ros.data.scene_graph import RELATIONS, SceneGraph

GAT_NEGATIVE_SLOPE = 0.2  # GATConv's LeakyReLU slope: graph.GAT builds its convolutions with it


class DenseGraphs(NamedTuple):
    """A few graphs padded to the largest one, for inference on small scene graphs
    (numpy arrays: see ``graph_serving_form``).

    ``x`` [G, N, F]; ``mask`` [G, N] (real nodes); ``adjacency`` [G, N, N] with
    ``adjacency[g, i, j]`` = number of edges j → i (messages flow to i, as in PyG);
    ``relation_adjacency`` [G, R, N, N] the same per edge type, or None when not asked
    for. The robot node is node 0 of every graph.
    """

    x: np.ndarray
    mask: np.ndarray
    adjacency: np.ndarray
    relation_adjacency: np.ndarray | None


def dense_graphs(graphs: Sequence[SceneGraph], relations: int | None = None) -> DenseGraphs:
    """Pad ``graphs`` into a DenseGraphs; ``relations`` (the number of edge types) adds the
    per-relation adjacency. Built in numpy: a scene of ~20 nodes costs microseconds."""
    n = max(g.num_nodes for g in graphs)
    x = np.zeros((len(graphs), n, graphs[0].x.shape[1]), dtype=np.float32)
    mask = np.zeros((len(graphs), n), dtype=bool)
    adjacency = np.zeros((len(graphs), n, n), dtype=np.float32)
    typed = np.zeros((len(graphs), relations, n, n), dtype=np.float32) if relations else None
    for k, graph in enumerate(graphs):
        x[k, :graph.num_nodes] = graph.x
        mask[k, :graph.num_nodes] = True
        source, target = graph.edge_index
        cell = target * n + source  # edges counted with bincount: np.add.at costs 3x as much here
        adjacency[k] = np.bincount(cell, minlength=n * n).reshape(n, n)
        if typed is not None:
            typed[k] = np.bincount(graph.edge_type * (n * n) + cell,
                                   minlength=relations * n * n).reshape(relations, n, n)
    return DenseGraphs(x, mask, adjacency, typed)


def _relu(x: np.ndarray) -> np.ndarray:
    return np.maximum(x, 0.0)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x))


class _Layer:
    """The weights of one module of the state dict, by their name under ``prefix``."""

    def __init__(self, weights: Mapping[str, np.ndarray], prefix: str):
        self._weights, self._prefix = weights, prefix

    def __getitem__(self, name: str) -> np.ndarray:
        return self._weights[self._prefix + name]

    def linear(self, name: str) -> tuple:
        """(weightᵀ, bias) of the Linear ``name``, so that ``x @ w + b`` applies it (bias 0.0
        where the Linear has none)."""
        return self[f'{name}.weight'].T.copy(), self._weights.get(f'{self._prefix}{name}.bias', 0.0)


def _mean_operator(adjacency: np.ndarray) -> np.ndarray:
    """Rows scaled so that multiplying averages the incoming neighbours (zero without
    any), PyG's aggr='mean'."""
    return adjacency / np.maximum(adjacency.sum(-1, keepdims=True), 1.0)


def _gcn_structure(graphs) -> np.ndarray:
    adjacency = graphs.adjacency + np.eye(graphs.adjacency.shape[-1], dtype=graphs.adjacency.dtype)
    scale = 1.0 / np.sqrt(adjacency.sum(-1))  # in-degree with the self loop, as gcn_norm
    return scale[..., :, None] * adjacency * scale[..., None, :]


def _gcn(conv: _Layer) -> Callable:
    weight, bias = conv.linear('lin')[0], conv['bias']
    return lambda h, structure: structure @ (h @ weight) + bias


def _gin(conv: _Layer) -> Callable:
    eps, (w1, b1), (w2, b2) = float(conv['eps'][0]), conv.linear('nn.0'), conv.linear('nn.2')
    return lambda h, structure: _relu(((1 + eps) * h + structure @ h) @ w1 + b1) @ w2 + b2


def _graphsage(conv: _Layer) -> Callable:
    (wl, bl), (wr, br) = conv.linear('lin_l'), conv.linear('lin_r')
    return lambda h, structure: (structure @ h) @ wl + bl + h @ wr + br


def _ggnn(conv: _Layer) -> Callable:
    """One GRU-gated propagation step (GatedGraphConv with num_layers=1)."""
    message = conv['weight'][0]
    wi, bi = conv['rnn.weight_ih'].T.copy(), conv['rnn.bias_ih']
    wh, bh = conv['rnn.weight_hh'].T.copy(), conv['rnn.bias_hh']

    def apply(h, structure):
        messages = structure @ (h @ message)
        gates_in, gates_state = messages @ wi + bi, h @ wh + bh  # torch.nn.GRUCell: reset, update, new
        reset_in, update_in, new_in = np.split(gates_in, 3, axis=-1)
        reset_state, update_state, new_state = np.split(gates_state, 3, axis=-1)
        reset, update = _sigmoid(reset_in + reset_state), _sigmoid(update_in + update_state)
        candidate = np.tanh(new_in + reset * new_state)
        return (1 - update) * candidate + update * h
    return apply


def _rgcn(conv: _Layer) -> Callable:
    """One weight matrix per edge type of ``scene_graph.RELATIONS`` (combined from bases
    where the convolution has them)."""
    weight = conv['weight']
    try:
        weight = (conv['comp'] @ weight.reshape(weight.shape[0], -1)).reshape(-1, *weight.shape[1:])
    except KeyError:
        pass  # no bases: one matrix per relation already
    relations, root, bias = weight.reshape(-1, weight.shape[-1]), conv['root'], conv['bias']  # [R * hidden, hidden]

    def apply(h, structure):
        g, n, _ = h.shape
        per_relation = structure @ h[:, None]  # [G, R, N, hidden]
        stacked = per_relation.transpose(0, 2, 1, 3).reshape(g, n, -1)  # [G, N, R * hidden]
        return stacked @ relations + h @ root + bias
    return apply


_CONVOLUTIONS = {'gcn': _gcn, 'gin': _gin, 'graphsage': _graphsage, 'ggnn': _ggnn, 'rgcn': _rgcn}
_STRUCTURES = {'gcn': _gcn_structure, 'graphsage': lambda graphs: _mean_operator(graphs.adjacency),
               'rgcn': lambda graphs: _mean_operator(graphs.relation_adjacency)}  # [G, R, N, N]
GRAPH_BACKBONES = frozenset({*_CONVOLUTIONS, 'gat'})


def _layers(weights: Mapping[str, np.ndarray]) -> int:
    return len({name.split('.')[1] for name in weights if name.startswith('convs.')})


def graph_serving_form(name: str, weights: Mapping[str, np.ndarray]) -> Callable[[Sequence[SceneGraph]], np.ndarray]:
    """The encoder ``name`` (a registered graph backbone) with ``weights`` (its state dict
    as float32 arrays) as a function of a list of scene graphs returning h [graphs, out_dim]
    (float32). The arrays are used as given: pass a copy if they may change."""
    layers = [_Layer(weights, f'convs.{k}.') for k in range(_layers(weights))]
    model = _Layer(weights, '')
    project, hidden_layer, output_layer = model.linear('project'), model.linear('readout.0'), model.linear('readout.2')
    if name == 'gat':
        from stars_ros.model.compiled_gat import GATKernel  # numba: only for GAT

        heads, channels = layers[0]['att_src'].shape[1:]
        return GATKernel(project, [conv.linear('lin')[0] for conv in layers],
                         [conv['att_src'].reshape(heads, channels) for conv in layers],
                         [conv['att_dst'].reshape(heads, channels) for conv in layers],
                         [conv['bias'] for conv in layers], GAT_NEGATIVE_SLOPE, hidden_layer, output_layer)
    if name not in _CONVOLUTIONS:
        raise ValueError(f"no serving form for graph backbone '{name}'; these have one: {sorted(GRAPH_BACKBONES)}")
    convolutions = [_CONVOLUTIONS[name](conv) for conv in layers]
    structure_of = _STRUCTURES.get(name, lambda graphs: graphs.adjacency)
    relations = len(RELATIONS) if name == 'rgcn' else None

    def encode(scene_graphs: Sequence[SceneGraph]) -> np.ndarray:
        graphs = dense_graphs(scene_graphs, relations)
        h = _relu(graphs.x @ project[0] + project[1])
        structure = structure_of(graphs)
        for convolution in convolutions:
            h = h + _relu(convolution(h, structure))
        mask = graphs.mask[..., None].astype(h.dtype)  # padding nodes never reach real ones
        pooled = (h * mask).sum(1) / mask.sum(1)
        state = np.concatenate([h[:, 0], pooled], axis=1)
        return _relu(state @ hidden_layer[0] + hidden_layer[1]) @ output_layer[0] + output_layer[1]

    return encode
