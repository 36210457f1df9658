"""Graph backbones over scene graphs (torch-geometric convolutions), for training.

All share ``GraphEncoder``: input projection, ``layers`` residual convolutions, and a
readout that concatenates the robot node's state with the mean over all nodes (the
question is how appropriate the *robot's* behaviour is, so its node is kept apart).

Training runs PyG's sparse convolutions over big batches. Serving runs each backbone's one
numpy form (``serving_forms``), built from the weights alone, so a checkpoint is served
without this module; ``serving_form`` builds it from this encoder's current weights.
"""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
import torch
from torch import nn
from torch_geometric import nn as gnn

from stars_ros.data.scene_graph import RELATIONS, SceneGraph
from stars_ros.data.scene_store import GraphBatch
from stars_ros.model.encoders.base import Encoder, register
from stars_ros.model.serving_forms import GAT_NEGATIVE_SLOPE, graph_serving_form


def _weights(module: nn.Module) -> dict:
    """``module``'s state dict as float32 arrays (copies: later training does not reach them)."""
    return {name: value.detach().to(torch.float32).numpy().copy() for name, value in module.state_dict().items()}


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
        does not reach it (``serving_forms.graph_serving_form``)."""
        return graph_serving_form(self.registry_name, _weights(self))


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
        return gnn.GATConv(hidden, hidden // heads, heads=heads, negative_slope=GAT_NEGATIVE_SLOPE)
