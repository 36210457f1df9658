"""Graph backbones over scene graphs (torch-geometric convolutions).

All share ``GraphEncoder``: input projection, ``layers`` residual convolutions, and a
readout that concatenates the robot node's state with the mean over all nodes (the
question is how appropriate the *robot's* behaviour is, so its node is kept apart).

Training runs PyG's sparse convolutions over big batches. Serving scores one or a few
scenes of ~20 nodes, where each tensor operation's fixed cost is the whole cost (PyG's
per-call bookkeeping, torch's dispatch, nn.Module calls), so every backbone has exactly one
numpy serving form, ``serving_form``, over a snapshot of its weights:

- ``DenseGraphEncoder`` backbones (GCN, GIN, GraphSAGE, GGNN, RGCN) run a padded dense
  batch: each says how its convolution reads it through ``dense_weights`` (its parameters
  as float32 arrays, in the layout the dense form multiplies by), ``dense_structure`` (the
  matrix its layers multiply by, computed once per batch) and ``dense_conv``;
- GAT runs the whole encoder compiled into one call (``compiled_gat``).

``test/model/test_dense_encoders.py`` checks every serving form against the PyG form. Both rely
on what ``featurise`` guarantees: no self loops.
"""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
import torch
from torch import nn
from torch_geometric import nn as gnn

from stars_ros.data.scene_graph import RELATIONS, SceneGraph
from stars_ros.data.scene_store import DenseGraphs, GraphBatch, dense_graphs
from stars_ros.model.encoders.base import Encoder, register
from stars_ros.model.encoders.compiled_gat import GATKernel


def _array(tensor: torch.Tensor | None) -> np.ndarray | float:
    """A parameter as a float32 array (0.0 for an absent bias, which then adds nothing)."""
    return 0.0 if tensor is None else tensor.detach().to(torch.float32).numpy().copy()


def _linear(layer: nn.Module) -> tuple:
    """(weightᵀ, bias) of a torch or PyG Linear, so that ``x @ w + b`` applies it."""
    return _array(layer.weight).T.copy(), _array(layer.bias)


def _relu(x: np.ndarray) -> np.ndarray:
    return np.maximum(x, 0.0)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x))


class GraphEncoder(Encoder):
    input_kind = 'graph'
    uses_edge_type = False

    def __init__(self, in_dim, out_dim, hidden=64, layers=3, dropout=0.0, **options):
        super().__init__(in_dim, out_dim, hidden, layers, dropout)
        self.project = nn.Linear(in_dim, hidden)
        self.convs = nn.ModuleList(self.init_conv(hidden, **options) for _ in range(layers))
        self.readout = nn.Sequential(nn.Linear(2 * hidden, hidden), nn.ReLU(), nn.Linear(hidden, out_dim))
        self.drop = nn.Dropout(dropout)

    def init_conv(self, hidden: int, **options) -> nn.Module:
        raise NotImplementedError

    def forward(self, graphs: GraphBatch) -> torch.Tensor:
        h = torch.relu(self.project(graphs.x))
        for conv in self.convs:
            if self.uses_edge_type:
                update = conv(h, graphs.edge_index, graphs.edge_type)
            else:
                update = conv(h, graphs.edge_index)
            h = h + self.drop(torch.relu(update))
        pooled = gnn.global_mean_pool(h, graphs.batch, size=graphs.num_graphs)
        return self.readout(torch.cat([h[graphs.root], pooled], dim=1))

    def serving_form(self) -> Callable[[Sequence[SceneGraph]], np.ndarray]:
        """This encoder (in eval mode) as a numpy function of a list of scene graphs returning
        h [graphs, out_dim] (float32), over a copy of the current weights: later training
        does not reach it."""
        raise NotImplementedError


class DenseGraphEncoder(GraphEncoder):
    """A graph backbone served by its dense numpy form: padded graphs (``DenseGraphs``),
    each convolution given by ``dense_weights``, ``dense_structure`` and ``dense_conv``."""

    def dense_weights(self, conv: nn.Module) -> dict:
        """``conv``'s parameters as float32 arrays, as ``dense_conv`` uses them."""
        raise NotImplementedError

    def dense_structure(self, graphs: DenseGraphs) -> np.ndarray:
        """What ``dense_conv`` needs of the graphs, shared by all layers (default: adjacency)."""
        return graphs.adjacency

    def dense_conv(self, weights: dict, h: np.ndarray, structure: np.ndarray) -> np.ndarray:
        """The convolution applied to node states ``h`` [G, N, hidden] of padded graphs."""
        raise NotImplementedError

    def serving_form(self) -> Callable[[Sequence[SceneGraph]], np.ndarray]:
        project = _linear(self.project)
        convs = [self.dense_weights(conv) for conv in self.convs]
        hidden_layer, output_layer = _linear(self.readout[0]), _linear(self.readout[2])
        relations = len(RELATIONS) if self.uses_edge_type else None

        def encode(scene_graphs: Sequence[SceneGraph]) -> np.ndarray:
            graphs = dense_graphs(scene_graphs, relations)
            h = _relu(graphs.x @ project[0] + project[1])
            structure = self.dense_structure(graphs)
            for weights in convs:
                h = h + _relu(self.dense_conv(weights, h, structure))
            mask = graphs.mask[..., None].astype(h.dtype)  # padding nodes never reach real ones
            pooled = (h * mask).sum(1) / mask.sum(1)
            state = np.concatenate([h[:, 0], pooled], axis=1)
            return _relu(state @ hidden_layer[0] + hidden_layer[1]) @ output_layer[0] + output_layer[1]

        return encode


