"""The training program end to end on generated SocNav1-format data, with a small config."""
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from stars_ros.model.checkpoint import read_checkpoint
from stars_ros.model.predictor import Predictor

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_train_writes_checkpoint_with_held_out_metrics(tmp_path, synthetic_root, synthetic):
    config = yaml.safe_load((REPO / 'config' / 'socnav1_gcn.yaml').read_text())
    config['encoder'].update(hidden=16, layers=1)
    config['model']['dim'] = 16
    config['training'].update(pretrain_epochs=1, joint_epochs=1, threads=1)
    (tmp_path / 'small.yaml').write_text(yaml.safe_dump(config))
    out = tmp_path / 'model.pt'
    result = subprocess.run([sys.executable, '-m', 'offline_training.train', '--config', str(tmp_path / 'small.yaml'),
                             '--data-root', str(synthetic_root), '--out', str(out)],
                            cwd=REPO, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert 'gcn-stars held-out: MSE' in result.stdout and 'Pearson r' in result.stdout and 'CCC' in result.stdout
    assert f'note: {synthetic.notes[0]}' in result.stdout  # the data decision is reported
    assert 'pretrain epoch 1/1: loss' in result.stderr and 'joint epoch 1/1: loss' in result.stderr
    assert 's left' in result.stderr
    metadata = read_checkpoint(out)['metadata']
    assert set(metadata['metrics']) >= {'mse', 'pearson_r', 'ccc'}
    assert metadata['data']['n_test'] == round(0.2 * len(synthetic))  # the config's split, one rating per example
    assert metadata['data']['fingerprint'] == synthetic.fingerprint and Predictor.load(out).knows_user('g')


def test_train_reports_bad_config(tmp_path, synthetic_root):
    (tmp_path / 'bad.yaml').write_text('encoder: {name: gat, widht: 3}\n')
    result = subprocess.run([sys.executable, '-m', 'offline_training.train', '--config', str(tmp_path / 'bad.yaml'),
                             '--data-root', str(synthetic_root), '--out', str(tmp_path / 'x.pt')],
                            cwd=REPO, capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and f"{tmp_path / 'bad.yaml'}: encoder.widht: unknown key" in result.stderr
