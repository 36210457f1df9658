"""The packaged model, models/socnav1_gat_stars.pt, which the ranker serves when its
checkpoint parameter is empty: it keeps its rating scale and its personalisation prior, every
score it serves for SocNav1 scenes lies on that scale, and models/README.md quotes its
held-out figures as the checkpoint stores them."""
import re
from pathlib import Path

import numpy as np
import pytest

from stars_ros.data.scene_source import placement_candidates, read_scenes
from stars_ros.model.checkpoint import read_checkpoint
from stars_ros.model.predictor import Predictor
from stars_ros.resources import resolve_checkpoint

pytestmark = pytest.mark.socnav1
REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope='module')
def packaged():
    return Predictor.load(resolve_checkpoint(''))


def test_the_packaged_checkpoint_keeps_its_rating_scale_and_prior():
    content = read_checkpoint(resolve_checkpoint(''))
    assert content['metadata']['rating_scale'] == [0.0, 1.0]  # SocNav1: score / 100
    assert 'user_prior' in content  # the Gaussian prior the node's fold-in starts from


def test_every_score_it_serves_for_socnav1_scenes_lies_on_its_scale(packaged, socnav1_root):
    """Every 40th scene of every annotator's file, for every trained user and a stranger,
    alone and as candidate robot placements (the demo's requests)."""
    low, high = packaged.metadata['rating_scale']
    scenes = [scene for path in sorted((socnav1_root / 'raw').glob('*.jsonl')) for scene in read_scenes(path)[::40]]
    assert len(scenes) > 200
    for user in [*packaged.users, 'a stranger']:
        scores = packaged.score(user, scenes)
        assert np.isfinite(scores).all() and scores.min() >= low and scores.max() <= high, user
        for scene in scenes[:10]:
            placements = placement_candidates(scene, 8)
            ranked = packaged.rank_scenes(user, [c['graph'] for c in placements], [c['candidate'] for c in placements])
            assert all(low <= entry.score <= high for entry in ranked), user


def test_models_readme_quotes_the_checkpoints_held_out_figures():
    metrics = read_checkpoint(resolve_checkpoint(''))['metadata']['metrics']
    text = ' '.join((REPO / 'models' / 'README.md').read_text().split())
    quoted = dict(re.findall(r'(MSE|RMSE|Pearson r|CCC) (0\.\d+)', text.split('held-out figures')[1]))
    assert quoted == {'MSE': f"{metrics['mse']:.4f}", 'RMSE': f"{metrics['rmse']:.3f}",
                      'Pearson r': f"{metrics['pearson_r']:.3f}", 'CCC': f"{metrics['ccc']:.3f}"}
