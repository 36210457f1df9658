"""The levers experiment's members train in the evaluation's fit executor and are kept as
each finishes (issue 50: one worker pool)."""
import numpy as np
from conftest import TINY_CONFIG

from stars_ros.evaluation import levers
from stars_ros.evaluation.folds import make_folds
from stars_ros.model.config import ExperimentConfig
from stars_ros.model.metrics import regression_report


def test_every_member_is_saved_as_it_finishes_and_the_mean_is_scored(synthetic, tmp_path):
    fold = make_folds(synthetic, 'rows', 2, 0)[0]
    (tmp_path / 'predictions').mkdir()
    experiment = ExperimentConfig.from_dict(TINY_CONFIG)
    tasks = [(levers.member_path(tmp_path, 'gcn', 'stars', '0:0', member), 'stars',
              experiment.replace(training={'seed': member}).to_dict(), fold.train, fold.test) for member in (0, 1)]
    finished = []
    levers.train_members(synthetic, tasks, jobs=1, on_member=lambda path, seconds: finished.append(path))
    assert finished == [task[0] for task in tasks]
    kept = [np.load(path) for path in finished]
    assert all(len(predictions) == len(fold.test) for predictions in kept)
    curve = levers.mean_prediction_mse(synthetic, tmp_path, 'gcn', 'stars', fold, '0:0', 2)
    y, actions = synthetic.scores[fold.test], synthetic.actions[fold.test]
    assert len(curve) == 2 and curve[1] == regression_report(y, np.mean(kept, axis=0), actions)['mse']
