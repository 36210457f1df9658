"""Graph backbones over scene graphs (torch-geometric convolutions).

All share ``GraphEncoder``: input projection, ``layers`` residual convolutions, and a
readout that concatenates the robot node's state with the mean over all nodes (the
question is how appropriate the *robot's* behaviour is, so its node is kept apart).
A backbone says which convolution it uses (``init_conv``) and how that convolution reads a
padded dense batch (``dense_structure``, the matrix its layers multiply by, computed once
per batch, and ``dense_conv``, with the convolution's own parameters). Training runs PyG's sparse
convolutions over big batches; serving scores one or a few scenes of ~20 nodes, where the
dense form computes the same function with a handful of tensor operations instead of
PyG's per-call bookkeeping (README, "Benchmarks"). ``test/test_dense_encoders.py`` checks
that both forms agree for every backbone. The dense forms rely on what ``featurise``
guarantees: no self loops.
"""
from __future__ import annotations

import torch
from torch import nn
from torch_geometric import nn as gnn

from ..scene_graph import RELATIONS
from ..scene_store import DenseGraphs, GraphBatch
from .base import Encoder, register


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

    def dense_structure(self, graphs: DenseGraphs) -> torch.Tensor:
        """What ``dense_conv`` needs of the graphs, shared by all layers (default: adjacency)."""
        return graphs.adjacency

    def dense_conv(self, conv: nn.Module, h: torch.Tensor, structure: torch.Tensor) -> torch.Tensor:
        """``conv`` applied to node states ``h`` [G, N, hidden] of padded graphs."""
        raise NotImplementedError

    def forward(self, graphs: GraphBatch | DenseGraphs) -> torch.Tensor:
        if isinstance(graphs, DenseGraphs):
            return self._forward_dense(graphs)
        h = torch.relu(self.project(graphs.x))
        for conv in self.convs:
            if self.uses_edge_type:
                update = conv(h, graphs.edge_index, graphs.edge_type)
            else:
                update = conv(h, graphs.edge_index)
            h = h + self.drop(torch.relu(update))
        pooled = gnn.global_mean_pool(h, graphs.batch, size=graphs.num_graphs)
        return self.readout(torch.cat([h[graphs.root], pooled], dim=1))

    def _forward_dense(self, graphs: DenseGraphs) -> torch.Tensor:
        h = torch.relu(self.project(graphs.x))
        structure = self.dense_structure(graphs)
        for conv in self.convs:
            h = h + self.drop(torch.relu(self.dense_conv(conv, h, structure)))
        mask = graphs.mask.unsqueeze(-1).to(h.dtype)  # padding nodes never reach real ones
        pooled = (h * mask).sum(1) / mask.sum(1)
        return self.readout(torch.cat([h[:, 0], pooled], dim=1))


def _mean_operator(adjacency: torch.Tensor) -> torch.Tensor:
    """Rows scaled so that multiplying averages the incoming neighbours (zero without
    any), PyG's aggr='mean'."""
    return adjacency / adjacency.sum(-1, keepdim=True).clamp(min=1)


def _with_self_loops(adjacency: torch.Tensor) -> torch.Tensor:
    return adjacency + torch.eye(adjacency.shape[-1], dtype=adjacency.dtype)


@register('gcn')
class GCN(GraphEncoder):
    def init_conv(self, hidden):
        return gnn.GCNConv(hidden, hidden)

    def dense_structure(self, graphs):
        adjacency = _with_self_loops(graphs.adjacency)
        scale = adjacency.sum(-1).rsqrt()  # in-degree with the self loop, as gcn_norm
        return scale.unsqueeze(-1) * adjacency * scale.unsqueeze(-2)

    def dense_conv(self, conv, h, structure):
        return structure @ conv.lin(h) + conv.bias


@register('gin')
class GIN(GraphEncoder):
    def init_conv(self, hidden):
        return gnn.GINConv(nn.Sequential(nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, hidden)),
                           train_eps=True)

    def dense_conv(self, conv, h, structure):
        return conv.nn((1 + conv.eps) * h + structure @ h)


@register('graphsage')
class GraphSAGE(GraphEncoder):
    def init_conv(self, hidden):
        return gnn.SAGEConv(hidden, hidden)

    def dense_structure(self, graphs):
        return _mean_operator(graphs.adjacency)

    def dense_conv(self, conv, h, structure):
        return conv.lin_l(structure @ h) + conv.lin_r(h)


@register('ggnn')
class GGNN(GraphEncoder):
    """Gated graph network: one GRU-gated propagation step per layer."""

    def init_conv(self, hidden):
        return gnn.GatedGraphConv(hidden, num_layers=1)

    def dense_conv(self, conv, h, structure):
        messages = structure @ (h @ conv.weight[0])
        return conv.rnn(messages.reshape(-1, h.shape[-1]), h.reshape(-1, h.shape[-1])).view_as(h)


@register('rgcn')
class RGCN(GraphEncoder):
    """Relational GCN: one weight matrix per edge type of ``scene_graph.RELATIONS``."""

    uses_edge_type = True

    def init_conv(self, hidden, num_bases=None):
        return gnn.RGCNConv(hidden, hidden, num_relations=len(RELATIONS), num_bases=num_bases)

    def dense_structure(self, graphs):
        return _mean_operator(graphs.relation_adjacency)  # [G, R, N, N]

    def dense_conv(self, conv, h, structure):
        weight = conv.weight
        if conv.num_bases is not None:
            weight = (conv.comp @ weight.view(conv.num_bases, -1)).view(conv.num_relations, *weight.shape[1:])
        per_relation = structure @ h.unsqueeze(1)  # [G, R, N, hidden]
        return torch.einsum('grnh,rhk->gnk', per_relation, weight) + h @ conv.root + conv.bias


@register('gat')
class GAT(GraphEncoder):
    """Graph attention; ``heads`` attention heads of ``hidden // heads`` channels each."""

    def init_conv(self, hidden, heads=4):
        if hidden % heads:
            raise ValueError(f'hidden ({hidden}) must be divisible by heads ({heads})')
        return gnn.GATConv(hidden, hidden // heads, heads=heads)

    def dense_structure(self, graphs):
        # GATConv adds one self loop; log gives -inf off the graph and log(k) for k parallel edges
        return torch.log(_with_self_loops(graphs.adjacency)).unsqueeze(-1)

    def dense_conv(self, conv, h, structure):
        g, n, _ = h.shape
        heads, channels = conv.heads, conv.out_channels
        values = conv.lin(h).view(g, n, heads, channels)
        source = (values * conv.att_src).sum(-1)  # [G, N, heads]
        target = (values * conv.att_dst).sum(-1)
        logits = nn.functional.leaky_relu(target.unsqueeze(2) + source.unsqueeze(1), conv.negative_slope)
        logits = logits + structure
        weights = torch.softmax(logits, dim=2).permute(0, 3, 1, 2)  # [G, heads, N (to), N (from)]
        out = weights @ values.transpose(1, 2)  # [G, heads, N, channels]
        return out.transpose(1, 2).reshape(g, n, heads * channels) + conv.bias
