"""Graph backbones over scene graphs (torch-geometric convolutions).

All share ``GraphEncoder``: input projection, ``layers`` residual convolutions, and a
readout that concatenates the robot node's state with the mean over all nodes (the
question is how appropriate the *robot's* behaviour is, so its node is kept apart).
A backbone only says which convolution it uses (``init_conv``).
"""
from __future__ import annotations

import torch
from torch import nn
from torch_geometric import nn as gnn

from ..scene_graph import RELATIONS
from ..scene_store import GraphBatch
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


@register('gcn')
class GCN(GraphEncoder):
    def init_conv(self, hidden):
        return gnn.GCNConv(hidden, hidden)


@register('gin')
class GIN(GraphEncoder):
    def init_conv(self, hidden):
        return gnn.GINConv(nn.Sequential(nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, hidden)),
                           train_eps=True)


@register('graphsage')
class GraphSAGE(GraphEncoder):
    def init_conv(self, hidden):
        return gnn.SAGEConv(hidden, hidden)


@register('ggnn')
class GGNN(GraphEncoder):
    """Gated graph network: one GRU-gated propagation step per layer."""

    def init_conv(self, hidden):
        return gnn.GatedGraphConv(hidden, num_layers=1)


@register('rgcn')
class RGCN(GraphEncoder):
    """Relational GCN: one weight matrix per edge type of ``scene_graph.RELATIONS``."""

    uses_edge_type = True

    def init_conv(self, hidden, num_bases=None):
        return gnn.RGCNConv(hidden, hidden, num_relations=len(RELATIONS), num_bases=num_bases)


@register('gat')
class GAT(GraphEncoder):
    """Graph attention; ``heads`` attention heads of ``hidden // heads`` channels each."""

    def init_conv(self, hidden, heads=4):
        if hidden % heads:
            raise ValueError(f'hidden ({hidden}) must be divisible by heads ({heads})')
        return gnn.GATConv(hidden, hidden // heads, heads=heads)
