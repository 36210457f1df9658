"""Shared fixtures: generated SocNav1-format data, a tiny checkpoint trained on it, and the
real SocNav1 files for the tests marked ``socnav1`` (skipped, saying why, without them). Every
ROS participant of the suite, in-process or started by a test, reads test/fastdds_profile.xml
(unless FASTRTPS_DEFAULT_PROFILES_FILE is set): a 100 ms writer heartbeat and a 2 s participant
lease instead of Fast DDS's 3 s and 20 s (docs/testing.md, "The suite's DDS settings")."""
import os
from pathlib import Path

import pytest

from stars_ros import StarsRecommender
from stars_ros.data.ratings import load_dataset
from stars_ros.data.scene_source import socnav1_root as default_socnav1_root
from stars_ros.data.scene_source import read_scenes
from stars_ros.model.config import ExperimentConfig
from stars_ros.model.training import split_rows
from test_support import synthetic_socnav

REPO = Path(__file__).resolve().parents[1]
os.environ.setdefault('FASTRTPS_DEFAULT_PROFILES_FILE', str(REPO / 'test' / 'fastdds_profile.xml'))
TINY_CONFIG = {
    'encoder': {'name': 'gcn', 'hidden': 16, 'layers': 1},
    'model': {'variant': 'stars', 'dim': 16},
    'training': {'pretrain_epochs': 1, 'joint_epochs': 2, 'lr': 3e-3, 'batch_size': 128, 'threads': 1},
}


def served_rows(fitted, data, rows):
    """The served form's predictions of ``rows`` of ``data`` by a fitted model held in memory
    (``model.scoring``): how every figure is scored."""
    from stars_ros.model.predictor import Predictor
    from stars_ros.model.scoring import served_predictions
    return served_predictions(Predictor.from_model(fitted), data, rows)


def served_report(fitted, data, rows) -> dict:
    """``model.metrics.regression_report`` of ``served_rows``."""
    from stars_ros.model.metrics import regression_report
    return regression_report(data.scores[rows], served_rows(fitted, data, rows), data.actions[rows])


def torch_scores(fitted, users, scene_keys, batch, user_rows=None):
    """Training's torch forward of ``fitted`` (a ``model.fitted.FittedModel``): clipped
    rating-scale scores [len(users), actions] of encoder input ``batch``, ``user_rows`` (p, b_u)
    in place of the user table's, against which the served form is checked."""
    import numpy as np
    import torch
    model = fitted.require_model()
    with torch.no_grad():
        z = model(fitted.user_index(users), fitted.scene_index(scene_keys), model.encode(batch), user_rows)
    return fitted.clip(model.to_rating_scale(z).numpy().astype(np.float64))


def socnav1_path() -> Path:
    return default_socnav1_root()


#: Where the files that start processes or train models live, heaviest first: collected first,
#: so xdist's workers (``--dist loadfile``, files handed out in collection order) take them
#: on early and end together on the many small in-process files. Any file with a ``slow`` test
#: goes before every file without one, wherever it lives.
HEAVY_FIRST = ('test_colcon_build.py', 'ros/', 'hri/', 'evaluation/', 'offline_training/', 'state/', 'node/')


def _weight_rank(item) -> int:
    path = Path(str(item.fspath)).relative_to(REPO / 'test').as_posix()
    return next((rank for rank, prefix in enumerate(HEAVY_FIRST) if path.startswith(prefix)), len(HEAVY_FIRST))


def pytest_collection_modifyitems(items):
    slow_files = {item.path for item in items if item.get_closest_marker('slow')}
    # stable: each file's tests keep their order
    items.sort(key=lambda item: (item.path not in slow_files, _weight_rank(item)))


def pytest_runtest_setup(item):
    """A test that reads SocNav1 must say so (``@pytest.mark.socnav1``); a marked test is
    skipped when the files are absent."""
    marked = item.get_closest_marker('socnav1') is not None
    if not marked and {'socnav1_root', 'socnav1'} & set(item.fixturenames):
        pytest.fail('this test reads SocNav1: mark it @pytest.mark.socnav1', pytrace=False)
    if marked and not (socnav1_path() / 'raw').is_dir():
        pytest.skip(f'needs SocNav1, not found at {socnav1_path()} (set STARS_SOCNAV1_ROOT)')


@pytest.fixture(scope='session')
def socnav1_root() -> Path:
    return socnav1_path()


@pytest.fixture(scope='session')
def socnav1(socnav1_root):
    return load_dataset(socnav1_root)


@pytest.fixture(scope='session')
def synthetic_root(tmp_path_factory) -> Path:
    """A SocNav1-format root (``raw/a.jsonl`` … ``raw/l.jsonl``) of generated data: 12
    annotators, 521 ratings of 272 small scenes, one identifier with two contents."""
    return synthetic_socnav.write(tmp_path_factory.mktemp('synthetic'), seed=0)


@pytest.fixture(scope='session')
def synthetic(synthetic_root):
    return load_dataset(synthetic_root)


@pytest.fixture(scope='session')
def synthetic_scenes(synthetic_root) -> list:
    """Every distinct scene of the generated data (first line of each identifier, in file order)."""
    scenes = {}
    for path in sorted((synthetic_root / 'raw').glob('*.jsonl')):
        for scene in read_scenes(path):
            scenes.setdefault(scene['identifier'], scene)
    return list(scenes.values())


@pytest.fixture(scope='session')
def tiny_checkpoint(synthetic, tmp_path_factory):
    """A small StARS-GCN trained on 80 % of the generated ratings (a second), saved to disk."""
    train, _ = split_rows(synthetic, 0.2, 0)
    path = tmp_path_factory.mktemp('checkpoint') / 'tiny.pt'
    StarsRecommender(TINY_CONFIG).fit(synthetic, train).save(path)
    return path


@pytest.fixture(scope='session')
def tiny_base_stranger_checkpoint(synthetic, tmp_path_factory):
    """``tiny_checkpoint``'s model serving strangers the plain encoder (``model.strangers``)."""
    train, _ = split_rows(synthetic, 0.2, 0)
    path = tmp_path_factory.mktemp('checkpoint') / 'tiny_base_stranger.pt'
    config = ExperimentConfig.from_dict(TINY_CONFIG).replace(model={'strangers': 'base_encoder'})
    StarsRecommender(config).fit(synthetic, train).save(path)
    return path
