"""The implicit-outcome simulation: the stated outcome model, the exact expectation over
outcomes, the exchange rate's interpolation, and the command line end to end on the
generated crowd data (quick)."""
import json

import numpy as np
import pytest

from offline_training import implicit_feedback
from stars_ros.evaluation.implicit import (OutcomeModel, exchange_rate, expected_mse_implicit, mse_explicit,
                                          mse_implicit)
from stars_ros.evaluation import implicit_run
from stars_ros.evaluation.kshot import Person


def test_outcomes_follow_the_stated_model():
    rng = np.random.default_rng(0)
    scores = np.full(200000, 4.0)
    assert OutcomeModel(0.0).stayed(rng, scores, (1.0, 5.0)).mean() == pytest.approx(0.75, abs=0.005)
    assert OutcomeModel(0.2).stayed(rng, scores, (1.0, 5.0)).mean() == pytest.approx(0.1 + 0.8 * 0.75, abs=0.005)
    assert not OutcomeModel(0.0).stayed(rng, np.zeros(100), (0.0, 1.0)).any()
    with pytest.raises(ValueError):
        OutcomeModel(1.5)


def test_exchange_rate_interpolates_in_log_n_and_says_when_it_is_out_of_reach():
    ns = [0, 1, 2, 4, 8]
    mse = [1.0, 0.9, 0.8, 0.7, 0.6]
    assert exchange_rate(ns, mse, 0.8) == pytest.approx(2.0)
    assert exchange_rate(ns, mse, 0.75) == pytest.approx(2 ** 1.5)
    assert exchange_rate(ns, mse, 1.0) == 0.0
    assert exchange_rate(ns, mse, 0.5) is None


def test_config_overrides_name_a_data_set_and_a_path(capsys):
    args = implicit_feedback.parse_args(['--config', 'socnav1=config/socnav1_gat_posterior.yaml'])
    assert args.configs == {'socnav1': 'config/socnav1_gat_posterior.yaml'}
    for wrong in ('nope=x.yaml', 'socnav1', 'crowd='):
        with pytest.raises(SystemExit):
            implicit_feedback.parse_args(['--config', wrong])
        assert '--config takes DATASET=PATH' in capsys.readouterr().err


@pytest.mark.slow
def test_the_command_writes_curves_and_exchange_rates(tmp_path):
    assert implicit_feedback.main(['--quick', '--datasets', 'crowd', '--exact-up-to', '1', '--out', str(tmp_path)]) == 0
    results = json.loads((tmp_path / 'results.json').read_text())
    crowd = results['datasets']['crowd']
    assert set(crowd['curves']) == {'explicit', 'implicit ε=0.0', 'implicit ε=0.2'}
    assert crowd['curves']['implicit ε=0.0']['0'] == crowd['curves']['explicit']['0']  # both start unpersonalised
    assert {'never_worse_than_unpersonalised', 'implicit_outcomes_worth'} <= set(crowd['summary']['ε=0.0'])
    assert (tmp_path / 'implicit.png').stat().st_size > 0 and 'exchange' not in (tmp_path / 'results.md').read_text()


class _Mean:
    """A fold-in whose posterior is the mean of its targets (z = score): errors by hand."""

    def prior_distribution(self, user_id):
        return np.array([0.5]), None, None

    def to_z(self, scores, actions):
        return np.asarray(scores, dtype=np.float64)

    def posterior(self, x, y, actions, user_id, implicit):
        return np.array([np.mean(y)]), None


class _Design:
    def __init__(self, scores):
        self.foldin = _Mean()
        self.data = type('Data', (), {'scores': np.asarray(scores, dtype=np.float64)})()

    def rows(self, rows):
        return np.ones((len(rows), 1)), np.zeros(len(rows)), None, np.zeros(len(rows), dtype=np.int64)

    def predict(self, test, theta):
        return np.full(len(test), theta[0])

    def posterior(self, rows):
        return np.array([np.mean(self.data.scores[rows])]), None


def test_the_expected_errors_weigh_every_outcome_sequence_by_its_probability():
    """Pool rows 0 (true 0.8) and 1 (true 0.3), test row 2 (true 0.6); the posterior is the
    mean outcome. One outcome, on row 0 or row 1 (the start, equally likely): stayed (1.0)
    with p 0.8 or 0.3, left (0.0) with 0.2 or 0.7. Two: the four sequences, the same from
    either start. And the draws' average tends to the same expectation."""
    design = _Design([0.8, 0.3, 0.6])
    person = Person(pool=(np.array([0]), np.array([1])), test=np.array([2]))
    model, scale = OutcomeModel(0.0), (0.0, 1.0)
    one = expected_mse_implicit(design, person, 1, model, scale)
    assert one == pytest.approx([((0.8 * 0.4 ** 2 + 0.2 * 0.6 ** 2) + (0.3 * 0.4 ** 2 + 0.7 * 0.6 ** 2)) / 2])
    two = expected_mse_implicit(design, person, 2, model, scale)
    by_hand = (0.8 * 0.3 * 0.4 ** 2 + 0.8 * 0.7 * 0.1 ** 2 + 0.2 * 0.3 * 0.1 ** 2 + 0.2 * 0.7 * 0.6 ** 2)
    assert two == pytest.approx([by_hand])
    rng = np.random.default_rng(0)
    drawn = np.mean([mse_implicit(design, person, 2, model, rng, scale) for _ in range(20000)])
    assert drawn == pytest.approx(by_hand, abs=0.003)
    assert expected_mse_implicit(design, person, 0, model, scale) == pytest.approx([0.1 ** 2])  # the prior mean


def test_explicit_ratings_are_averaged_over_where_the_robot_starts():
    """k = 1 from row 0 (true 0.8) or row 1 (true 0.3), test row 2 (true 0.6): errors 0.2² and
    0.3², equally likely; k = 2 rates both from either start (posterior 0.55)."""
    design = _Design([0.8, 0.3, 0.6])
    person = Person(pool=(np.array([0]), np.array([1])), test=np.array([2]))
    assert mse_explicit(design, person, 1) == pytest.approx([(0.2 ** 2 + 0.3 ** 2) / 2])
    assert mse_explicit(design, person, 2) == pytest.approx([0.05 ** 2])


def test_a_fold_that_loses_is_named_though_the_mean_over_folds_gains():
    """Two folds: unpersonalised 0.5 and 0.3; one implicit outcome gives 0.4 (−0.1) and 0.32
    (+0.02): the mean gains (0.36 < 0.40), fold 1 loses by 0.02, and explicit ratings lose nowhere."""
    folds = [{'explicit': {'0': 0.5, '1': 0.45}, 'implicit ε=0.0': {'0': 0.5, '1': 0.4}},
             {'explicit': {'0': 0.3, '1': 0.29}, 'implicit ε=0.0': {'0': 0.3, '1': 0.32}}]
    curves = {curve: {n: {'mean': np.mean([f[curve][n] for f in folds]), 'sd': 0.0} for n in ('0', '1')}
              for curve in folds[0]}
    summary = implicit_run.summarise(curves, [0, 1], [0, 1], [0.0], folds)
    assert summary['ε=0.0']['never_worse_than_unpersonalised']
    assert [(fold, n) for fold, n, _ in summary['ε=0.0']['failing_folds']] == [(1, 1)]
    assert summary['ε=0.0']['failing_folds'][0][2] == pytest.approx(0.02)
    assert summary['explicit']['failing_folds'] == []
