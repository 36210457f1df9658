"""The learning curve: a point is the fit with that many epochs, and its command line writes
its results, on generated data."""
import csv
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from offline_training import learning_curve
from stars_ros.model.config import ExperimentConfig
from stars_ros.evaluation.executors import FitTask, run_fit
from stars_ros.evaluation.folds import make_folds

REPO = Path(__file__).resolve().parents[2]



def test_learning_curve_point_is_the_fit_with_that_many_epochs(synthetic):
    """A curve point at T2 = k equals a separate fit with (T1, k): the curve only watches."""
    rows = np.arange(0, len(synthetic), 7)
    fold = make_folds(synthetic, 'rows', 2, 0, rows)[0]
    experiment = ExperimentConfig.from_dict({
        'encoder': {'name': 'gcn', 'hidden': 8, 'layers': 1}, 'model': {'dim': 8, 'variant': 'stars'},
        'training': {'pretrain_epochs': 1, 'joint_epochs': 4, 'lr': 3e-3, 'threads': 1, 'seed': 0}})
    curve = run_fit(FitTask('m', '0:0', 'curve', experiment.to_dict(), fold.train, fold.test, curve_at=(2, 4)),
                    synthetic)['curve']
    assert [point['epoch'] for point in curve] == [2, 4]
    shorter = experiment.replace(training={'joint_epochs': 2})
    alone = run_fit(FitTask('m', '0:0', 'final', shorter.to_dict(), fold.train, fold.test), synthetic)
    assert 'curve' not in alone
    for metric in ('mse', 'pearson_r', 'ccc'):
        assert curve[0][metric] == pytest.approx(alone[metric], rel=1e-6)


@pytest.mark.slow
def test_learning_curve_cli_writes_its_results(synthetic_root, tmp_path, capsys):
    protocol = tmp_path / 'protocol.yaml'
    protocol.write_text(yaml.safe_dump({
        'name': 'tiny', 'folds': 2, 'grid': [[1, 2]], 'backbones': {'gcn': {}}, 'baselines': [],
        'experiment': {'encoder': {'name': 'gcn', 'hidden': 8, 'layers': 1}, 'model': {'dim': 8},
                       'training': {'batch_size': 512, 'lr': 3e-3}}}))
    config = tmp_path / 'curve.yaml'
    config.write_text(yaml.safe_dump({
        'protocol': 'protocol.yaml', 'backbone': 'gcn', 'variants': ['base', 'stars'], 'pretrain_epochs': 1,
        'joint_epochs': 2, 'every': 1, 'settings': {'a': {'lr': 3e-3}, 'b': {'lr': 1e-3, 'embedding_l2': 0.01}}}))
    out = tmp_path / 'out'
    done = subprocess.run([sys.executable, '-m', 'offline_training.learning_curve', '--config', str(config),
                           '--data-root', str(synthetic_root), '--jobs', '1', '--out', str(out)],
                          cwd=REPO, env={**os.environ, 'PYTHONPATH': str(REPO)}, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    with (out / 'curve.csv').open() as handle:
        points = list(csv.DictReader(handle))
    assert len(points) == 2 * 2 * 2 * 2  # settings × variants × folds × epochs
    assert {(p['setting'], p['variant']) for p in points} == {(s, v) for s in 'ab' for v in ('base', 'stars')}
    assert all(0 < float(p['mse']) < 0.5 for p in points)
    assert '| T2 | a base | a stars | b base | b stars |' in (out / 'results.md').read_text()
    assert (out / 'curve_mse.png').read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    assert len((out / 'records.jsonl').read_text().splitlines()) == 8
    bad = tmp_path / 'bad.yaml'
    bad.write_text(yaml.safe_dump({'protocol': 'protocol.yaml'}))
    assert learning_curve.main(['--config', str(bad), '--data-root', str(synthetic_root),
                                '--out', str(tmp_path / 'refused')]) == 2
    assert f'{bad}: backbone: required key missing' in capsys.readouterr().err
