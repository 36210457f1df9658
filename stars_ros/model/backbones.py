"""The names of the scene encoders φθ and the module that defines each, known without
importing any of them (or torch): a config is checked, and a checkpoint served, by name."""
from __future__ import annotations

import re

GRAPH = 'stars_ros.model.encoders.graph'
TABULAR = 'stars_ros.model.encoders.tabular'
BACKBONES = {**dict.fromkeys(('gat', 'gcn', 'ggnn', 'gin', 'graphsage', 'rgcn'), GRAPH),
             **dict.fromkeys(('dcnv2', 'fttransformer', 'graceae', 'mlp', 'resmlp'), TABULAR)}


def normalise_name(name: str) -> str:
    """A backbone's name matched case- and punctuation-insensitively (``'FT-Transformer'``
    == ``'ft_transformer'``)."""
    return re.sub(r'[^a-z0-9]', '', name.lower())
