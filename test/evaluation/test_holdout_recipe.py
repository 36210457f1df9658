"""The hold-out recipe's ablation row (evaluation.specs.HOLDOUT_RECIPE): the recipe's hold-out
fit with its own prior, the model the recipe before the refit shipped, scored on the same test
rows in its served form by the shipped model's own fit, for StARS and for MF."""
import pytest

from conftest import TINY_CONFIG
from stars_ros.errors import NotFittedError
from stars_ros.evaluation import executors
from stars_ros.evaluation.folds import make_folds
from stars_ros.evaluation.protocol import ProtocolConfig, run_protocol
from stars_ros.evaluation.summaries import recipe_tests
from stars_ros.model.config import ExperimentConfig
from stars_ros.model.metrics import regression_report
from stars_ros.model.predictor import Predictor
from stars_ros.model.scoring import served_predictions
from stars_ros.personalisation.prior import held_out_split
from stars_ros.personalisation.recipe import Recipe

STARS_ROW = 'GCN StARS, hold-out recipe (fit on 90 %, its own prior)'
MF_ROW = 'MF (biased, no content), hold-out recipe (fit on 90 %, its own prior)'
PROTOCOL = {'folds': 2, 'grid': [[1, 2]], 'backbones': {'gcn': {'hidden': 16, 'layers': 1}},
            'variants': ['stars'], 'baselines': ['mf'], 'ablation_backbones': ['gcn'],
            'ablations': ['holdout_recipe'],
            'experiment': {'encoder': TINY_CONFIG['encoder'], 'model': {'dim': 16},
                           'training': {'lr': 3e-3, 'batch_size': 128}}}


def test_the_rows_are_the_hold_out_fit_on_fewer_rows_scored_in_served_form_by_the_same_fit(synthetic,
                                                                                            monkeypatch):
    tasks, run_fit = [], executors.run_fit

    def watched(task, data=None):
        tasks.append((task.model, task.fold, task.holdout))
        return run_fit(task, data)
    monkeypatch.setattr(executors, 'run_fit', watched)
    config = ProtocolConfig.from_dict(PROTOCOL)
    result = run_protocol(synthetic, config, 'rows')
    assert sorted(tasks) == sorted((model, fold, True) for model in ('GCN StARS', 'MF (biased, no content)')
                                   for fold in ('0:0', '0:1'))  # no fit of their own
    final = {(r['model'], r['fold']): r for r in result.final()}
    assert {model for model, _ in final} == {'GCN StARS', STARS_ROW, 'MF (biased, no content)', MF_ROW}
    fold = make_folds(synthetic, 'rows', 2, 0)[0]
    for shipped, row, variant in (('GCN StARS', STARS_ROW, 'stars'),
                                  ('MF (biased, no content)', MF_ROW, 'mf')):
        ablation, model = final[row, '0:0'], final[shipped, '0:0']
        experiment = config.experiment_config(None if variant == 'mf' else 'gcn', variant).replace(training={
            'pretrain_epochs': 0 if variant == 'mf' else 1, 'joint_epochs': 2, 'threads': 1})
        fit_rows, _ = held_out_split(synthetic, fold.train, seed=experiment.split.seed)
        assert model['n_train'] == len(fold.train) and ablation['n_train'] == len(fit_rows) < len(fold.train)
        assert (ablation['settings'], ablation['T1'], ablation['T2']) == (model['settings'], model['T1'],
                                                                         model['T2'])
        recipe = Recipe(ExperimentConfig.from_dict(experiment.to_dict()))
        recipe.fit(synthetic, fold.train)
        earlier = recipe.holdout_model()
        assert earlier.model is recipe.holdout.model and earlier.user_prior is not None
        predictions = served_predictions(Predictor.from_model(earlier), synthetic, fold.test)
        by_hand = regression_report(synthetic.scores[fold.test], predictions, synthetic.actions[fold.test])
        assert ablation['mse'] == by_hand['mse'] and ablation['ccc'] == by_hand['ccc']


def _fake_fit(task, data=None):
    scores = {'mse': 0.02, 'rmse': 0.14, 'pearson_r': 0.9, 'ccc': 0.9, 'n': len(task.test), 'z_rmse': 0.5,
              'fit_seconds': 1.0, 'predict_seconds': 0.1, 'epochs': 3}
    if task.holdout:
        scores['holdout'] = {**scores, 'mse': 0.03, 'n_train': len(task.train) - 1, 'fit_seconds': 0.0}
    return scores


def test_a_resumed_run_takes_both_rows_from_the_earlier_records(synthetic, monkeypatch):
    monkeypatch.setattr(executors, 'run_fit', _fake_fit)
    config = ProtocolConfig.from_dict(PROTOCOL)
    first = run_protocol(synthetic, config, 'rows')
    rows = {(r['model'], r['fold']): r for r in first.final()}
    assert rows[STARS_ROW, '0:0']['mse'] == 0.03 and rows[STARS_ROW, '0:0']['fit_seconds'] == 0.0
    tests = {t['model']: t for t in recipe_tests(first, 'mse')}  # the report's shipped − hold-out section
    assert set(tests) == {'GCN StARS', 'MF (biased, no content)'}
    assert all(t['delta'] == pytest.approx(-0.01) and t['at_or_below'] == 2 for t in tests.values())
    monkeypatch.setattr(executors, 'run_fit', lambda task, data=None: pytest.fail(f'{task.name} ran again'))
    again = run_protocol(synthetic, config, 'rows', resume=first.records)
    assert again.resumed == 4
    assert [(r['model'], r['mse'], r['n_train']) for r in again.final()] == \
        [(r['model'], r['mse'], r['n_train']) for r in first.final()]
    without = [r for r in first.records if r['model'] != STARS_ROW]  # recorded before the row existed
    monkeypatch.setattr(executors, 'run_fit', _fake_fit)
    assert run_protocol(synthetic, config, 'rows', resume=without).resumed == 2  # MF's only: StARS runs again


def test_the_row_needs_a_personalised_fit():
    with pytest.raises(NotFittedError, match='holdout_model'):
        base = ExperimentConfig.from_dict({**TINY_CONFIG, 'model': {'variant': 'base', 'dim': 16}})
        Recipe(base).holdout_model()
