"""The trained model's serving arithmetic in numpy, over a snapshot of its weights.

A request scores one or a few scenes. At that size each tensor operation's fixed cost is
the whole cost (torch's dispatch ~3–6 µs an operation on this machine, nn.Module calls
more, numpy 1–5 µs), so serving and the fold-in do not go through torch: graph encoders
run their serving form (``GraphEncoder.serving_form``: GAT compiled, the others their
dense numpy form) and the StARS scoring is two array products. Tabular encoders keep
their torch forward: one row through a few layers has no graph bookkeeping to save.
``test/test_inference.py`` checks that the result equals ``StarsModel`` within float32
rounding.
"""
from __future__ import annotations

import numpy as np
import torch

from .model import UNKNOWN, StarsModel


def _array(tensor: torch.Tensor) -> np.ndarray:
    return tensor.detach().to(torch.float32).numpy().copy()


class InferenceModel:
    """``StarsModel`` for scoring only: ``encode`` scene inputs, then ``scores`` on the
    rating scale. Built once per loaded checkpoint (the weights are copied)."""

    def __init__(self, model: StarsModel):
        self.dim = model.encoder.out_dim
        self.uses_content = model.uses_content
        self.personalised = model.personalised
        self.residual = model.residual
        self._target_mean = _array(model.target_mean).astype(np.float64)
        self._target_std = _array(model.target_std).astype(np.float64)
        if self.personalised:
            self.user_rows = _array(model.user_embedding.weight)
            self.user_offsets = _array(model.user_bias.weight)[:, 0]
            self._scene_rows = _array(model.scene_embedding.weight)
            self._scene_offsets = _array(model.scene_bias.weight)[:, 0]
            self._actions_t = _array(model.action_embedding).T.copy()  # [dim, actions]
            self._bias = float(model.bias.detach())
        else:
            self._head = (_array(model.head.weight).T.copy(), _array(model.head.bias))
        if model.encoder.input_kind == 'graph':
            self._encode = model.encoder.serving_form()
        else:
            self._encode = self._torch_encoder(model)

    @staticmethod
    def _torch_encoder(model: StarsModel):
        def encode(features: np.ndarray) -> np.ndarray:
            with torch.inference_mode():
                return model.encode(torch.from_numpy(features)).numpy()
        return encode

    def encode(self, scene_input, count: int) -> np.ndarray:
        """h [count, dim] (float32) of a list of SceneGraph or a [count, features] array."""
        if not self.uses_content:
            return np.zeros((count, self.dim), dtype=np.float32)
        return np.asarray(self._encode(scene_input), dtype=np.float32)

    def scores(self, h: np.ndarray, user_rows: tuple, scene_rows: np.ndarray) -> np.ndarray:
        """Rating-scale scores [R, actions] (float64) of scenes encoded as ``h`` [R, dim].

        ``user_rows`` is (p [R, dim] or [dim], b_u [R] or scalar); ``scene_rows`` [R] indexes
        the trained scene table, UNKNOWN (-1) for scenes not seen in training (q_i = 0, b_i = 0).
        """
        if self.personalised:
            p, user_offset = user_rows
            known = scene_rows != UNKNOWN
            if known.any():
                rows = np.maximum(scene_rows, 0)
                q = self._scene_rows[rows] * known[:, None]
                scene_offset = self._scene_offsets[rows] * known
            else:  # the serving case: new scenes
                q, scene_offset = 0.0, 0.0
            offsets = np.reshape(user_offset + scene_offset + self._bias, (-1, 1))  # [R, 1] or [1, 1]
            interaction = p * (q + h) + h if self.residual else p * (q + h)
            z = interaction @ self._actions_t + offsets
        else:
            z = h @ self._head[0] + self._head[1]
        return z.astype(np.float64) * self._target_std + self._target_mean
