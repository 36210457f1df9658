"""The one fit recipe (stars_ros.personalisation.recipe): the shipped model learns from every rating it
is given; the prior's noise comes from a hold-out fit's served predictions of ratings it did
not see."""
import numpy as np
import pytest

from conftest import TINY_CONFIG, served_rows
from stars_ros import StarsRecommender
from stars_ros.model.config import ExperimentConfig
from stars_ros.personalisation.recipe import Recipe
from stars_ros.model.training import StarsTrainer, split_rows
from stars_ros.personalisation.prior import held_out_split


@pytest.fixture(scope='module')
def given(synthetic):
    return split_rows(synthetic, 0.2, 0)[0]


def test_the_shipped_models_rows_see_every_training_rating(synthetic, given, monkeypatch):
    """Every fit the recipe makes, and on which rows: the plain encoder and the shipped model
    on every given rating, the hold-out fit on them less its held-out examples; the shipped
    model's normalisation is every given rating's."""
    fits, fit = [], StarsTrainer.fit

    def watched(trainer, data, rows=None, on_epoch=None):
        fits.append((trainer.config.model.variant, np.asarray(rows)))
        return fit(trainer, data, rows, on_epoch)
    monkeypatch.setattr(StarsTrainer, 'fit', watched)
    config = ExperimentConfig.from_dict(TINY_CONFIG).replace(model={'strangers': 'base_encoder'})
    recommender = StarsRecommender(config).fit(synthetic, given)
    trained_on, held = held_out_split(synthetic, given, seed=config.split.seed)
    assert len(held) and len(trained_on) + len(held) == len(given)
    assert [variant for variant, _ in fits] == ['base', 'stars', 'stars']
    assert np.array_equal(fits[0][1], given) and np.array_equal(fits[2][1], given)  # plain encoder, shipped
    assert np.array_equal(fits[1][1], trained_on)  # the hold-out fit
    model = recommender.fitted.model
    assert model.target_mean[0].item() == pytest.approx(synthetic.scores[given].mean(), rel=1e-6)
    assert set(recommender.users) == set(synthetic.users[given].tolist())
    assert recommender.checkpoint_metadata['data']['n_train'] == len(given)


def test_the_priors_noise_is_the_hold_out_fits_served_error_on_what_it_did_not_see(synthetic, given):
    config = ExperimentConfig.from_dict(TINY_CONFIG)
    recipe = Recipe(config)
    shipped = recipe.fit(synthetic, given)
    _, held = held_out_split(synthetic, given, seed=config.split.seed)
    # the served predictions of the held-out ratings by the hold-out fit, on the z-scale
    residual = synthetic.scores[held] - served_rows(recipe.holdout, synthetic, held)
    by_hand = np.mean((residual / shipped.model.target_std[0].item()) ** 2)
    noise = shipped.user_prior['noise'][0].item()
    assert noise == pytest.approx(by_hand, rel=0.05)  # the served scores are clipped, the noise's are not
    assert 'held-out ratings' in shipped.user_prior['details']['noise']
    assert recipe.holdout.model is not shipped.model


def test_a_curve_point_is_both_fits_at_that_epoch(synthetic, given):
    """``now`` inside ``on_epoch`` is what a fit with that many joint epochs returns."""
    config = ExperimentConfig.from_dict(TINY_CONFIG)
    recipe, seen = Recipe(config), {}
    recipe.fit(synthetic, given, on_epoch=lambda stage, epoch: seen.update(
        {epoch: recipe.now(stage, epoch)} if stage == 'joint' and epoch == 1 else {}))
    shorter = Recipe(config.replace(training={'joint_epochs': 1})).fit(synthetic, given)
    rows = given[:200]
    assert np.array_equal(served_rows(seen[1], synthetic, rows), served_rows(shorter, synthetic, rows))
    assert np.array_equal(seen[1].user_prior['noise'].numpy(), shorter.user_prior['noise'].numpy())
