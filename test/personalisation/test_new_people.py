"""New people through the front door, as a Python user meets them: ``StarsRecommender.fit``
with its defaults on generated crowd data, then people the fit never saw folded in from one
to three of their examples and scored on their other examples. Their error never exceeds
what they got as strangers, also for a planted group whose preferences run against the
population's."""
import numpy as np
import pytest

from stars_ros import StarsRecommender, load_dataset
from stars_ros.evaluation import crowd_data

CONFIG = {'encoder': {'name': 'mlp', 'hidden': 32, 'layers': 2}, 'model': {'dim': 8},
          'training': {'pretrain_epochs': 5, 'joint_epochs': 15, 'lr': 1.0e-2, 'batch_size': 64, 'threads': 1}}
NEW_PEOPLE = 12


@pytest.fixture(scope='module')
def crowd(tmp_path_factory):
    """60 raters of 150 scenes (9 actions, scores 1-5); the last ``NEW_PEOPLE`` are the new
    people, and of them the odd ones are the planted group, who rate 6 − score."""
    annotations, scenes = crowd_data.generate(crowd_data.CrowdShape(users=60, scenes=150, features=8,
                                                                    raters_per_scene=10, latent=2), seed=3)
    new = sorted(set(annotations.user))[-NEW_PEOPLE:]
    planted = new[1::2]
    contrary = annotations.user.isin(planted)
    annotations.loc[contrary, 'score'] = 6 - annotations.loc[contrary, 'score']
    root = tmp_path_factory.mktemp('crowd')
    annotations.to_csv(root / 'annotations.csv', index=False)
    scenes.to_csv(root / 'scenes.csv', index=False)
    data = load_dataset(root)
    known = np.flatnonzero(~np.isin(data.users, new))
    recommender = StarsRecommender(CONFIG).fit(data, known)  # defaults: the prior's noise held out inside
    return data, recommender, new, planted


def examples_of(data, person) -> list:
    """The person's examples (their ratings of one scene, every action), in a seeded order,
    each a list of (scene id, action, score)."""
    rows = np.flatnonzero(data.users == person)
    ids = np.random.default_rng(sum(map(ord, person))).permutation(np.unique(data.examples[rows]))
    return [[(data.scene_keys[data.scenes[r]], data.action_names[data.actions[r]], float(data.scores[r]))
             for r in rows[data.examples[rows] == e]] for e in ids]


def squared_errors(recommender, person, examples) -> np.ndarray:
    return np.array([(recommender.predict(person, scene, action) - score) ** 2
                     for example in examples for scene, action, score in example])


def errors_by_k(crowd, people) -> dict:
    """{k: pooled squared errors on each person's examples after their first 3} for k = 0..3."""
    data, recommender, _, _ = crowd
    errors = {k: [] for k in range(4)}
    for person in people:
        examples = examples_of(data, person)
        for k in range(4):
            recommender.fold_in(person, [rating for example in examples[:k] for rating in example])
            errors[k].append(squared_errors(recommender, person, examples[3:]))
        recommender.fold_in(person, [])
    return {k: np.concatenate(v) for k, v in errors.items()}


def test_the_default_fit_holds_out_ratings_for_the_noise_and_finds_the_tails(crowd):
    data, recommender, new, _ = crowd
    prior = recommender.predictor.served.user_prior
    assert 'held-out ratings' in prior['details']['noise']
    assert float(prior['nu']) > 2


@pytest.mark.slow
def test_new_people_are_never_worse_after_one_to_three_examples(crowd):
    errors = errors_by_k(crowd, crowd[2])
    for k in (1, 2, 3):
        assert errors[k].mean() <= errors[0].mean()


def test_a_planted_group_against_the_population_is_never_worse_and_gains(crowd):
    errors = errors_by_k(crowd, crowd[3])
    for k in (1, 2, 3):
        assert errors[k].mean() <= errors[0].mean()
    assert errors[3].mean() < 0.9 * errors[0].mean()  # the fold-in learns what the population mean cannot
