"""The generated crowd data set, and why a protocol row is an example, not a rating line.

A planted per-(user, scene) mood is shared by every action a person rates in a scene. Split
by line, a test rating's siblings sit in training and reveal the mood: a predictor that
memorises it (a person's mean residual on their other ratings of the same scene, or MF
with a row per scene) scores well for the wrong reason. Split by example, no sibling is in
training and the memoriser has nothing to memorise.
"""
import numpy as np
import pytest

from stars_ros.data.ratings import load_dataset
from stars_ros.evaluation import crowd_data
from stars_ros.evaluation.folds import Fold, make_folds
from stars_ros.model.config import ExperimentConfig
from stars_ros.model.training import StarsTrainer
from conftest import served_rows

MOODY = crowd_data.CrowdShape(users=60, scenes=120, features=8, raters_per_scene=6, latent=3, taste=0.2,
                              leniency=0.2, mood=1.5, noise=0.2)


@pytest.fixture(scope='module')
def moody(tmp_path_factory):
    return load_dataset(crowd_data.write(tmp_path_factory.mktemp('moody'), MOODY, seed=3))


def line_folds(n: int, k: int, seed: int) -> list[Fold]:
    """The split this project no longer makes: a permutation of rating lines cut in k."""
    parts = np.array_split(np.random.default_rng(seed).permutation(n), k)
    return [Fold(np.sort(np.concatenate(parts[:f] + parts[f + 1:])), np.sort(parts[f])) for f in range(k)]


def memoriser_rmse(data, fold: Fold) -> tuple[float, float]:
    """RMSE of action mean + the person's mean residual on their other actions of the same
    scene in training; and the mean number of such siblings per test rating."""
    train, test = fold
    means = np.array([data.scores[train][data.actions[train] == a].mean() for a in range(len(data.action_names))])
    residual = data.scores[train] - means[data.actions[train]]
    by_example = {}
    for example, value in zip(data.examples[train], residual):
        by_example.setdefault(example, []).append(value)
    offsets = np.array([np.mean(by_example.get(e, [0.0])) for e in data.examples[test]])
    siblings = np.array([len(by_example.get(e, [])) for e in data.examples[test]])
    predictions = means[data.actions[test]] + offsets
    return float(np.sqrt(np.mean((predictions - data.scores[test]) ** 2))), float(siblings.mean())


def test_generated_data_has_the_shape_of_mannersdb(tmp_path):
    annotations, scenes = crowd_data.generate(crowd_data.CrowdShape(users=120, scenes=90), seed=1)
    again, _ = crowd_data.generate(crowd_data.CrowdShape(users=120, scenes=90), seed=1)
    assert annotations.equals(again)
    assert set(annotations.action) == set(crowd_data.ACTIONS) and len(crowd_data.ACTIONS) == 9
    assert set(annotations.score) == {1, 2, 3, 4, 5}
    assert annotations.groupby('scene').user.nunique().eq(14).all()
    assert scenes.shape == (90, 1 + 29)
    data = load_dataset(crowd_data.write(tmp_path, crowd_data.CrowdShape(users=120, scenes=90), seed=1))
    assert data.kind == 'tabular' and data.scale == (1.0, 5.0) and len(data) == len(annotations)
    assert len(np.unique(data.examples)) == 90 * 14


def test_splitting_by_line_leaks_the_mood_and_splitting_by_example_does_not(moody):
    by_line = [memoriser_rmse(moody, fold) for fold in line_folds(len(moody), 5, seed=0)]
    by_example = [memoriser_rmse(moody, fold) for fold in make_folds(moody, 'rows', 5, seed=0)]
    assert min(s for _, s in by_line) > 5  # of ~8 siblings, 4/5 sit in training
    assert all(s == 0 for _, s in by_example)
    line_rmse, example_rmse = np.mean([r for r, _ in by_line]), np.mean([r for r, _ in by_example])
    assert line_rmse < 0.75 * example_rmse  # the memoriser looks good only when it can cheat


def test_mf_memorises_the_mood_only_across_a_line_split(moody):
    """The project's own MF (a row per scene and user, no content) learns the leaked mood."""
    config = ExperimentConfig.from_dict({
        'encoder': {'name': 'mlp', 'hidden': 8, 'layers': 1}, 'model': {'variant': 'mf', 'dim': 8},
        'training': {'pretrain_epochs': 0, 'joint_epochs': 40, 'lr': 1e-2, 'batch_size': 64,
                     'weight_decay': 0.0, 'embedding_l2': 0.001}})

    def rmse(fold):
        recommender = StarsTrainer(config).fit(moody, fold.train)
        errors = served_rows(recommender, moody, fold.test) - moody.scores[fold.test]
        return float(np.sqrt(np.mean(errors ** 2)))
    assert rmse(line_folds(len(moody), 5, seed=0)[0]) < 0.85 * rmse(make_folds(moody, 'rows', 5, seed=0)[0])
