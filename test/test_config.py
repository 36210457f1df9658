from pathlib import Path

import pytest

from stars_ros.config import ExperimentConfig
from stars_ros.errors import ConfigError

CONFIG_DIR = Path(__file__).resolve().parents[1] / 'config'


def test_round_trip():
    config = ExperimentConfig.from_dict({'encoder': {'name': 'rgcn', 'options': {'num_bases': 2}},
                                         'training': {'lr': 1e-3}})
    assert ExperimentConfig.from_dict(config.to_dict()) == config


def test_defaults_are_the_published_optimiser():
    training = ExperimentConfig().training
    assert (training.lr, training.weight_decay) == (5e-5, 1e-5)


@pytest.mark.parametrize('values, message', [
    ({'encoder': {'nmae': 'gat'}}, r"encoder: unknown keys \['nmae'\]"),
    ({'trainig': {}}, r"unknown top-level keys \['trainig'\]"),
    ({'model': {'variant': 'fancy'}}, 'model.variant must be one of'),
    ({'split': {'test_fraction': 1.5}}, 'test_fraction'),
    ({'training': {'lr': -1}}, 'positive'),
    ({'model': 3}, 'expected a mapping'),
    ({'training': {'device': 'gpu'}}, 'training.device must be'),
    ({'training': {'device': 'cuda:x'}}, 'training.device must be'),
    ({'training': {'device': 'CUDA'}}, 'training.device must be'),
])
def test_bad_values_refused(values, message):
    with pytest.raises(ConfigError, match=message):
        ExperimentConfig.from_dict(values)


@pytest.mark.parametrize('device', ['cpu', 'cuda', 'cuda:1'])
def test_training_device_accepted(device):
    assert ExperimentConfig.from_dict({'training': {'device': device}}).training.device == device


def test_training_device_defaults_to_cpu():
    assert ExperimentConfig().training.device == 'cpu'


def test_replace_switches_variant_only():
    config = ExperimentConfig.from_dict({'encoder': {'name': 'gin'}})
    base = config.replace(model={'variant': 'base'})
    assert base.model.variant == 'base' and base.encoder == config.encoder


@pytest.mark.parametrize('path', sorted(p for p in CONFIG_DIR.glob('*.yaml')
                                         if not p.name.startswith(('eval', 'ranker', 'learning_curve'))))
def test_shipped_experiment_configs_parse(path):
    ExperimentConfig.from_yaml(path)


@pytest.mark.parametrize('path', sorted(CONFIG_DIR.glob('learning_curve*.yaml')))
def test_shipped_learning_curve_configs_parse(path):
    from offline_training.learning_curve import read_config
    values = read_config(path)
    assert values['backbone'] in values['protocol_config'].backbones


def test_unreadable_yaml(tmp_path):
    (tmp_path / 'c.yaml').write_text('encoder: [unclosed')
    with pytest.raises(ConfigError, match='cannot read config'):
        ExperimentConfig.from_yaml(tmp_path / 'c.yaml')
