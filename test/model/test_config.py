from pathlib import Path

import pytest
import yaml

from stars_ros.model.config import ExperimentConfig
from stars_ros.errors import ConfigError
from stars_ros.evaluation.protocol import ProtocolConfig

CONFIG_DIR = Path(__file__).resolve().parents[2] / 'config'


def test_round_trip():
    config = ExperimentConfig.from_dict({'encoder': {'name': 'rgcn', 'options': {'num_bases': 2}},
                                         'training': {'lr': 1e-3}})
    assert ExperimentConfig.from_dict(config.to_dict()) == config


def test_defaults_are_the_published_optimiser():
    training = ExperimentConfig().training
    assert (training.lr, training.weight_decay) == (5e-5, 1e-5)


@pytest.mark.parametrize('values, message', [
    ({'encoder': {'nmae': 'gat'}}, r"^encoder\.nmae: unknown key; allowed: name, hidden"),
    ({'trainig': {}}, r"^trainig: unknown key; allowed: encoder, model, training, split$"),
    ({'model': {'variant': 'fancy'}}, r"^model\.variant: Input should be 'base', 'stars'"),
    ({'split': {'test_fraction': 1.5}}, r'^split\.test_fraction: Input should be less than 1'),
    ({'training': {'lr': -1}}, r'^training\.lr: Input should be greater than 0, got -1$'),
    ({'encoder': {'dropout': 1.0}}, r'^encoder\.dropout: Input should be less than 1'),
    ({'training': {'threads': 0}}, r'^training\.threads: Input should be greater than or equal to 1'),
    ({'model': 3}, r'^model: expected a mapping, got int$'),
    ({'training': {'device': 'gpu'}}, r'^training\.device: must be'),
    ({'training': {'device': 'cuda:x'}}, r'^training\.device: must be'),
    ({'training': {'device': 'CUDA'}}, r'^training\.device: must be'),
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
    config = read_config(path)
    assert config.backbone in config.protocol_config.backbones


def test_unreadable_yaml(tmp_path):
    (tmp_path / 'c.yaml').write_text('encoder: [unclosed')
    with pytest.raises(ConfigError, match='cannot read config'):
        ExperimentConfig.from_yaml(tmp_path / 'c.yaml')


@pytest.mark.parametrize('section, key, value, message', [
    ('encoder', 'hidden', '64', "Input should be a valid integer, got '64'"),
    ('encoder', 'hidden', 64.7, 'Input should be a valid integer, got 64.7'),
    ('training', 'seed', 'x', "Input should be a valid integer, got 'x'"),
    ('training', 'lr', 'fast', "Input should be a valid number, got 'fast'"),
    ('encoder', 'name', 'gatt', "unknown encoder 'gatt'; registered: "),
])
def test_wrong_type_or_unknown_encoder_names_file_and_key(tmp_path, section, key, value, message):
    """Refused while the YAML is read, before any data: the message names file and key."""
    path = tmp_path / 'experiment.yaml'
    path.write_text(yaml.safe_dump({section: {key: value}}))
    with pytest.raises(ConfigError) as refused:
        ExperimentConfig.from_yaml(path)
    assert str(refused.value).startswith(f'{path}: {section}.{key}: {message}')


def test_protocol_errors_name_file_and_key(tmp_path):
    path = tmp_path / 'protocol.yaml'
    path.write_text('backbones: {gcn: {hidden: 64.7}}\nexperiment: {training: {lr: fast}}\n')
    with pytest.raises(ConfigError) as refused:
        ProtocolConfig.from_yaml(path)
    assert str(refused.value) == f"{path}: experiment.training.lr: Input should be a valid number, got 'fast'"
    path.write_text('backbones: {gcn: {hidden: 64.7}}\n')
    with pytest.raises(ConfigError, match=r'protocol\.yaml: backbones\.gcn\.hidden: Input should be a valid integer'):
        ProtocolConfig.from_yaml(path)
    path.write_text('backbones: {gatt: {}}\n')
    with pytest.raises(ConfigError, match=r"protocol\.yaml: backbones\.gatt\.name: unknown encoder 'gatt'"):
        ProtocolConfig.from_yaml(path)


def test_learning_curve_errors_name_file_and_key(tmp_path):
    from offline_training.learning_curve import read_config
    (tmp_path / 'protocol.yaml').write_text('backbones: {gcn: {}}\n')
    path = tmp_path / 'curve.yaml'
    values = {'protocol': 'protocol.yaml', 'backbone': 'gcn', 'variants': ['base'], 'pretrain_epochs': 1,
              'joint_epochs': 2, 'every': 1, 'settings': {'a': {'lr': 'fast'}}}
    path.write_text(yaml.safe_dump(values))
    with pytest.raises(ConfigError, match=rf"^{path}: settings\.a\.lr: Input should be a valid number"):
        read_config(path)
    path.write_text(yaml.safe_dump({**values, 'settings': {'a': {}}, 'every': '1'}))
    with pytest.raises(ConfigError, match=rf"^{path}: every: Input should be a valid integer, got '1'$"):
        read_config(path)
    path.write_text(yaml.safe_dump({'protocol': 'protocol.yaml'}))
    with pytest.raises(ConfigError, match=rf'^{path}: backbone: required key missing'):
        read_config(path)


def test_missing_keys_take_defaults_and_configs_are_immutable():
    """A checkpoint written before ``model.item_key`` existed still loads."""
    config = ExperimentConfig.from_dict({'model': {'variant': 'base', 'dim': 8}, 'encoder': None})
    assert (config.model.item_key, config.encoder.name, config.training.threads) == ('identifier', 'gat', 1)
    with pytest.raises(ValueError):
        config.training.lr = 1.0


def test_a_stars_config_serving_strangers_the_plain_encoder_run_as_base_is_the_plain_encoder():
    config = ExperimentConfig.from_dict({'model': {'strangers': 'base_encoder'}})
    assert config.model.strangers == 'base_encoder'
    assert config.replace(model={'variant': 'base'}).model.strangers == 'prior_mean'
    assert config.stranger_encoder().model == config.replace(model={'variant': 'base'}).model
    with pytest.raises(ConfigError, match='strangers'):
        ExperimentConfig.from_dict({'model': {'strangers': 'nearest_person'}})


def test_a_checkpoints_training_settings_this_version_does_not_know_are_dropped_a_configs_refused():
    """An older checkpoint may hold settings of experiments that did not ship: it still loads (its
    weights and prior hold what they did); in a config file the same key is a typo to report."""
    with pytest.raises(ConfigError, match=r'^training\.retired_setting: unknown key'):
        ExperimentConfig.from_dict({'training': {'retired_setting': 0}})
    stored = ExperimentConfig().to_dict()
    stored['training'] = {**stored['training'], 'retired_setting': 3, 'another_one': True}
    assert ExperimentConfig.from_checkpoint(stored) == ExperimentConfig()
    with pytest.raises(ConfigError, match=r'^model\.retired_setting: unknown key'):  # only training settings
        ExperimentConfig.from_checkpoint({**stored, 'model': {'retired_setting': 0}})
