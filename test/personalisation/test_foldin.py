"""Fold-in math on the tiny checkpoint: the design reproduces the model, the solve is the
ridge solution, the limits of λ behave, and the Predictor serves folded-in users safely."""
import json
import threading

import numpy as np
import pytest
import torch

from stars_ros import messages
from stars_ros.personalisation.foldin import FoldIn, Rating, UserModel, solve_ridge
from stars_ros.personalisation.histories import FeedbackHistories
from stars_ros.model.checkpoint import load_checkpoint
from stars_ros.model.predictor import Predictor
from stars_ros.data.scene_graph import featurise
from stars_ros.data.scene_store import GraphStore
from conftest import torch_scores


@pytest.fixture()
def predictor(tiny_checkpoint):
    return Predictor.load(tiny_checkpoint)


@pytest.fixture(scope='module')
def ratings(synthetic_root):
    """Annotator e's first ratings, at most 40 (SocNav1-format scenes, scores on [0, 1])."""
    lines = (synthetic_root / 'raw' / 'e.jsonl').read_text().splitlines()[:40]
    scenes = [json.loads(line) for line in lines]
    return [Rating(s, 'navigate', s['score'] / 100, s['identifier']) for s in scenes]


def test_design_reproduces_the_model_for_any_user_rows(predictor, ratings, tiny_checkpoint):
    """FoldIn.predict (the design) equals the served score and the torch model given the
    same (p_u, b_u) in place of a trained row."""
    foldin = FoldIn(predictor)
    rng = np.random.default_rng(0)
    theta = rng.normal(size=foldin.dim + 1)
    user = UserModel(theta[:-1], float(theta[-1]), 3, 1.0)
    predictor.set_user_model('someone', user)
    scenes, keys = [r.scene for r in ratings[:10]], [r.scene_id for r in ratings[:10]]
    expected = predictor.score('someone', scenes, keys)[:, 0]
    assert np.allclose(foldin.predict(user, ratings[:10]), expected, atol=1e-5)
    batch = GraphStore([featurise(s) for s in scenes]).batch(torch.arange(len(scenes)))
    fitted = load_checkpoint(tiny_checkpoint)[0]  # the torch form
    rows = (torch.tensor(user.p, dtype=torch.float32).expand(10, -1), torch.full((10, 1), user.b))
    expected = torch_scores(fitted, [None] * 10, keys, batch, rows)
    assert np.allclose(foldin.predict(user, ratings[:10]), expected[:, 0], atol=1e-5)
    mean = np.asarray(predictor.served.user_prior['mean'], dtype=np.float64)
    prior_mean = UserModel(mean[:-1], float(mean[-1]), 0, 1.0)  # the prior's mean: the stranger's prediction
    stranger = predictor.score('stranger', [r.scene for r in ratings[:10]], [r.scene_id for r in ratings[:10]])[:, 0]
    assert np.allclose(foldin.predict(prior_mean, ratings[:10]), stranger, atol=1e-5)


def test_design_reproduces_the_model_for_a_trained_user(predictor, ratings, tiny_checkpoint):
    """xᵀθ + c with θ the trained row of user 'a' is what InferenceModel.scores serves for
    'a', and what the torch model predicts, on scenes with and without a trained q_i."""
    recommender = load_checkpoint(tiny_checkpoint)[0]  # the torch form
    scenes, keys = [r.scene for r in ratings], [r.scene_id for r in ratings]
    assert 0 < sum(k in recommender.scene_vocabulary for k in keys) < len(keys)
    foldin = FoldIn(predictor)
    x, c, _ = foldin.design(ratings)
    designed = foldin.to_rating_scale(x @ foldin.prior('a') + c, foldin.action_index(['navigate'] * len(ratings)))
    inference = predictor.inference
    row = recommender.user_vocabulary.row('a')
    served = inference.scores(predictor.encode(scenes), (inference.user_rows[row], inference.user_offsets[row]),
                              recommender.scene_vocabulary.rows(keys))[:, 0]
    assert np.allclose(designed, recommender.clip(served), atol=1e-5)
    batch = GraphStore([featurise(s) for s in scenes]).batch(torch.arange(len(scenes)))
    assert np.allclose(designed, torch_scores(recommender, ['a'] * len(scenes), keys, batch)[:, 0], atol=1e-5)


def test_solve_is_the_ridge_solution(predictor, ratings):
    foldin = FoldIn(predictor)
    x, c, z = foldin.design(ratings)
    prior = foldin.prior()
    for regularisation in (0.1, 1.0, 10.0):
        theta = solve_ridge(x, z - c, prior, regularisation)
        # normal equations
        assert np.allclose((x.T @ x + regularisation * np.eye(len(prior))) @ theta,
                           x.T @ (z - c) + regularisation * prior, atol=1e-9)
        # the same problem as an augmented least-squares system
        stacked = np.vstack([x, np.sqrt(regularisation) * np.eye(len(prior))])
        target = np.concatenate([z - c, np.sqrt(regularisation) * prior])
        assert np.allclose(theta, np.linalg.lstsq(stacked, target, rcond=None)[0], atol=1e-8)
    with pytest.raises(ValueError):
        solve_ridge(x, z - c, prior, 0.0)


