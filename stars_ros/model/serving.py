"""A checkpoint in its serving form, ``ServedModel``: the one thing the node, the front door
and the offline programs score with.

It is built from a checkpoint's content alone (config, vocabularies, normalisation, rating
scale, personalisation prior and weights as numpy arrays), never from a torch model: graph
backbones run their numpy form (``model.serving_forms``, GAT compiled), so serving a
graph checkpoint imports neither torch, torch-geometric nor training; a tabular backbone's
one torch module is built from its registry entry, torch imported then (refused, naming the
``train`` extra, on a serving install without it). A model fitted in
memory is served the same way, from the content its checkpoint would hold
(``checkpoint.served_content``), so a saved and a fitted model serve identically.
"""
from __future__ import annotations

from typing import Callable, Mapping

import numpy as np

from stars_ros.errors import INSTALL_TRAIN, ConfigError, TrainExtraMissing
from stars_ros.model.checkpoint import incompatible, read_checkpoint, split_stranger, stored_prior
from stars_ros.model.config import ExperimentConfig
from stars_ros.model.backbones import normalise_name
from stars_ros.model.serving_forms import GRAPH_BACKBONES, graph_serving_form
from stars_ros.model.numpy_model import InferenceModel
from stars_ros.model.vocabulary import Rows, Vocabulary

ENCODER = 'encoder.'  # the encoder's weights sit under this prefix of the model's state dict


def encoder_serving_form(config: ExperimentConfig, input_kind: str, feature_dim: int,
                         state: Mapping[str, np.ndarray]) -> Callable:
    """The encoder ``config`` names with the weights of ``state`` (the model's state dict as
    arrays), as a function of scene inputs returning h [count, dim] (float32): a graph
    backbone's numpy form, or a tabular backbone's torch module over standardised features."""
    name = normalise_name(config.encoder.name)
    weights = {key[len(ENCODER):]: value for key, value in state.items() if key.startswith(ENCODER)}
    if input_kind == 'graph':
        if name not in GRAPH_BACKBONES:
            raise ConfigError(f"encoder '{config.encoder.name}' does not read scene graphs")
        return graph_serving_form(name, {key: np.asarray(value, dtype=np.float32) for key, value in weights.items()})
    try:
        import torch  # a tabular backbone is a torch module

        from stars_ros.model.encoders import resolve_encoder
    except ModuleNotFoundError as error:
        if (error.name or '').split('.')[0] not in ('torch', 'torch_geometric'):
            raise
        raise TrainExtraMissing(f"the tabular backbone '{config.encoder.name}' runs on {error.name}, which "
                                'this serving install leaves out (it serves graph checkpoints): '
                                f'{INSTALL_TRAIN}') from None
    with torch.random.fork_rng(devices=[]):  # its initial weights, replaced at once, draw on no one's random state
        encoder = resolve_encoder(name, feature_dim, config.model.dim, hidden=config.encoder.hidden,
                                  layers=config.encoder.layers, dropout=config.encoder.dropout,
                                  **config.encoder.options)
    encoder.load_state_dict({key: torch.from_numpy(np.array(value)) for key, value in weights.items()})
    encoder.eval()
    mean, std = torch.from_numpy(np.array(state['feature_mean'])), torch.from_numpy(np.array(state['feature_std']))
    return _numpy_form(lambda features: encoder((features - mean) / std))


def _numpy_form(forward: Callable) -> Callable:
    """A torch forward over a [count, features] tensor as a function of a numpy array."""
    import torch

    def encode(features: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return forward(torch.from_numpy(features)).numpy()
    return encode


def arrays(state: Mapping) -> dict:
    """A torch state dict as numpy arrays (copies)."""
    return {name: value.detach().cpu().numpy().copy() for name, value in state.items()}


class ServedModel(Rows):
    """What serving needs of a fitted model, read from its checkpoint's content.

    Args:
        metadata (dict): ``config``, ``users``, ``scene_keys``, ``actions``, ``input_kind``,
            ``feature_dim`` and ``rating_scale`` (a checkpoint's metadata holds them).
        state (Mapping): the model's state dict (numpy arrays).
        user_prior (dict, optional): the personalisation prior (``UserPrior.to_dict``).

    Raises ConfigError or KeyError for content this version cannot serve (``load`` says
    which file).
    """

    def __init__(self, metadata: dict, state: Mapping[str, np.ndarray], user_prior: dict | None = None):
        self.config = ExperimentConfig.from_checkpoint(metadata['config'])
        self.user_vocabulary = Vocabulary(metadata['users'])
        self.scene_vocabulary = Vocabulary(metadata['scene_keys'])
        self.action_names = tuple(metadata['actions'])
        self.input_kind, self.feature_dim = metadata['input_kind'], metadata['feature_dim']
        scale = metadata.get('rating_scale')  # absent from checkpoints written before it was kept
        self.rating_scale = tuple(scale) if scale is not None else None
        self.user_prior = user_prior
        self.variant = self.config.model.variant
        self.personalised = self.variant != 'base'
        state, stranger_state = split_stranger(state)
        self.feature_mean = np.array(state['feature_mean']) if 'feature_mean' in state else None
        self.inference = InferenceModel(state, self.variant, self.config.model.dim,
                                        encoder_serving_form(self.config, self.input_kind, self.feature_dim, state))
        self.stranger_inference = None  # the plain encoder a stranger is scored by (model.strangers)
        if self.config.model.strangers == 'base_encoder':
            if stranger_state is None:
                raise ConfigError("model.strangers is 'base_encoder', but the weights hold no stranger encoder")
            config = self.config.stranger_encoder()
            self.stranger_inference = InferenceModel(
                stranger_state, 'base', config.model.dim,
                encoder_serving_form(config, self.input_kind, self.feature_dim, stranger_state))

    @classmethod
    def load(cls, path) -> tuple:
        """(ServedModel, metadata, digest) of the checkpoint at ``path``; CheckpointError for a
        missing, truncated, corrupted or incompatible file."""
        content = read_checkpoint(path)
        try:
            served = cls(content['metadata'], content['state_dict'], stored_prior(content))
        except (ConfigError, KeyError, RuntimeError, TypeError, ValueError) as error:
            raise incompatible(path, error) from error
        return served, content['metadata'], content['digest']

