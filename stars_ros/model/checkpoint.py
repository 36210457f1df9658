"""Checkpoints are data, not code: one ``torch.save`` file of tensors and plain values.

Loaded with ``torch.load(weights_only=True)``, so no pickled code ever runs. A SHA-256
digest over the weights and metadata is stored inside and checked on load, so a flipped
byte is reported instead of silently changing predictions.
"""
from __future__ import annotations

import datetime
import hashlib
import json
import pickle
import re
import zipfile
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from stars_ros import __version__
from stars_ros.errors import CheckpointError, ConfigError, StarsError
from stars_ros.files import atomic_write
from stars_ros.model.tensor_file import read_tensor_file

if TYPE_CHECKING:
    from stars_ros.model.fitted import FittedModel

FORMAT = 'stars_ros.checkpoint'  # a data format's name: it stays when modules move
FORMAT_VERSION = 1
_ZIP_MAGIC = b'PK\x03\x04'  # torch.save's format since torch 1.6
_PICKLE_PROTOCOL = b'\x80'  # the legacy format: a pickle, protocol 2 or later
STRANGER = 'stranger.'  # where a state dict holds the plain encoder strangers are served (model.strangers)


def _tensors(content: dict) -> dict:
    """The tensors a checkpoint's digest covers: the weights and the personalisation prior."""
    prior = {f'user_prior.{k}': v for k, v in content.get('user_prior', {}).items()}
    return {**content['state_dict'], **prior}


def _digest(metadata: dict, state: dict) -> str:
    """Over the metadata and every tensor's bytes (torch tensors as saved, numpy arrays as read)."""
    sha = hashlib.sha256(json.dumps(metadata, sort_keys=True, default=str).encode())
    for name in sorted(state):
        value = state[name]
        sha.update(name.encode())
        sha.update(np.ascontiguousarray(value if isinstance(value, np.ndarray) else value.detach().cpu().numpy())
                   .tobytes())
    return sha.hexdigest()


def split_stranger(state: dict) -> tuple:
    """(the model's state, the stranger encoder's state or None) of a checkpoint's state dict."""
    own = {key: value for key, value in state.items() if not key.startswith(STRANGER)}
    stranger = {key[len(STRANGER):]: value for key, value in state.items() if key.startswith(STRANGER)}
    return own, stranger or None


def served_content(fitted: FittedModel) -> tuple:
    """(metadata, state dict, personalisation prior or None) of ``fitted`` as its checkpoint
    holds them: what ``serving.ServedModel`` is built from, whether read from a file or not."""
    model = fitted.require_model()
    metadata = {
        'config': fitted.config.to_dict(),
        'input_kind': model.encoder.input_kind,
        'feature_dim': model.encoder.in_dim,
        'users': list(fitted.users),
        'scene_keys': list(fitted.scene_keys),
        'actions': list(fitted.action_names),
        'normalisation': {'mean': model.target_mean.tolist(), 'std': model.target_std.tolist()},
        'rating_scale': list(fitted.rating_scale) if fitted.rating_scale is not None else None,
    }
    state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
    if fitted.stranger_model is not None:  # the plain encoder strangers are served (model.strangers)
        state.update({f'{STRANGER}{k}': v.detach().cpu().clone()
                      for k, v in fitted.stranger_model.state_dict().items()})
    prior = None if fitted.user_prior is None else dict(fitted.user_prior)
    return metadata, state, prior


def save_checkpoint(fitted: FittedModel, path, *, data: dict, metrics: dict | None = None,
                    provenance: dict | None = None) -> str:
    """Write ``fitted`` to ``path`` atomically; returns the checkpoint's digest.

    Args:
        data (dict): what it was trained on (``fingerprint``, ``source``, ``n_ratings`` ...).
        metrics (dict, optional): held-out figures to keep with the weights.
        provenance (dict, optional): anything else worth keeping (command line, logs used).
    """
    import torch

    served, state, prior = served_content(fitted)
    metadata = {
        'format': FORMAT,
        'format_version': FORMAT_VERSION,
        'package_version': __version__,
        'torch_version': str(torch.__version__),
        'created_utc': datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds'),
        **served,
        'data': dict(data),
        'metrics': dict(metrics or {}),
        'provenance': dict(provenance or {}),
    }
    content = {'metadata': metadata, 'state_dict': state}
    if prior is not None:
        metadata['user_prior'] = prior.pop('details', {})
        content['user_prior'] = prior
    content['digest'] = digest = _digest(metadata, _tensors(content))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda handle: torch.save(content, handle))
    return digest