def test_regularisation_limits(predictor, ratings):
    foldin = FoldIn(predictor)
    prior = foldin.prior('stranger')
    strong = foldin.fit(ratings, 'stranger', regularisation=1e9)
    assert np.allclose(np.append(strong.p, strong.b), prior, atol=1e-6)
    few = ratings[:5]  # fewer ratings than dim + 1 unknowns: a weak prior interpolates them
    weak = foldin.fit(few, 'stranger', regularisation=1e-10)
    assert np.allclose(foldin.predict(weak, few), [r.score for r in few], atol=1e-3)
    assert weak.n_ratings == 5 and weak.regularisation == 1e-10
    empty = foldin.fit([], 'stranger')
    assert empty.n_ratings == 0 and np.allclose(np.append(empty.p, empty.b), prior)


def test_prior_is_the_trained_row_or_the_shrunk_population_mean(predictor, tiny_checkpoint):
    foldin = FoldIn(predictor)
    model = load_checkpoint(tiny_checkpoint)[0].model
    row = predictor.served.user_vocabulary.row('a')
    trained = np.append(model.user_embedding.weight[row].detach().numpy(), model.user_bias.weight[row, 0].item())
    assert np.allclose(foldin.prior('a'), trained, atol=1e-6)
    rows = np.concatenate([model.user_embedding.weight.detach().numpy(), model.user_bias.weight.detach().numpy()],
                          axis=1)
    weight = foldin.user_prior.details['mean_weight']  # James-Stein, towards the scene-only θ = 0
    assert 0 <= weight <= 1
    assert np.allclose(foldin.prior('never-seen'), weight * rows.mean(0), atol=1e-6)
    assert np.allclose(foldin.prior(None), foldin.prior('never-seen'))


def test_folded_in_user_predicts_its_ratings_better(predictor, ratings):
    foldin = FoldIn(predictor)
    y = np.array([r.score for r in ratings])
    errors = [np.mean((foldin.predict(foldin.fit(ratings if lam else [], 'e-new', lam or 1.0), ratings) - y) ** 2)
              for lam in (None, 10.0, 1.0, 0.1, 0.01)]  # None: no ratings, the prior
    assert all(later < earlier for earlier, later in zip(errors, errors[1:])), errors  # weaker prior, closer fit
    assert errors[-1] < 0.8 * errors[0], errors


def test_scene_cache_reuses_encodings_and_is_bounded(predictor, ratings, monkeypatch):
    foldin = FoldIn(predictor, cache_scenes=8)
    calls = []
    encode = predictor.encode
    monkeypatch.setattr(predictor, 'encode', lambda scenes: calls.append(1) or encode(scenes))
    scenes = [r.scene for r in ratings]
    first = foldin.encode(scenes[:4])
    assert len(calls) == 1 and np.array_equal(foldin.encode(scenes[:4]), first)  # the same objects: cached
    assert np.allclose(foldin.encode([dict(s) for s in scenes[:4]]), first) and len(calls) == 2  # copies: encoded
    rows = foldin.encode(scenes[4:20])
    assert rows.shape == (16, foldin.dim) and foldin.cached[0] == 8  # bounded, least recent dropped
    foldin.fit(ratings[20:23], 'x')
    calls.clear()
    foldin.fit(ratings[20:24], 'x')  # one more rating: only its scene is encoded
    assert len(calls) == 1


def test_overlay_serves_folded_users_and_leaves_others_alone(predictor, ratings):
    scenes = [r.scene for r in ratings[:6]]
    stranger = predictor.score('newcomer', scenes)
    trained = predictor.score('a', scenes)
    user = FoldIn(predictor).fit(ratings, 'newcomer')
    predictor.set_user_model('newcomer', user)
    assert not np.allclose(predictor.score('newcomer', scenes), stranger)
    assert np.array_equal(predictor.score('someone-else', scenes), stranger)
    assert np.array_equal(predictor.score('a', scenes), trained)
    assert predictor.personalised_from('newcomer') == len(ratings) and predictor.personalised_from('x') == 0
    assert not predictor.knows_user('newcomer')  # knows_user stays "in the training data"
    predictor.set_user_model('newcomer', None)
    assert np.array_equal(predictor.score('newcomer', scenes), stranger)


def test_overlay_swap_is_safe_while_another_thread_scores(predictor, ratings):
    scenes = [r.scene for r in ratings[:3]]
    foldin = FoldIn(predictor)
    models = [foldin.fit(ratings[:k], 'racer') for k in (5, 30)]
    expected = []
    for model in models:
        predictor.set_user_model('racer', model)
        expected.append(predictor.score('racer', scenes))
    stop = threading.Event()
    errors = []

    def write():
        k = 0
        while not stop.is_set():
            predictor.set_user_model('racer', models[k % 2])
            predictor.set_user_model(f'other-{k % 50}', models[0])
            k += 1
    writer = threading.Thread(target=write)
    writer.start()
    try:
        for _ in range(200):
            scores = predictor.score('racer', scenes)
            if not any(np.array_equal(scores, e) for e in expected):
                errors.append(scores)
    finally:
        stop.set()
        writer.join()
    assert not errors


