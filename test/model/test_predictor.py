import json

import numpy as np
import torch
import pytest

from stars_ros.errors import CheckpointError, SceneGraphError, UnknownActionError
from stars_ros.model.checkpoint import load_checkpoint
from stars_ros.model.predictor import Predictor
from conftest import torch_scores


@pytest.fixture(scope='module')
def predictor(tiny_checkpoint):
    return Predictor.load(tiny_checkpoint)


@pytest.fixture(scope='module')
def scenes(synthetic_root):
    with open(synthetic_root / 'raw' / 'a.jsonl') as handle:
        return [json.loads(next(handle)) for _ in range(5)]


def test_rank_known_and_unknown_users(predictor, scenes):
    assert predictor.knows_user('a') and not predictor.knows_user('stranger')
    for user in ('a', 'stranger', None):
        ranking = predictor.rank(user, scenes[0])
        assert [r.name for r in ranking] == ['navigate'] and ranking[0].rank == 1
        assert 0.0 < ranking[0].score < 1.0


def test_users_get_different_scores(predictor, scenes):
    scores = {user: predictor.score(user, scenes)[:, 0] for user in predictor.users}
    assert len({tuple(np.round(s, 6)) for s in scores.values()}) > 1


def test_batch_equals_one_by_one(predictor, scenes):
    batch = predictor.score('b', scenes)
    single = np.concatenate([predictor.score('b', [s]) for s in scenes])
    assert np.allclose(batch, single, atol=1e-6)


def test_rank_scenes_best_first(predictor, scenes):
    ranking = predictor.rank_scenes('c', scenes, labels=[f'placement{k}' for k in range(5)])
    scores = [r.score for r in ranking]
    assert scores == sorted(scores, reverse=True)
    assert [r.rank for r in ranking] == [1, 2, 3, 4, 5]
    direct = predictor.score('c', scenes)[:, 0]
    assert ranking[0].name == f'placement{int(np.argmax(direct))}'


def test_unknown_action_and_bad_scene(predictor, scenes):
    with pytest.raises(UnknownActionError, match=r"unknown actions \['dance'\]"):
        predictor.rank('a', scenes[0], candidates=['dance'])
    with pytest.raises(UnknownActionError):
        predictor.rank('a', scenes[0], candidates=[])
    with pytest.raises(SceneGraphError):
        predictor.rank('a', {'humans': []})


def test_the_ranking_action_is_the_named_one_or_the_only_one(predictor, scenes):
    assert predictor.ranking_action(None) == predictor.ranking_action('navigate') == 'navigate'
    with pytest.raises(UnknownActionError, match=r"unknown actions \['dance'\]"):
        predictor.ranking_action('dance')
    with pytest.raises(UnknownActionError, match='dance'):
        predictor.rank_scenes('a', scenes, action='dance')


def test_missing_checkpoint_is_a_checkpoint_error(tmp_path):
    with pytest.raises(CheckpointError):
        Predictor.load(tmp_path / 'none.pt')


def test_predictor_matches_training_scale(predictor, synthetic, tiny_checkpoint):
    """Predictor on a raw scene == recommender on the featurised dataset row (same user)."""
    rows = np.flatnonzero(synthetic.users == 'a')[:3]
    fitted = load_checkpoint(tiny_checkpoint)[0]
    keys = [synthetic.scene_keys[s] for s in synthetic.scenes[rows]]
    batch = synthetic.store.batch(torch.from_numpy(synthetic.scenes[rows]))
    expected = torch_scores(fitted, ['a'] * len(rows), keys, batch)[:, 0]  # training's torch form
    raw = {}
    with open(synthetic.source + '/a.jsonl') as handle:
        for line in handle:
            scene = json.loads(line)
            raw[scene['identifier']] = scene
    got = [predictor.score('a', [raw[k]], [k])[0, 0] for k in keys]
    assert np.allclose(got, expected, atol=1e-5)


def test_served_scores_are_clipped_to_the_checkpoints_rating_scale(tiny_checkpoint, scenes):
    """A user row that pushes the raw score far outside [0, 1]: ranking reports the scale's
    edge, as evaluation does (the scale is stored in the checkpoint)."""
    from stars_ros.personalisation.foldin import UserModel
    predictor = Predictor.load(tiny_checkpoint)
    assert predictor.rating_scale == (0.0, 1.0)
    dim = predictor.inference.dim
    for offset, edge in ((50.0, 1.0), (-50.0, 0.0)):
        predictor.set_user_model('pushy', UserModel(np.zeros(dim), offset, 1, 1.0))
        assert predictor.rank('pushy', scenes[0])[0].score == edge
        assert np.all(predictor.score('pushy', scenes) == edge)
