"""Short real training runs on SocNav1 (seconds each)."""
import numpy as np
import pytest
import torch

from stars_ros.config import ExperimentConfig
from stars_ros.errors import ConfigError, TrainingDivergedError
from stars_ros.training import NotFittedError, StarsRecommender, split_rows

SMALL = {'encoder': {'name': 'gcn', 'hidden': 16, 'layers': 1}, 'model': {'dim': 16},
         'training': {'pretrain_epochs': 2, 'joint_epochs': 4, 'lr': 3e-3, 'batch_size': 128, 'threads': 1}}


@pytest.fixture(scope='module')
def rows(socnav1):
    train, test = split_rows(len(socnav1), 0.2, 0)
    return train[:2000], test[:500]


def test_split_is_seeded_and_disjoint():
    train, test = split_rows(100, 0.2, 7)
    assert len(test) == 20 and not set(train) & set(test) and len(train) + len(test) == 100
    assert np.array_equal(test, split_rows(100, 0.2, 7)[1])
    assert not np.array_equal(test, split_rows(100, 0.2, 8)[1])


@pytest.mark.parametrize('variant', ['stars', 'base', 'mf'])
def test_training_lowers_the_loss_and_beats_the_mean(socnav1, rows, variant):
    train, test = rows
    recommender = StarsRecommender(ExperimentConfig.from_dict(SMALL).replace(model={'variant': variant}))
    recommender.fit(socnav1, train)
    joint = recommender.history['joint']
    assert joint[-1] < joint[0]
    assert len(recommender.history['pretrain']) == (0 if variant == 'mf' else 2)
    metrics = recommender.evaluate(socnav1, test)
    mean_mse = float(np.mean((socnav1.scores[test] - socnav1.scores[train].mean()) ** 2))
    if variant != 'mf':  # content models must beat the global mean already
        assert metrics['mse'] < mean_mse
    assert metrics['n'] == len(test)


def test_training_is_deterministic(socnav1, rows):
    train, test = rows
    config = ExperimentConfig.from_dict(SMALL)
    first = StarsRecommender(config).fit(socnav1, train[:800]).predict_rows(socnav1, test)
    second = StarsRecommender(config).fit(socnav1, train[:800]).predict_rows(socnav1, test)
    assert np.array_equal(first, second)


def test_vocabularies_come_from_training_rows_only(socnav1, rows):
    train, _ = rows
    recommender = StarsRecommender(ExperimentConfig.from_dict(SMALL).replace(
        training={'pretrain_epochs': 0, 'joint_epochs': 1})).fit(socnav1, train[:300])
    assert set(recommender.users) == set(socnav1.users[train[:300]].tolist())
    assert len(recommender.scene_keys) == len(set(socnav1.scenes[train[:300]].tolist()))


def test_divergence_is_reported(socnav1, rows):
    config = ExperimentConfig.from_dict(SMALL).replace(training={'lr': 1e30, 'grad_clip': 1e30,
                                                                 'pretrain_epochs': 1, 'joint_epochs': 1})
    with pytest.raises(TrainingDivergedError, match='lower the learning rate'):
        StarsRecommender(config).fit(socnav1, rows[0][:500])


def test_predict_before_fit():
    with pytest.raises(NotFittedError, match='not fitted'):
        StarsRecommender(ExperimentConfig()).predict_scores(['a'], [None], None)


@pytest.mark.skipif(torch.cuda.is_available(), reason='checks the message torch gives without a GPU')
def test_cuda_device_without_a_gpu_is_a_config_error(socnav1, rows):
    config = ExperimentConfig.from_dict(SMALL).replace(training={'device': 'cuda'})
    with pytest.raises(ConfigError, match='torch sees no CUDA GPU'):
        StarsRecommender(config).fit(socnav1, rows[0][:100])


@pytest.mark.skipif(not torch.cuda.is_available(), reason='needs a CUDA GPU')
@pytest.mark.parametrize('encoder, variant', [('gcn', 'stars'), ('gat', 'base'), ('gat', 'mf'),
                                              ('rgcn', 'stars'), ('ggnn', 'stars')])
def test_cuda_fit_matches_the_cpu_fit(socnav1, rows, encoder, variant):
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
        recommender = StarsRecommender(config.replace(training={'device': device}))
        seen = []
        recommender.fit(socnav1, train, on_epoch=lambda stage, epoch: seen.append(
            (next(recommender.model.parameters()).device.type, recommender.predict_rows(socnav1, test))))
        assert {t.device.type for t in recommender.model.state_dict().values()} == {'cpu'}
        fitted[device] = (seen, recommender.predict_rows(socnav1, test), recommender.history)
    (cpu_seen, cpu_final, cpu_history), (gpu_seen, gpu_final, gpu_history) = fitted['cpu'], fitted['cuda']
    assert {d for d, _ in gpu_seen} == {'cuda'} and len(gpu_seen) == len(cpu_seen)
    for (_, on_cpu), (_, on_gpu) in zip(cpu_seen, gpu_seen):
        np.testing.assert_allclose(on_gpu, on_cpu, atol=1e-4)
    np.testing.assert_allclose(gpu_final, cpu_final, atol=1e-4)
    for stage in ('pretrain', 'joint'):
        np.testing.assert_allclose(gpu_history[stage], cpu_history[stage], rtol=1e-4)