def test_user_model_message_follows_its_schema(predictor, ratings):
    jsonschema = pytest.importorskip('jsonschema')
    user = FoldIn(predictor).fit(ratings[:3], 'u')
    payload = json.loads(messages.dumps(messages.user_model_payload('u', user, predictor.fingerprint)))
    schema = messages.load_schema('user_model')
    jsonschema.Draft202012Validator(schema).validate(payload)
    messages.check('user_model', payload)
    assert UserModel.from_json(payload).n_ratings == 3
    with pytest.raises(messages.BadMessage):
        messages.check('user_model', {**payload, 'regularisation': -1.0})  # 0 is the posterior, a λ is positive


def _rated(k):
    return Rating({'k': k}, 'a', float(k))


def test_histories_keep_the_most_recent_ratings_and_users():
    histories = FeedbackHistories(max_ratings=3, max_users=2)
    for k in range(5):
        assert histories.add('ann', _rated(k)) == []
    assert [r.score for r in histories.ratings('ann')] == [2.0, 3.0, 4.0]
    assert histories.dropped('ann') == 2
    assert histories.add('bob', _rated(10)) == []
    histories.add('ann', _rated(5))  # ann rated most recently: bob is the oldest now
    assert histories.add('cy', _rated(20)) == ['bob']
    assert 'bob' not in histories and len(histories) == 2
    assert histories.set_limits(max_ratings=1, max_users=1) == ['ann']
    assert [r.score for r in histories.ratings('cy')] == [20.0]


def test_histories_absorb_counts_ratings_already_trimmed():
    """A refit that consumed the first n ratings removes exactly those, trimmed or not."""
    histories = FeedbackHistories(max_ratings=3, max_users=10)
    for k in range(6):  # ratings 0..5; 0..2 trimmed
        histories.add('ann', _rated(k))
    histories.add('bob', _rated(100))
    assert histories.absorb({'ann': 4, 'bob': 1, 'stranger': 7}) == ['ann']
    assert [r.score for r in histories.ratings('ann')] == [4.0, 5.0]
    assert histories.dropped('ann') == 4
    assert histories.absorb({'ann': 4}) == ['ann']  # the same refit again removes nothing more
    assert histories.absorb({'ann': 6}) == []


def test_histories_discard_and_restore_round_trip():
    histories = FeedbackHistories(max_ratings=5, max_users=2)
    ratings = [_rated(k) for k in range(3)]
    for rating in ratings:
        histories.add('ann', rating)
    histories.discard('ann', [ratings[1]])
    assert histories.ratings('ann') == [ratings[0], ratings[2]] and histories.dropped('ann') == 1
    state = histories.snapshot()
    restored = FeedbackHistories(max_ratings=1, max_users=1)
    restored.add('old', _rated(9))
    assert restored.restore(state) == ['old']
    assert restored.ratings('ann') == [ratings[2]] and restored.dropped('ann') == 2
    with pytest.raises(ValueError):
        FeedbackHistories(0, 1)


def test_remembered_encodings_are_not_encoded_again(predictor, ratings, monkeypatch):
    foldin = FoldIn(predictor)
    scene = ratings[0].scene
    h = predictor.encode([scene])  # what ranking the scene computed (float32)
    monkeypatch.setattr(predictor, 'encode', lambda scenes: pytest.fail('encoded again'))
    foldin.remember([scene], h)
    assert np.array_equal(foldin.encode([scene]), h.astype(np.float64))
    foldin.fit([ratings[0]], 'x')  # solves from the remembered h


def test_regression_rows_are_computed_once_per_rating(predictor, ratings, monkeypatch):
    foldin = FoldIn(predictor, cache_scenes=16)
    x, c, z = FoldIn(predictor).design(ratings[:30])
    designed = []
    design = foldin.design
    monkeypatch.setattr(foldin, 'design', lambda rated: designed.append(len(rated)) or design(rated))
    foldin.fit(ratings[:10], 'u', 1.0)
    grown = foldin.fit(ratings[:11], 'u', 1.0)
    assert designed == [10, 1]  # a user's next rating: only its row is built
    rows, targets = foldin.regression(ratings[:11])
    assert designed == [10, 1]
    assert np.allclose(rows, x[:11], atol=1e-6) and np.allclose(targets, (z - c)[:11], atol=1e-6)
    assert np.array_equal(np.append(grown.p, grown.b), solve_ridge(rows, targets, foldin.prior('u'), 1.0))
    foldin.fit(ratings[:30], 'u', 1.0)
    assert foldin.cached[1] == 16  # bounded: the least recently used rows go, and are rebuilt when needed
    foldin.fit(ratings[:2], 'u', 1.0)
    assert designed[-1] == 2
