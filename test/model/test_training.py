"""Short real training runs on generated SocNav1-format data (a second or less each)."""
import dataclasses

import numpy as np
import pytest
import torch

from stars_ros.model.config import ExperimentConfig
from stars_ros.errors import ConfigError, DataError, TrainingDivergedError
from stars_ros.errors import NotFittedError
from stars_ros.model.training import StarsTrainer, split_rows
from conftest import served_report, served_rows

SMALL = {'encoder': {'name': 'gcn', 'hidden': 16, 'layers': 1}, 'model': {'dim': 16},
         'training': {'pretrain_epochs': 2, 'joint_epochs': 4, 'lr': 3e-3, 'batch_size': 128, 'threads': 1}}


@pytest.fixture(scope='module')
def rows(synthetic):
    train, test = split_rows(synthetic, 0.2, 0)
    return train[:2000], test[:500]


def test_split_is_seeded_disjoint_and_by_example(synthetic):
    train, test = split_rows(synthetic, 0.2, 7)
    assert not set(train) & set(test) and len(train) + len(test) == len(synthetic)
    assert len(test) == round(0.2 * len(synthetic))  # one action: one rating per example
    assert np.array_equal(test, split_rows(synthetic, 0.2, 7)[1])
    assert not np.array_equal(test, split_rows(synthetic, 0.2, 8)[1])
    three = dataclasses.replace(synthetic, actions=np.arange(len(synthetic)) % 3, action_names=('a', 'b', 'c'),
                                users=np.repeat(synthetic.users[::3], 3)[:len(synthetic)],
                                scenes=np.repeat(synthetic.scenes[::3], 3)[:len(synthetic)])
    train, test = split_rows(three, 0.2, 7)
    assert not set(three.examples[train].tolist()) & set(three.examples[test].tolist())


def test_stars_and_its_ablations_start_exactly_where_base_ends(synthetic, rows):
    """The hand-over: after the same pre-training, a personalised model with no joint epoch
    yet predicts what the scene-only model predicts."""
    train, test = rows
    config = ExperimentConfig.from_dict(SMALL).replace(training={'pretrain_epochs': 2, 'joint_epochs': 0})
    base = served_rows(StarsTrainer(config.replace(model={'variant': 'base'})).fit(synthetic, train),
                       synthetic, test)
    for variant in ('stars', 'base_user_bias', 'stars_no_q'):
        started = StarsTrainer(config.replace(model={'variant': variant})).fit(synthetic, train)
        np.testing.assert_allclose(served_rows(started, synthetic, test), base, atol=1e-6)


def test_ablations_keep_their_missing_parts_at_zero(synthetic, rows):
    train, _ = rows
    config = ExperimentConfig.from_dict(SMALL).replace(training={'pretrain_epochs': 1, 'joint_epochs': 2})
    for variant, absent in (('base_user_bias', ('user_embedding', 'scene_embedding', 'scene_bias')),
                            ('stars_no_q', ('scene_embedding',)),
                            ('user_bias', ('user_embedding', 'scene_embedding', 'scene_bias'))):
        model = StarsTrainer(config.replace(model={'variant': variant})).fit(synthetic, train[:600]).model
        for name in absent:
            assert getattr(model, name).weight.abs().sum() == 0, (variant, name)
        assert model.user_bias.weight.abs().sum() > 0


def test_predictions_stay_on_the_rating_scale(synthetic, rows):
    train, test = rows
    recommender = StarsTrainer(ExperimentConfig.from_dict(SMALL).replace(
        training={'pretrain_epochs': 1, 'joint_epochs': 1})).fit(synthetic, train[:500])
    assert recommender.rating_scale == (0.0, 1.0)
    with torch.no_grad():
        recommender.model.bias.fill_(40.0)  # far above the scale
    assert np.all(served_rows(recommender, synthetic, test) == 1.0)


def test_prefix_keying_merges_scenes_that_share_a_numeric_prefix(synthetic):
    prefixes = synthetic.item_keys('prefix')
    assert prefixes == [key.split(' ')[0] for key in synthetic.scene_keys]
    pairs = {p for p in prefixes if prefixes.count(p) > 1}  # "00007 A" and "00007 B" both rated
    assert pairs and len(set(prefixes)) < len(synthetic.scene_keys)
    config = ExperimentConfig.from_dict(SMALL).replace(training={'pretrain_epochs': 0, 'joint_epochs': 1})
    rows = np.arange(len(synthetic))
    by_identifier = StarsTrainer(config).fit(synthetic, rows)
    by_prefix = StarsTrainer(config.replace(model={'item_key': 'prefix'})).fit(synthetic, rows)
    assert len(by_identifier.scene_keys) == len(synthetic.scene_keys)
    assert sorted(by_prefix.scene_keys) == sorted(set(prefixes))
    with pytest.raises(DataError, match="item keying 'room'"):
        synthetic.item_keys('room')


