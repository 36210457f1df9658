import copy

import pytest
import torch

from stars_ros.model.config import ExperimentConfig
from stars_ros.model.encoders import BACKBONES, ENCODERS, Encoder, encoder_class, resolve_encoder
from stars_ros.data.scene_graph import NODE_FEATURES
from stars_ros.data.scene_store import TabularStore
from stars_ros.model.fitted import build_model

GRAPH_BACKBONES = ['gcn', 'gin', 'graphsage', 'ggnn', 'rgcn', 'gat']
TABULAR_BACKBONES = ['mlp', 'resmlp', 'dcnv2', 'graceae', 'fttransformer']


def test_registry_holds_every_published_backbone():
    assert sorted(BACKBONES) == sorted(GRAPH_BACKBONES + TABULAR_BACKBONES)
    for name in BACKBONES:  # each module named defines what it is named for
        assert encoder_class(name).registry_name == name
    assert sorted(ENCODERS) == sorted(BACKBONES)


@pytest.mark.parametrize('name', ['FT-Transformer', 'ft_transformer', 'GraphSAGE', 'DCN-v2'])
def test_names_are_normalised(name):
    assert isinstance(resolve_encoder(name, 4, 8), Encoder)


def test_unknown_name_lists_choices():
    with pytest.raises(ValueError, match=r"Could not resolve 'transformerxl' among choices \['dcnv2'"):
        resolve_encoder('transformerxl', 4, 8)


def test_instance_passes_through():
    encoder = resolve_encoder('mlp', 4, 8)
    assert resolve_encoder(encoder) is encoder


def scene_input(kind, synthetic):
    if kind == 'graph':
        return synthetic.store.batch(torch.tensor([0, 5, 9])), synthetic.store.feature_dim
    return TabularStore(torch.randn(3, 6).numpy(), [f'f{k}' for k in range(6)]).batch(torch.arange(3)), 6


@pytest.mark.parametrize('variant', ['base', 'stars'])
@pytest.mark.parametrize('name', GRAPH_BACKBONES + TABULAR_BACKBONES)
def test_every_encoder_in_both_variants(name, variant, synthetic):
    """Contract every backbone keeps: output shape, finite values, gradients reach φθ."""
    kind = 'graph' if name in GRAPH_BACKBONES else 'tabular'
    inputs, feature_dim = scene_input(kind, synthetic)
    config = ExperimentConfig.from_dict({'encoder': {'name': name, 'hidden': 16, 'layers': 2},
                                         'model': {'variant': variant, 'dim': 8}})
    model = build_model(config, feature_dim, kind, n_users=4, n_scenes=5, n_actions=3)
    model.train()
    h = model.encode(inputs)
    assert h.shape == (3, 8)
    scores = model(torch.tensor([0, -1, 3]), torch.tensor([1, 2, -1]), h)
    assert scores.shape == (3, 3) and torch.isfinite(scores).all()
    scores.sum().backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.encoder.parameters())
    assert hasattr(model, 'user_embedding') == (variant == 'stars')


def test_graph_encoder_refuses_tabular_data():
    config = ExperimentConfig.from_dict({'encoder': {'name': 'gat'}})
    with pytest.raises(Exception, match='reads graph scenes, the data holds tabular'):
        build_model(config, 6, 'tabular', 2, 2, 1)


def test_graph_encoder_uses_all_node_features():
    encoder = resolve_encoder('gcn', len(NODE_FEATURES), 8)
    assert encoder.in_dim == len(NODE_FEATURES)


def test_graceae_reconstruction_loss_only_in_training():
    encoder = resolve_encoder('graceae', 6, 4)
    encoder.train()
    encoder(torch.randn(5, 6))
    assert encoder.auxiliary_loss() > 0
    encoder.eval()
    first = encoder(torch.ones(2, 6))
    assert encoder.auxiliary_loss() is None
    assert torch.equal(first, encoder(torch.ones(2, 6)))  # no corruption at inference


def test_graceae_copies_mid_training_once_its_loss_is_taken():
    """The trainer takes the reconstruction loss every step; a copy made between steps (the
    posterior head's curve points) must not meet the loss's graph."""
    encoder = resolve_encoder('graceae', 6, 4)
    encoder.train()
    encoder(torch.randn(5, 6))
    encoder.auxiliary_loss().backward()
    assert encoder.auxiliary_loss() is None
    copy.deepcopy(encoder)
