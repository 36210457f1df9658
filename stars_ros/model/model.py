"""The StARS model: a scene encoder fused with multi-task matrix factorisation.

    ŷ(u, i, a) = ((p_u ⊙ (q_i + h_i)) + h_i)ᵀ r_a + b_u + b_i + b,    h_i = φθ(x_i)

The ``base`` variant is the same encoder with a linear head over the actions,
ŷ(i, a) = w_aᵀ h_i + c_a; the ``mf`` variant is StARS with h_i = 0 (biased matrix
factorisation, no scene content), a baseline that shows what the content adds. The other
variants of ``PARTS`` are ablations: StARS with some of its parts held at zero (frozen), so
each differs from the full model in the parts named and nothing else. All predict
per-action z-scores; ``target_mean`` and
``target_std`` (training-split statistics, kept as buffers so they travel with the weights)
map them back to the rating scale.

A user or scene index of -1 means "not seen in training": its embedding and offset are
exactly zero, so the prediction falls back to the content term h_iᵀ r_a and the population
offsets, never to an untrained random row.
"""
from __future__ import annotations

import torch
from torch import nn

from stars_ros.model.config import VARIANTS, ModelConfig
from stars_ros.model.encoders import Encoder


def _lookup(table: nn.Embedding, index: torch.Tensor) -> torch.Tensor:
    """Rows of ``table`` for ``index``, zeros where ``index`` is UNKNOWN."""
    known = (index >= 0).unsqueeze(-1)
    return table(index.clamp(min=0)) * known


class StarsModel(nn.Module):
    """Encoder + (personalised) scoring; ``forward`` returns z-scores for every action.

    Args:
        encoder (Encoder): φθ, output size ``dim``.
        n_users (int): users seen in training (rows of p and b_u).
        n_scenes (int): scenes seen in training (rows of q and b_i).
        n_actions (int): actions (targets).
        variant (str): ``'base'`` or a key of ``PARTS`` (``'stars'``, ``'mf'``, ablations).
        feature_dim (int, optional): for tabular encoders, the size of the input
            standardisation buffers. (default: ``None``, no standardisation)

    Shapes:
        forward(users [R], scenes [R], h [R, dim]) -> [R, n_actions]
    """

    def __init__(self, encoder: Encoder, n_users: int, n_scenes: int, n_actions: int,
                 variant: str, feature_dim: int | None = None):
        super().__init__()
        dim = encoder.out_dim
        self.encoder = encoder
        self.variant = variant
        if variant not in VARIANTS:
            raise ValueError(f"Could not resolve variant '{variant}' among choices {list(VARIANTS)}")
        self.personalised = variant != 'base'
        self.parts = ModelConfig(variant=variant).parts
        self.uses_content = 'content' in self.parts
        self.residual = 'residual' in self.parts
        self.n_actions = n_actions
        self.register_buffer('target_mean', torch.zeros(n_actions))
        self.register_buffer('target_std', torch.ones(n_actions))
        if feature_dim is not None:
            self.register_buffer('feature_mean', torch.zeros(feature_dim))
            self.register_buffer('feature_std', torch.ones(feature_dim))
        if self.personalised:
            self.user_embedding = nn.Embedding(max(n_users, 1), dim)
            self.scene_embedding = nn.Embedding(max(n_scenes, 1), dim)
            self.user_bias = nn.Embedding(max(n_users, 1), 1)
            self.scene_bias = nn.Embedding(max(n_scenes, 1), 1)
            self.action_embedding = nn.Parameter(torch.empty(n_actions, dim))
            self.bias = nn.Parameter(torch.zeros(1))
        else:
            self.head = nn.Linear(dim, n_actions)
        self.reset_parameters()

    def reset_parameters(self):
        if self.personalised:
            # With content, p_u starts at zero: the model starts as the scene-only model and p_u
            # still learns (its gradient carries h_i). Without content p = q = 0 would be a saddle.
            if self.uses_content:
                nn.init.zeros_(self.user_embedding.weight)
            else:
                nn.init.normal_(self.user_embedding.weight, std=0.01)
            nn.init.zeros_(self.scene_embedding.weight)
            nn.init.zeros_(self.user_bias.weight)
            nn.init.zeros_(self.scene_bias.weight)
            nn.init.normal_(self.action_embedding, std=self.encoder.out_dim ** -0.5)
            nn.init.zeros_(self.bias)
            for part, table in (('p', self.user_embedding), ('q', self.scene_embedding),
                                ('b_u', self.user_bias), ('b_i', self.scene_bias)):
                if part not in self.parts:  # held at zero: an ablation without this part
                    nn.init.zeros_(table.weight)
                    table.weight.requires_grad_(False)

    @torch.no_grad()
    def start_from_head(self, head: nn.Linear) -> None:
        """Hand over from pre-training: r_a = w_a and b = mean c_a of the pre-trained head.

        With p_u = q_i = 0 and b_u = b_i = 0 (their initial values) the personalised model then
        starts where the scene-only model ended (exactly, for one action; for several, up to
        the spread of the head's per-action intercepts around their mean, ~0 on z-scored
        targets), so joint training adds the collaborative part to a working content model
        instead of re-learning the head."""
        self.action_embedding.copy_(head.weight)
        self.bias.fill_(float(head.bias.mean()))

    @property
    def device(self) -> torch.device:
        """Where the weights are (every model has the ``target_mean`` buffer)."""
        return self.target_mean.device

    def encode(self, scene_input) -> torch.Tensor:
        """h_i for a batch of scenes (tabular inputs are standardised first; zeros for ``mf``)."""
        if not self.uses_content:
            count = scene_input.num_graphs if hasattr(scene_input, 'num_graphs') else len(scene_input)
            return torch.zeros(count, self.encoder.out_dim, device=self.device)
        if hasattr(self, 'feature_mean'):
            scene_input = (scene_input - self.feature_mean) / self.feature_std
        return self.encoder(scene_input)

    def forward(self, users: torch.Tensor, scenes: torch.Tensor, h: torch.Tensor,
                user_rows: tuple | None = None) -> torch.Tensor:
        """``user_rows`` (p [R, dim], b_u [R, 1]) replaces the table lookup of ``users``:
        how users folded in after training (stars_ros.personalisation.foldin) are scored."""
        if not self.personalised:
            return self.head(h)
        p, user_bias = user_rows if user_rows is not None else (
            _lookup(self.user_embedding, users), _lookup(self.user_bias, users))
        q = _lookup(self.scene_embedding, scenes)
        offsets = user_bias + _lookup(self.scene_bias, scenes) + self.bias
        interaction = p * (q + h) + h if self.residual else p * (q + h)
        return interaction @ self.action_embedding.T + offsets

    def embedding_penalty(self, users: torch.Tensor, scenes: torch.Tensor) -> torch.Tensor:
        """Mean squared norm of the user and scene rows (and offsets) a batch touches: the
        classic matrix-factorisation L2, which keeps q_i from memorising the one or two
        ratings most scenes have."""
        if not self.personalised:
            return torch.zeros((), device=self.device)
        rows = (_lookup(self.user_embedding, users), _lookup(self.scene_embedding, scenes),
                _lookup(self.user_bias, users), _lookup(self.scene_bias, scenes))
        return sum(row.pow(2).sum(1).mean() for row in rows)

    def to_rating_scale(self, z: torch.Tensor) -> torch.Tensor:
        return z * self.target_std + self.target_mean

    def to_z(self, scores: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        return (scores - self.target_mean[actions]) / self.target_std[actions]
