"""Shared fixtures: the real SocNav1 files and a tiny trained checkpoint."""
import os
from pathlib import Path

import pytest

from stars_ros.model.checkpoint import save_checkpoint
from stars_ros.model.config import ExperimentConfig
from stars_ros.data.ratings import load_dataset
from stars_ros.model.training import StarsTrainer, split_rows

REPO = Path(__file__).resolve().parents[1]
TINY_CONFIG = {
    'encoder': {'name': 'gcn', 'hidden': 16, 'layers': 1},
    'model': {'variant': 'stars', 'dim': 16},
    'training': {'pretrain_epochs': 1, 'joint_epochs': 2, 'lr': 3e-3, 'batch_size': 128, 'threads': 1},
}


def socnav1_path() -> Path:
    return Path(os.environ.get('STARS_SOCNAV1_ROOT', REPO.parent / 'shared' / 'datasets' / 'socnav1'))


@pytest.fixture(scope='session')
def socnav1_root() -> Path:
    root = socnav1_path()
    if not (root / 'raw').is_dir():
        pytest.fail(f'SocNav1 not found at {root}: set STARS_SOCNAV1_ROOT')
    return root


@pytest.fixture(scope='session')
def socnav1(socnav1_root):
    return load_dataset(socnav1_root)


@pytest.fixture(scope='session')
def tiny_checkpoint(socnav1, tmp_path_factory):
    """A small StARS-GCN trained on 1,500 SocNav1 ratings (a few seconds), saved to disk."""
    train, _ = split_rows(socnav1, 0.2, 0)
    recommender = StarsTrainer(ExperimentConfig.from_dict(TINY_CONFIG)).fit(socnav1, train[:1500])
    path = tmp_path_factory.mktemp('checkpoint') / 'tiny.pt'
    save_checkpoint(recommender, path, data={'fingerprint': socnav1.fingerprint, 'source': 'socnav1'})
    return path
