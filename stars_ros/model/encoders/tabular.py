"""Tabular backbones over one feature vector per scene (e.g. MannersDB+).

Inputs arrive standardised with training-split statistics (see ``model.StarsModel``).
"""
from __future__ import annotations

import torch
from torch import nn

from stars_ros.model.encoders.base import Encoder, register


def _mlp(sizes, dropout):
    layers = []
    for a, b in zip(sizes[:-1], sizes[1:]):
        layers += [nn.Linear(a, b), nn.ReLU(), nn.Dropout(dropout)]
    return nn.Sequential(*layers)


class TabularEncoder(Encoder):
    input_kind = 'tabular'


@register('mlp')
class MLP(TabularEncoder):
    def __init__(self, in_dim, out_dim, hidden=64, layers=3, dropout=0.0):
        super().__init__(in_dim, out_dim, hidden, layers, dropout)
        self.body = _mlp([in_dim] + [hidden] * layers, dropout)
        self.out = nn.Linear(hidden, out_dim)

    def forward(self, x):
        return self.out(self.body(x))


@register('resmlp')
class ResMLP(TabularEncoder):
    """Pre-norm residual blocks: x + Linear(Dropout(ReLU(Linear(LayerNorm(x)))))."""

    def __init__(self, in_dim, out_dim, hidden=64, layers=3, dropout=0.0):
        super().__init__(in_dim, out_dim, hidden, layers, dropout)
        self.project = nn.Linear(in_dim, hidden)
        self.blocks = nn.ModuleList(
            nn.Sequential(nn.LayerNorm(hidden), nn.Linear(hidden, 2 * hidden), nn.ReLU(),
                          nn.Dropout(dropout), nn.Linear(2 * hidden, hidden))
            for _ in range(layers))
        self.out = nn.Sequential(nn.LayerNorm(hidden), nn.ReLU(), nn.Linear(hidden, out_dim))

    def forward(self, x):
        h = self.project(x)
        for block in self.blocks:
            h = h + block(h)
        return self.out(h)


@register('dcnv2')
class DCNv2(TabularEncoder):
    """Deep & Cross Network v2: ``layers`` full-rank cross layers x0 ⊙ (W x + b) + x beside
    a deep MLP; the two are concatenated."""

    def __init__(self, in_dim, out_dim, hidden=64, layers=3, dropout=0.0):
        super().__init__(in_dim, out_dim, hidden, layers, dropout)
        self.cross = nn.ModuleList(nn.Linear(in_dim, in_dim) for _ in range(layers))
        self.deep = _mlp([in_dim] + [hidden] * layers, dropout)
        self.out = nn.Linear(in_dim + hidden, out_dim)

    def forward(self, x):
        crossed = x
        for layer in self.cross:
            crossed = x * layer(crossed) + crossed
        return self.out(torch.cat([crossed, self.deep(x)], dim=1))


@register('graceae')
class GraceAE(TabularEncoder):
    """Denoising-autoencoder backbone: the code of a corrupted input is h_i, and the
    reconstruction of the clean input is an auxiliary training loss.

    Args:
        noise (float, optional): std of the Gaussian corruption in training. (default: ``0.1``)
    """

    def __init__(self, in_dim, out_dim, hidden=64, layers=3, dropout=0.0, noise=0.1):
        super().__init__(in_dim, out_dim, hidden, layers, dropout)
        self.noise = noise
        self.encode = nn.Sequential(_mlp([in_dim] + [hidden] * layers, dropout), nn.Linear(hidden, out_dim))
        self.decode = nn.Sequential(_mlp([out_dim] + [hidden] * layers, dropout), nn.Linear(hidden, in_dim))
        self._reconstruction = None

    def forward(self, x):
        corrupted = x + self.noise * torch.randn_like(x) if self.training else x
        code = self.encode(corrupted)
        if self.training:
            self._reconstruction = nn.functional.mse_loss(self.decode(code), x)
        return code

    def auxiliary_loss(self):
        """The last training forward's reconstruction loss, handed over once: holding on to it
        would keep its graph, and a copy of the model mid-training (the posterior head's
        curve points) cannot copy a tensor that is not a graph leaf."""
        loss, self._reconstruction = self._reconstruction, None
        return loss if self.training else None


@register('fttransformer')
class FTTransformer(TabularEncoder):
    """Feature-tokeniser transformer: each feature becomes a token (x_j w_j + b_j), a
    learned [CLS] token is prepended, and its final state gives h_i.

    Args:
        heads (int, optional): attention heads. (default: ``4``)
    """

    def __init__(self, in_dim, out_dim, hidden=64, layers=3, dropout=0.0, heads=4):
        super().__init__(in_dim, out_dim, hidden, layers, dropout)
        self.weight = nn.Parameter(torch.randn(in_dim, hidden) / hidden ** 0.5)
        self.bias = nn.Parameter(torch.zeros(in_dim, hidden))
        self.cls = nn.Parameter(torch.randn(1, 1, hidden) / hidden ** 0.5)
        layer = nn.TransformerEncoderLayer(hidden, heads, dim_feedforward=2 * hidden, dropout=dropout,
                                           batch_first=True, norm_first=True)
        self.transformer = nn.TransformerEncoder(layer, layers, enable_nested_tensor=False)
        self.out = nn.Sequential(nn.LayerNorm(hidden), nn.ReLU(), nn.Linear(hidden, out_dim))

    def forward(self, x):
        tokens = x.unsqueeze(-1) * self.weight + self.bias
        tokens = torch.cat([self.cls.expand(len(x), -1, -1), tokens], dim=1)
        return self.out(self.transformer(tokens)[:, 0])
