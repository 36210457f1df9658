"""The numpy serving arithmetic (stars_ros.model.numpy_model) against the hand-checked StARS
prediction and against StarsModel on a trained checkpoint."""
import numpy as np
import pytest
import torch

from stars_ros.model.numpy_model import InferenceModel
from stars_ros.model.serving import arrays
from stars_ros.model.vocabulary import UNKNOWN
from stars_ros.model.checkpoint import load_checkpoint
from stars_ros.model.predictor import Predictor
from stars_ros.data.scene_graph import featurise
from stars_ros.data.scene_source import read_scenes
from stars_ros.data.scene_store import GraphStore
from conftest import torch_scores
from test_model import small_model

H = np.array([[0.5, 1.0]], dtype=np.float32)


def inference_of(model) -> InferenceModel:
    """The serving arithmetic over a small torch model's weights (its encoder's torch forward)."""
    def encode(features):
        with torch.no_grad():
            return model.encode(torch.from_numpy(features)).numpy()
    return InferenceModel(arrays(model.state_dict()), model.variant, model.encoder.out_dim, encode)


def test_scores_by_hand():
    inference = inference_of(small_model())
    user_0 = (inference.user_rows[0], inference.user_offsets[0])
    # the case of test_model.test_prediction_by_hand: user 0, scene 1 -> (1.8, -6.2)
    assert inference.scores(H, user_0, np.array([1])).tolist() == [pytest.approx([1.8, -6.2])]
    # stranger, new scene: hᵀ r_a + b -> (0.6, 0.1); known user, new scene -> (1.4, -0.6)
    stranger = (np.zeros(2, np.float32), np.float32(0))
    assert inference.scores(H, stranger, np.array([UNKNOWN])).tolist() == [pytest.approx([0.6, 0.1])]
    assert inference.scores(H, user_0, np.array([UNKNOWN])).tolist() == [pytest.approx([1.4, -0.6])]


def test_rating_scale_and_batches_of_mixed_scenes():
    model = small_model()
    model.target_mean.copy_(torch.tensor([3.0, 1.0]))
    model.target_std.copy_(torch.tensor([2.0, 0.5]))
    inference = inference_of(model)
    h = np.array([[0.5, 1.0], [0.5, 1.0]], dtype=np.float32)
    user_0 = (inference.user_rows[0], inference.user_offsets[0])
    scores = inference.scores(h, user_0, np.array([1, UNKNOWN]))
    assert scores.dtype == np.float64
    assert scores.tolist() == [pytest.approx([1.8 * 2 + 3, -6.2 * 0.5 + 1]), pytest.approx([1.4 * 2 + 3,
                                                                                            -0.6 * 0.5 + 1])]


def test_base_and_mf_variants_match_the_model():
    for variant in ('base', 'mf'):
        model = small_model(variant)
        inference = inference_of(model)
        features = np.random.default_rng(0).normal(size=(3, 3)).astype(np.float32)
        with torch.no_grad():
            h = model.encode(torch.from_numpy(features))
            expected = model.to_rating_scale(model(torch.tensor([0] * 3), torch.tensor([1] * 3), h)).numpy()
        h_np = inference.encode(features, 3)
        rows = (inference.user_rows[0], inference.user_offsets[0]) if variant == 'mf' else None
        assert np.allclose(inference.scores(h_np, rows, np.array([1, 1, 1])), expected, atol=1e-5)


@pytest.mark.parametrize('variant', ['stars', 'stars_no_residual', 'mf'])
def test_linear_form_is_the_scoring_arithmetic_in_the_user(variant):
    """z = xᵀ(p_u, b_u) + c for one action per row, residual term included only where the
    variant has it: the fold-in's regression is the model's prediction."""
    model = small_model(variant)
    inference = inference_of(model)
    h = np.random.default_rng(1).normal(size=(4, 2))
    scenes, actions = np.array([1, UNKNOWN, 0, 1]), np.array([0, 1, 1, 0])
    x, c = inference.linear_form(h, scenes, actions)
    assert x.dtype == c.dtype == np.float64 and x.shape == (4, 3) and c.shape == (4,)
    theta = np.array([1.0, 2.0, 0.3])  # user 0: p = (1, 2), b_u = 0.3
    with torch.no_grad():
        expected = model(torch.zeros(4, dtype=torch.long), torch.from_numpy(scenes), torch.from_numpy(h).float())
    assert np.allclose(x @ theta + c, expected.numpy()[np.arange(4), actions], atol=1e-5)
    stranger = inference.scores(h.astype(np.float32), (np.zeros(2, np.float32), np.float32(0)), scenes)
    assert np.allclose(inference.to_rating_scale(c, actions), stranger[np.arange(4), actions], atol=1e-5)


def test_predictor_equals_the_torch_model_on_a_trained_checkpoint(tiny_checkpoint, synthetic_root):
    predictor = Predictor.load(tiny_checkpoint)
    recommender = load_checkpoint(tiny_checkpoint)[0]  # the torch form
    scenes = read_scenes(synthetic_root / 'raw' / 'b.jsonl')[:60]
    keys = [s['identifier'] for s in scenes]  # training scenes: their q_i and b_i apply
    assert sum(k in recommender.scene_vocabulary for k in keys) > 10
    batch = GraphStore([featurise(s) for s in scenes]).batch(torch.arange(len(scenes)))
    expected = torch_scores(recommender, [recommender.users[0]] * len(scenes), keys, batch)
    assert np.allclose(predictor.score(recommender.users[0], scenes, keys), expected, atol=1e-5)
    mean = torch.as_tensor(recommender.user_prior['mean'], dtype=torch.float32)  # a stranger gets the prior's mean
    stranger = (mean[:-1].expand(len(scenes), -1), mean[-1:].expand(len(scenes), 1))
    for scene_keys in (keys, [None] * len(scenes)):
        expected = torch_scores(recommender, [None] * len(scenes), scene_keys, batch, stranger)
        assert np.allclose(predictor.score('nobody', scenes, scene_keys), expected, atol=1e-5)
    assert mean.abs().max() > 0  # the prior's mean is not the zero row an unknown user has in the table