@pytest.mark.parametrize('variant', ['stars', 'base', 'mf'])
def test_training_lowers_the_loss_and_beats_the_mean(synthetic, rows, variant):
    train, test = rows
    recommender = StarsTrainer(ExperimentConfig.from_dict(SMALL).replace(model={'variant': variant}))
    recommender.fit(synthetic, train)
    joint = recommender.history['joint']
    assert joint[-1] < joint[0]
    assert len(recommender.history['pretrain']) == (0 if variant == 'mf' else 2)
    metrics = served_report(recommender, synthetic, test)
    mean_mse = float(np.mean((synthetic.scores[test] - synthetic.scores[train].mean()) ** 2))
    if variant != 'mf':  # content models must beat the global mean already
        assert metrics['mse'] < mean_mse
    assert metrics['n'] == len(test)


def test_training_is_deterministic(synthetic, rows):
    train, test = rows
    config = ExperimentConfig.from_dict(SMALL)
    first = served_rows(StarsTrainer(config).fit(synthetic, train[:800]), synthetic, test)
    second = served_rows(StarsTrainer(config).fit(synthetic, train[:800]), synthetic, test)
    assert np.array_equal(first, second)


def test_vocabularies_come_from_training_rows_only(synthetic, rows):
    train, _ = rows
    recommender = StarsTrainer(ExperimentConfig.from_dict(SMALL).replace(
        training={'pretrain_epochs': 0, 'joint_epochs': 1})).fit(synthetic, train[:300])
    assert set(recommender.users) == set(synthetic.users[train[:300]].tolist())
    assert len(recommender.scene_keys) == len(set(synthetic.scenes[train[:300]].tolist()))


def test_divergence_is_reported(synthetic, rows):
    config = ExperimentConfig.from_dict(SMALL).replace(training={'lr': 1e30, 'grad_clip': 1e30,
                                                                 'pretrain_epochs': 1, 'joint_epochs': 1})
    with pytest.raises(TrainingDivergedError, match='lower the learning rate'):
        StarsTrainer(config).fit(synthetic, rows[0][:500])


def test_predict_before_fit():
    with pytest.raises(NotFittedError, match='not fitted'):
        StarsTrainer(ExperimentConfig()).require_model()


@pytest.mark.skipif(torch.cuda.is_available(), reason='checks the message torch gives without a GPU')
def test_cuda_device_without_a_gpu_is_a_config_error(synthetic, rows):
    config = ExperimentConfig.from_dict(SMALL).replace(training={'device': 'cuda'})
    with pytest.raises(ConfigError, match='torch sees no CUDA GPU'):
        StarsTrainer(config).fit(synthetic, rows[0][:100])


@pytest.mark.skipif(not torch.cuda.is_available(), reason='needs a CUDA GPU')
@pytest.mark.parametrize('encoder, variant', [('gcn', 'stars'), ('gat', 'base'), ('gat', 'mf'),
                                              ('rgcn', 'stars'), ('ggnn', 'stars')])
def test_cuda_fit_matches_the_cpu_fit(synthetic, rows, encoder, variant):
    """The same seeded fit on the GPU and the CPU: mid-training predictions (made on the GPU
    through on_epoch) and final ones agree to 1e-4, and the model comes back on the CPU.
    Two optimiser steps only (one batch per epoch), so rounding differences between the
    devices have little room to grow."""
    train, test = rows[0][:400], rows[1][:200]
    config = ExperimentConfig.from_dict(SMALL).replace(
        encoder={'name': encoder}, model={'variant': variant},
        training={'pretrain_epochs': 1, 'joint_epochs': 1, 'batch_size': 512, 'lr': 1e-3, 'embedding_l2': 0.01})
    fitted = {}
    for device in ('cpu', 'cuda'):
        recommender = StarsTrainer(config.replace(training={'device': device}))
        seen = []
        recommender.fit(synthetic, train, on_epoch=lambda stage, epoch: seen.append(
            (next(recommender.model.parameters()).device.type, served_rows(recommender, synthetic, test))))
        assert {t.device.type for t in recommender.model.state_dict().values()} == {'cpu'}
        fitted[device] = (seen, served_rows(recommender, synthetic, test), recommender.history)
    (cpu_seen, cpu_final, cpu_history), (gpu_seen, gpu_final, gpu_history) = fitted['cpu'], fitted['cuda']
    assert {d for d, _ in gpu_seen} == {'cuda'} and len(gpu_seen) == len(cpu_seen)
    for (_, on_cpu), (_, on_gpu) in zip(cpu_seen, gpu_seen):
        np.testing.assert_allclose(on_gpu, on_cpu, atol=1e-4)
    np.testing.assert_allclose(gpu_final, cpu_final, atol=1e-4)
    for stage in ('pretrain', 'joint'):
        np.testing.assert_allclose(gpu_history[stage], cpu_history[stage], rtol=1e-4)
