"""One registry of scene encoders φθ; every backbone shares the ``Encoder`` interface.

Any registered backbone serves both the ``base`` and the ``stars`` model variant: the
variant is a switch in the model, never a second copy of an encoder.
"""
from __future__ import annotations

import re

from stars_ros.model.encoders.base import Encoder, ENCODERS, register
from stars_ros.model.encoders import graph, tabular  # noqa: F401  (modules register their backbones on import)


def normalise_name(name: str) -> str:
    return re.sub(r'[^a-z0-9]', '', name.lower())


def resolve_encoder(query, *args, **kwargs) -> Encoder:
    """Return ``query`` if it is an Encoder, else build the backbone it names.

    Names are matched case- and punctuation-insensitively (``'FT-Transformer'`` ==
    ``'ft_transformer'``); extra arguments go to the backbone's constructor.
    """
    if isinstance(query, Encoder):
        return query
    cls = ENCODERS.get(normalise_name(str(query)))
    if cls is None:
        raise ValueError(f"Could not resolve '{query}' among choices {sorted(ENCODERS)}")
    return cls(*args, **kwargs)


__all__ = ['Encoder', 'ENCODERS', 'register', 'resolve_encoder', 'normalise_name']