def _mean_operator(adjacency: np.ndarray) -> np.ndarray:
    """Rows scaled so that multiplying averages the incoming neighbours (zero without
    any), PyG's aggr='mean'."""
    return adjacency / np.maximum(adjacency.sum(-1, keepdims=True), 1.0)


def _with_self_loops(adjacency: np.ndarray) -> np.ndarray:
    return adjacency + np.eye(adjacency.shape[-1], dtype=adjacency.dtype)


@register('gcn')
class GCN(DenseGraphEncoder):
    def init_conv(self, hidden):
        return gnn.GCNConv(hidden, hidden)

    def dense_weights(self, conv):
        return {'weight': _linear(conv.lin)[0], 'bias': _array(conv.bias)}

    def dense_structure(self, graphs):
        adjacency = _with_self_loops(graphs.adjacency)
        scale = 1.0 / np.sqrt(adjacency.sum(-1))  # in-degree with the self loop, as gcn_norm
        return scale[..., :, None] * adjacency * scale[..., None, :]

    def dense_conv(self, weights, h, structure):
        return structure @ (h @ weights['weight']) + weights['bias']


@register('gin')
class GIN(DenseGraphEncoder):
    def init_conv(self, hidden):
        return gnn.GINConv(nn.Sequential(nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, hidden)),
                           train_eps=True)

    def dense_weights(self, conv):
        return {'eps': float(conv.eps.detach()), 'first': _linear(conv.nn[0]), 'second': _linear(conv.nn[2])}

    def dense_conv(self, weights, h, structure):
        (w1, b1), (w2, b2) = weights['first'], weights['second']
        return _relu(((1 + weights['eps']) * h + structure @ h) @ w1 + b1) @ w2 + b2


@register('graphsage')
class GraphSAGE(DenseGraphEncoder):
    def init_conv(self, hidden):
        return gnn.SAGEConv(hidden, hidden)

    def dense_weights(self, conv):
        return {'neighbours': _linear(conv.lin_l), 'own': _linear(conv.lin_r)}

    def dense_structure(self, graphs):
        return _mean_operator(graphs.adjacency)

    def dense_conv(self, weights, h, structure):
        (wl, bl), (wr, br) = weights['neighbours'], weights['own']
        return (structure @ h) @ wl + bl + h @ wr + br


@register('ggnn')
class GGNN(DenseGraphEncoder):
    """Gated graph network: one GRU-gated propagation step per layer."""

    def init_conv(self, hidden):
        return gnn.GatedGraphConv(hidden, num_layers=1)

    def dense_weights(self, conv):
        rnn = conv.rnn
        return {'message': _array(conv.weight[0]), 'input': (_array(rnn.weight_ih).T.copy(), _array(rnn.bias_ih)),
                'state': (_array(rnn.weight_hh).T.copy(), _array(rnn.bias_hh))}

    def dense_conv(self, weights, h, structure):
        messages = structure @ (h @ weights['message'])
        (wi, bi), (wh, bh) = weights['input'], weights['state']
        gates_in, gates_state = messages @ wi + bi, h @ wh + bh  # torch.nn.GRUCell: reset, update, new
        reset_in, update_in, new_in = np.split(gates_in, 3, axis=-1)
        reset_state, update_state, new_state = np.split(gates_state, 3, axis=-1)
        reset, update = _sigmoid(reset_in + reset_state), _sigmoid(update_in + update_state)
        candidate = np.tanh(new_in + reset * new_state)
        return (1 - update) * candidate + update * h


@register('rgcn')
class RGCN(DenseGraphEncoder):
    """Relational GCN: one weight matrix per edge type of ``scene_graph.RELATIONS``."""

    uses_edge_type = True

    def init_conv(self, hidden, num_bases=None):
        return gnn.RGCNConv(hidden, hidden, num_relations=len(RELATIONS), num_bases=num_bases)

    def dense_weights(self, conv):
        weight = conv.weight
        if conv.num_bases is not None:
            weight = (conv.comp @ weight.view(conv.num_bases, -1)).view(conv.num_relations, *weight.shape[1:])
        return {'relations': _array(weight).reshape(-1, weight.shape[-1]),  # [R * hidden, hidden]
                'root': _array(conv.root), 'bias': _array(conv.bias)}

    def dense_structure(self, graphs):
        return _mean_operator(graphs.relation_adjacency)  # [G, R, N, N]

    def dense_conv(self, weights, h, structure):
        g, n, hidden = h.shape
        per_relation = structure @ h[:, None]  # [G, R, N, hidden]
        stacked = per_relation.transpose(0, 2, 1, 3).reshape(g, n, -1)  # [G, N, R * hidden]
        return stacked @ weights['relations'] + h @ weights['root'] + weights['bias']


@register('gat')
class GAT(GraphEncoder):
    """Graph attention; ``heads`` attention heads of ``hidden // heads`` channels each."""

    def init_conv(self, hidden, heads=4):
        if hidden % heads:
            raise ValueError(f'hidden ({hidden}) must be divisible by heads ({heads})')
        return gnn.GATConv(hidden, hidden // heads, heads=heads)

    def serving_form(self):
        """The compiled kernel (``compiled_gat``): the whole encoder in one call."""
        heads, channels = self.convs[0].heads, self.convs[0].out_channels
        return GATKernel(_linear(self.project), [_linear(conv.lin)[0] for conv in self.convs],
                         [_array(conv.att_src).reshape(heads, channels) for conv in self.convs],
                         [_array(conv.att_dst).reshape(heads, channels) for conv in self.convs],
                         [_array(conv.bias) for conv in self.convs], self.convs[0].negative_slope,
                         _linear(self.readout[0]), _linear(self.readout[2]))