def _torch_reason(error: Exception) -> str:
    """What torch found wrong with the file, without its advice on loading it anyway
    (``weights_only=False``, allow-listing globals): that would run the file's pickled code."""
    text = str(error)
    found = re.search(r'WeightsUnpickler error:\s*(.+?)(?:\. Please use|\n\n|$)', text, re.S)
    reason = found.group(1) if found else text.split('. ')[0]
    return ' '.join(reason.split()) or type(error).__name__


def read_checkpoint(path) -> dict:
    """The checkpoint's raw content (``metadata``, ``state_dict``, ``digest``), verified;
    tensors as numpy arrays (``tensor_file``: read without torch, running no pickled code)."""
    path = Path(path)
    try:
        content = read_tensor_file(path)
    except FileNotFoundError:
        raise CheckpointError(f'{path}: no such checkpoint file') from None
    except (EOFError, OSError, pickle.UnpicklingError, zipfile.BadZipFile, ValueError, KeyError, TypeError,
            IndexError) as error:
        try:
            with open(path, 'rb') as handle:
                head = handle.read(4)
        except OSError as unreadable:
            raise CheckpointError(f'{path}: cannot read the checkpoint: {unreadable}') from None
        if not head.startswith((_ZIP_MAGIC, _PICKLE_PROTOCOL)):
            what = 'an empty file' if not head else 'not a torch zip/pickle file'
            raise CheckpointError(f'{path}: not a stars_ros checkpoint ({what})') from None
        reason = _torch_reason(error)
        if reason.startswith('Unsupported global'):
            raise CheckpointError(f'{path}: not a stars_ros checkpoint: it holds Python objects besides tensors and '
                                  f'plain values ({reason}), and loading those would run code') from None
        raise CheckpointError(f'{path}: not a readable checkpoint (truncated or corrupted?): {reason}') from None
    if not isinstance(content, dict) or not {'metadata', 'state_dict', 'digest'} <= set(content):
        raise CheckpointError(f'{path}: not a stars_ros checkpoint')
    metadata = content['metadata']
    if metadata.get('format') != FORMAT:
        raise CheckpointError(f'{path}: not a stars_ros checkpoint (format {metadata.get("format")!r})')
    if metadata.get('format_version') != FORMAT_VERSION:
        raise CheckpointError(f'{path}: checkpoint format version {metadata.get("format_version")} '
                              f'is not supported (this is version {FORMAT_VERSION})')
    if _digest(metadata, _tensors(content)) != content['digest']:
        raise CheckpointError(f'{path}: checkpoint digest mismatch: the file is corrupted')
    return content


def stored_prior(content: dict) -> dict | None:
    """The personalisation prior a checkpoint's content keeps (``UserPrior.to_dict``'s form),
    None in one written before it was kept."""
    if 'user_prior' not in content:
        return None
    return {**content['user_prior'], 'details': content['metadata'].get('user_prior', {})}


def incompatible(path, error: Exception) -> CheckpointError:
    """The CheckpointError of content this version cannot rebuild or serve."""
    message = str(error) if isinstance(error, StarsError) else f'{type(error).__name__}: {error}'
    return CheckpointError(f'{path}: checkpoint is incompatible with this version: {message}')


def load_checkpoint(path):
    """Rebuild the torch ``FittedModel`` stored in ``path`` (training's form: serving reads
    ``serving.ServedModel.load``); returns (fitted model, metadata). (``StarsTrainer.resume``
    makes it trainable again.)"""
    import torch

    from stars_ros.model.config import ExperimentConfig
    from stars_ros.model.fitted import FittedModel, build_model

    content = read_checkpoint(path)
    metadata = content['metadata']
    state, stranger_state = split_stranger(content['state_dict'])

    def rebuilt(config, weights):
        model = build_model(config, metadata['feature_dim'], metadata['input_kind'], len(metadata['users']),
                            len(metadata['scene_keys']), len(metadata['actions']))
        model.load_state_dict({name: torch.from_numpy(value) for name, value in weights.items()})
        return model.eval()
    try:
        config = ExperimentConfig.from_checkpoint(metadata['config'])
        fitted = FittedModel(config)
        fitted.set_vocabularies(metadata['users'], metadata['scene_keys'], metadata['actions'])
        fitted.model = rebuilt(config, state)
        if config.model.strangers == 'base_encoder':
            fitted.stranger_model = rebuilt(config.stranger_encoder(), stranger_state or {})
    except (ConfigError, KeyError, RuntimeError, TypeError) as error:
        raise incompatible(path, error) from error
    scale = metadata.get('rating_scale')  # absent from checkpoints written before it was kept
    fitted.rating_scale = tuple(scale) if scale is not None else None
    prior = stored_prior(content)
    if prior is not None:  # tensors, as a fitted model's: saved again, they are tensors in the file
        fitted.user_prior = {name: torch.from_numpy(value) if isinstance(value, np.ndarray) else value
                             for name, value in prior.items()}
    return fitted, metadata
