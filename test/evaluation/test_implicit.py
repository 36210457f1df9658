"""The implicit-outcome simulation: the stated outcome model, the exchange rate's
interpolation, and the command line end to end on the generated crowd data (quick)."""
import json

import numpy as np
import pytest

from offline_training import implicit_feedback
from stars_ros.evaluation.implicit import OutcomeModel, exchange_rate


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


@pytest.mark.slow
def test_the_command_writes_curves_and_exchange_rates(tmp_path):
    assert implicit_feedback.main(['--quick', '--datasets', 'crowd', '--out', str(tmp_path)]) == 0
    results = json.loads((tmp_path / 'results.json').read_text())
    crowd = results['datasets']['crowd']
    assert set(crowd['curves']) == {'explicit', 'implicit ε=0.0', 'implicit ε=0.2'}
    assert crowd['curves']['implicit ε=0.0']['0'] == crowd['curves']['explicit']['0']  # both start unpersonalised
    assert {'never_worse_than_unpersonalised', 'implicit_outcomes_worth'} <= set(crowd['summary']['ε=0.0'])
    assert (tmp_path / 'implicit.png').stat().st_size > 0 and 'exchange' not in (tmp_path / 'results.md').read_text()
