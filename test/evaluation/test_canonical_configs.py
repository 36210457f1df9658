"""The canonical records' configs (issue 62) say what their headers say: each backbone with its
packaged settings, a fold seed of no earlier record, the hold-out recipe's row on every backbone,
and k-shot configs equal to the shipped method's."""
from pathlib import Path

import pytest
import yaml

from stars_ros.errors import ConfigError
from stars_ros.evaluation.protocol import ProtocolConfig
from stars_ros.evaluation.specs import model_specs
from stars_ros.model.config import ExperimentConfig

CONFIG = Path(__file__).resolve().parents[2] / 'config'


def test_each_socnav1_backbone_trains_with_its_packaged_settings():
    config = ProtocolConfig.from_yaml(CONFIG / 'eval_socnav1_canonical.yaml')
    assert list(config.backbones) == ['gcn', 'gin', 'graphsage', 'ggnn', 'rgcn', 'gat']
    for backbone in config.backbones:
        packaged = ExperimentConfig.from_yaml(CONFIG / f'socnav1_{backbone}.yaml')
        ours = config.experiment_config(backbone, 'stars')
        assert ours.encoder == packaged.encoder and ours.model.dim == packaged.model.dim
        assert config.grid == ((packaged.training.pretrain_epochs, packaged.training.joint_epochs),)
        for key in ('lr', 'weight_decay', 'embedding_l2', 'batch_size', 'grad_clip', 'seed'):
            assert getattr(ours.training, key) == getattr(packaged.training, key), (backbone, key)
    assert config.search['stars'] == {'posterior_sweeps': [0, 50, 200]}  # GAT's packaged 50 among them


@pytest.mark.parametrize('name', ['eval_socnav1_canonical.yaml', 'eval_crowd_canonical.yaml'])
def test_a_canonical_run_has_the_hold_out_row_everywhere_and_a_fresh_fold_seed(name):
    config = ProtocolConfig.from_yaml(CONFIG / name)
    assert config.folds == 5 and config.ablations == ('holdout_recipe',)
    assert set(config.ablation_backbones) == set(config.backbones)
    rows = [spec for spec in model_specs(config) if spec.from_holdout]
    assert len(rows) == len(config.backbones) + 1  # and MF's
    assert {'mf', 'surprise_svd', 'myfm', 'myfm_encoder', 'population_mean'} <= set(config.baselines)
    earlier = [path for path in CONFIG.glob('eval_*.yaml') if 'canonical' not in path.name]
    used = {seed for path in earlier for seed in (yaml.safe_load(path.read_text()) or {}).get('seeds', [0])}
    assert not set(config.seeds) & used


@pytest.mark.parametrize('canonical, shipped', [
    ('kshot_socnav1_canonical.yaml', 'socnav1_gat.yaml'),
    ('kshot_crowd_canonical.yaml', 'crowd_mlp_shipped_method.yaml')])
def test_the_kshot_configs_are_the_shipped_methods(canonical, shipped):
    assert ExperimentConfig.from_yaml(CONFIG / canonical).to_dict() == \
        ExperimentConfig.from_yaml(CONFIG / shipped).to_dict()


def test_a_backbones_training_settings_reach_its_models_alone_and_are_checked():
    config = ProtocolConfig.from_dict({'backbones': {'gcn': {'training': {'embedding_l2': 0.3}}, 'gat': {}}})
    assert config.experiment_config('gcn', 'stars').training.embedding_l2 == 0.3
    assert config.experiment_config('gat', 'stars').training.embedding_l2 != 0.3
    with pytest.raises(ConfigError, match=r'^backbones\.gcn\.training\.lrr'):
        ProtocolConfig.from_dict({'backbones': {'gcn': {'training': {'lrr': 0.1}}}})
