"""The interface every scene encoder implements, and the registry they join."""
from __future__ import annotations

from typing import ClassVar

import torch
from torch import nn

ENCODERS: dict = {}


def register(name: str):
    """Class decorator adding a backbone to ``ENCODERS`` under its normalised name."""
    def add(cls):
        ENCODERS[name] = cls
        cls.registry_name = name
        return cls
    return add


class Encoder(nn.Module):
    """Maps a batch of scenes to h_i ∈ R^out_dim.

    Args:
        in_dim (int): features per node (graphs) or per scene (tabular).
        out_dim (int): size of h_i.
        hidden (int, optional): internal width. (default: ``64``)
        layers (int, optional): message-passing layers or blocks. (default: ``3``)
        dropout (float, optional): dropout probability. (default: ``0.0``)

    Shapes:
        input: a ``GraphBatch`` of G graphs (``input_kind == 'graph'``) or a [G, in_dim]
        tensor (``'tabular'``); output: [G, out_dim].
    """

    input_kind: ClassVar[str]
    registry_name: ClassVar[str]

    def __init__(self, in_dim: int, out_dim: int, hidden: int = 64, layers: int = 3,
                 dropout: float = 0.0):
        super().__init__()
        if min(in_dim, out_dim, hidden, layers) < 1:
            raise ValueError('in_dim, out_dim, hidden and layers must be positive')
        self.in_dim, self.out_dim, self.hidden, self.layers = in_dim, out_dim, hidden, layers
        self.dropout = dropout

    def auxiliary_loss(self) -> torch.Tensor | None:
        """Extra training loss of the last forward pass (e.g. reconstruction), if any."""
        return None

    def __repr__(self) -> str:
        return f'{type(self).__name__}({self.in_dim}, {self.out_dim}, hidden={self.hidden}, layers={self.layers})'
