"""One registry of scene encoders φθ; every backbone shares the ``Encoder`` interface.

Any registered backbone serves both the ``base`` and the ``stars`` model variant: the
variant is a switch in the model, never a second copy of an encoder.

Backbones are found lazily: ``backbones.BACKBONES`` names the module that defines each,
and it is imported (joining ``ENCODERS``) only when one of its backbones is built, so a
process that builds a GAT never imports the tabular modules, and serving (``model.serving``)
imports none of them.
"""
from __future__ import annotations

import importlib

from stars_ros.model.backbones import BACKBONES, normalise_name
from stars_ros.model.encoders.base import Encoder, ENCODERS, register


def encoder_class(name: str) -> type:
    """The Encoder class registered under ``name`` (matched as ``resolve_encoder`` matches),
    its module imported now; ValueError for a name no module defines."""
    key = normalise_name(str(name))
    if key not in BACKBONES:
        raise ValueError(f"Could not resolve '{name}' among choices {sorted(BACKBONES)}")
    importlib.import_module(BACKBONES[key])
    return ENCODERS[key]


def resolve_encoder(query, *args, **kwargs) -> Encoder:
    """Return ``query`` if it is an Encoder, else build the backbone it names.

    Names are matched case- and punctuation-insensitively (``'FT-Transformer'`` ==
    ``'ft_transformer'``); extra arguments go to the backbone's constructor.
    """
    if isinstance(query, Encoder):
        return query
    return encoder_class(query)(*args, **kwargs)


__all__ = ['BACKBONES', 'Encoder', 'ENCODERS', 'encoder_class', 'register', 'resolve_encoder', 'normalise_name']
