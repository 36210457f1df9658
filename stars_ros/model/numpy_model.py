"""The trained model's serving arithmetic in numpy, over a snapshot of its weights.

A request scores one or a few scenes, where each tensor operation's fixed cost (torch's
dispatch, nn.Module calls) is the whole cost, so serving and the fold-in do not go through
torch: graph encoders run their serving form (``model.serving_forms``: GAT compiled,
the others their dense numpy form) and the StARS scoring is two array products. Tabular
encoders keep their torch forward: one row through a few layers has no graph bookkeeping
to save. ``InferenceModel`` holds the one numpy copy of the weights: the Predictor scores
with it and ``stars_ros.personalisation.foldin`` builds its regression from it (``linear_form``).
``model.serving`` builds it from a checkpoint's weights; ``test/model/test_inference.py``
checks that the result equals ``StarsModel`` within float32 rounding.
"""
from __future__ import annotations

from typing import Callable, Mapping

import numpy as np

from stars_ros.model.config import ModelConfig
from stars_ros.model.vocabulary import UNKNOWN


def _array(value: np.ndarray) -> np.ndarray:
    return np.array(value, dtype=np.float32)


class InferenceModel:
    """``StarsModel`` for scoring only: ``encode`` scene inputs, then ``scores`` on the
    rating scale. Built once per loaded checkpoint from its weights (copied), never from a
    torch model: serving needs no module of training.

    Args:
        state (Mapping): the model's state dict as numpy arrays (names as ``StarsModel`` has them).
        variant (str): the model variant (``ModelConfig.variant``).
        dim (int): size of h_i, p_u, q_i and r_a.
        encode (callable): the encoder's serving form, scene inputs -> h [count, dim]
            (``serving.encoder_serving_form``).

    The weights are public, read-only float32 arrays: ``target_mean``, ``target_std``
    [actions] (float64) and, for personalised variants, ``user_rows`` [users, dim],
    ``user_offsets`` [users], ``scene_rows`` [scenes, dim], ``scene_offsets`` [scenes],
    ``action_rows`` [actions, dim] (r_a) and ``bias`` (b).
    """

    def __init__(self, state: Mapping[str, np.ndarray], variant: str, dim: int, encode: Callable):
        parts = ModelConfig(variant=variant).parts
        self.dim = dim
        self.uses_content = 'content' in parts
        self.personalised = variant != 'base'
        self.residual = 'residual' in parts
        self.target_mean = _array(state['target_mean']).astype(np.float64)
        self.target_std = _array(state['target_std']).astype(np.float64)
        if self.personalised:
            self.user_rows = _array(state['user_embedding.weight'])
            self.user_offsets = _array(state['user_bias.weight'])[:, 0]
            self.scene_rows = _array(state['scene_embedding.weight'])
            self.scene_offsets = _array(state['scene_bias.weight'])[:, 0]
            self.action_rows = _array(state['action_embedding'])
            self._actions_t = self.action_rows.T.copy()  # [dim, actions], contiguous for the product
            self.bias = float(state['bias'][0])
            for array in (self.user_rows, self.user_offsets, self.scene_rows, self.scene_offsets, self.action_rows):
                array.flags.writeable = False
        else:
            self._head = (_array(state['head.weight']).T.copy(), _array(state['head.bias']))
        self.target_mean.flags.writeable = self.target_std.flags.writeable = False
        width = self.action_rows.shape[1] if self.personalised else self._head[0].shape[0]
        if width != dim:  # weights of another model than the config describes
            raise ValueError(f'the weights are {width} wide, the config says dim {dim}')
        self._encode = encode

    def encode(self, scene_input, count: int) -> np.ndarray:
        """h [count, dim] (float32) of a list of SceneGraph or a [count, features] array."""
        if not self.uses_content:
            return np.zeros((count, self.dim), dtype=np.float32)
        return np.asarray(self._encode(scene_input), dtype=np.float32)

    def scene_terms(self, scene_rows: np.ndarray) -> tuple:
        """(q_i [R, dim], b_i [R]) of ``scene_rows`` [R] of the trained scene table: zero for
        UNKNOWN (-1), a scene not seen in training (then the scalars 0.0, 0.0 if no row is known)."""
        known = scene_rows != UNKNOWN
        if not known.any():  # the serving case: new scenes
            return 0.0, 0.0
        rows = np.maximum(scene_rows, 0)
        return self.scene_rows[rows] * known[:, None], self.scene_offsets[rows] * known

    def scores(self, h: np.ndarray, user_rows: tuple, scene_rows: np.ndarray) -> np.ndarray:
        """Rating-scale scores [R, actions] (float64) of scenes encoded as ``h`` [R, dim].

        ``user_rows`` is (p [R, dim] or [dim], b_u [R] or scalar); ``scene_rows`` [R] indexes
        the trained scene table, UNKNOWN (-1) for scenes not seen in training (q_i = 0, b_i = 0).
        """
        if self.personalised:
            p, user_offset = user_rows
            q, scene_offset = self.scene_terms(scene_rows)
            offsets = np.reshape(user_offset + scene_offset + self.bias, (-1, 1))  # [R, 1] or [1, 1]
            interaction = p * (q + h) + h if self.residual else p * (q + h)
            z = interaction @ self._actions_t + offsets
        else:
            z = h @ self._head[0] + self._head[1]
        return z.astype(np.float64) * self.target_std + self.target_mean

    def linear_form(self, h: np.ndarray, scene_rows: np.ndarray, actions: np.ndarray) -> tuple:
        """``scores``' z of one (scene, action) per row as a linear function of the user's
        θ = (p_u, b_u): z = xᵀθ + c with x = [(q_i + h_i) ⊙ r_a, 1] and
        c = h_iᵀ r_a (only for residual variants) + b_i + b. Returns (x [R, dim+1], c [R])
        in ``h``'s precision (pass float64 h for a solve)."""
        if not self.personalised:
            raise ValueError('a model without users has no user term')
        q, scene_offset = self.scene_terms(scene_rows)
        r = self.action_rows[actions]
        x = np.empty((len(h), h.shape[1] + 1), dtype=h.dtype)
        np.multiply(q + h, r, out=x[:, :-1])
        x[:, -1] = 1.0
        content = (h * r).sum(1) if self.residual else np.zeros(len(h), dtype=h.dtype)
        return x, content + np.asarray(scene_offset, dtype=h.dtype) + self.bias

    def to_z(self, scores, actions: np.ndarray) -> np.ndarray:
        """Normalised scores (float64) of rating-scale ``scores`` of ``actions``."""
        return (np.asarray(scores, dtype=np.float64) - self.target_mean[actions]) / self.target_std[actions]

    def to_rating_scale(self, z, actions: np.ndarray) -> np.ndarray:
        """Rating-scale scores (float64) of normalised ``z`` [R] of ``actions`` [R]."""
        return np.asarray(z, dtype=np.float64) * self.target_std[actions] + self.target_mean[actions]
