"""Implicit outcomes in the Bayesian fold-in: their own, larger noise (not fake explicit
ratings), carried through the feedback message, the rating's JSON and the refusal of scores
that are not an outcome."""
import json

import numpy as np
import pytest

from stars_ros import messages
from stars_ros.model.predictor import Predictor
from stars_ros.errors import OutOfScaleError
from stars_ros.personalisation.foldin import (FoldIn, Rating, check_feedback_score, gaussian_posterior,
                                              rating_from_feedback)


@pytest.fixture()
def predictor(tiny_checkpoint):
    return Predictor.load(tiny_checkpoint)


@pytest.fixture(scope='module')
def scenes(synthetic_root):
    return [json.loads(line) for line in (synthetic_root / 'raw' / 'e.jsonl').read_text().splitlines()[:12]]


def outcome(scene, stayed: bool) -> Rating:
    message = {'user_id': 'u', 'scene_id': scene['identifier'], 'action': 'navigate', 'score': float(stayed),
               'implicit': True}
    return Rating(scene, 'navigate', float(stayed), scene['identifier'], feedback=message)


def test_an_outcome_is_the_same_row_with_the_noise_of_a_bernoulli_on_the_scale(predictor, scenes):
    foldin = FoldIn(predictor)
    explicit = [Rating(s, 'navigate', 1.0, s['identifier']) for s in scenes[:4]]
    implicit = [outcome(s, True) for s in scenes[:4]]
    assert not explicit[0].implicit and implicit[0].implicit
    x_e, y_e = foldin.regression(explicit)
    x_i, y_i = foldin.regression(implicit)
    assert np.array_equal(x_e, x_i) and np.array_equal(y_e, y_i)  # the same observation row
    std = predictor.inference.target_std[foldin.action_index(['navigate'])[0]]
    assert foldin.rating_noise(implicit) == pytest.approx(foldin.rating_noise(explicit) + 0.25 / std ** 2)
    mean, covariance, precision = foldin.prior_distribution('u')
    actions = foldin.action_index(['navigate'] * 4)
    mixture, _ = foldin.posterior(x_i, y_i, actions, 'u', [True] * 4)
    model = foldin.fit(implicit, 'u')
    assert np.append(model.p, model.b) == pytest.approx(mixture)  # the node's one way, with the outcome noise
    assert not np.allclose(mixture, foldin.posterior(x_i, y_i, actions, 'u')[0])
    plain, _ = gaussian_posterior(x_i, y_i, foldin.rating_noise(implicit), mean, precision)
    assert not np.allclose(plain, gaussian_posterior(x_i, y_i, foldin.rating_noise(explicit), mean, precision)[0])


def test_an_outcome_moves_the_person_less_than_a_rating_and_many_move_them_further(predictor, scenes):
    foldin = FoldIn(predictor)
    prior = foldin.prior('u')
    explicit = foldin.fit([Rating(scenes[0], 'navigate', 1.0, scenes[0]['identifier'])], 'u')
    one = foldin.fit([outcome(scenes[0], True)], 'u')
    many = foldin.fit([outcome(s, True) for s in scenes], 'u')

    def shift(model):
        return np.linalg.norm(np.append(model.p, model.b) - prior)
    assert 0 < shift(one) < shift(explicit)
    assert shift(many) > shift(one)
    known = [foldin.fit([r], 'e') for r in (Rating(scenes[0], 'navigate', 1.0, scenes[0]['identifier']),
                                             outcome(scenes[0], True))]  # a trained person: the plain posterior
    assert np.trace(known[1].covariance) > np.trace(known[0].covariance)  # an outcome says less


def test_the_ridge_override_weighs_outcomes_less_too(predictor, scenes):
    foldin = FoldIn(predictor)
    explicit = foldin.fit([Rating(scenes[0], 'navigate', 1.0, scenes[0]['identifier'])], 'u', regularisation=1.0)
    implicit = foldin.fit([outcome(scenes[0], True)], 'u', regularisation=1.0)
    prior = foldin.prior('u')
    assert 0 < np.linalg.norm(np.append(implicit.p, implicit.b) - prior) < np.linalg.norm(
        np.append(explicit.p, explicit.b) - prior)


def test_implicit_feedback_parses_stays_implicit_and_must_be_an_outcome(predictor, scenes):
    scene = scenes[0]
    request = messages.parse_scene_request(json.dumps({'scene_id': 's1', 'graph': scene}))
    text = json.dumps({'user_id': 'u', 'scene_id': 's1', 'action': 'navigate', 'score': 0.0, 'implicit': True})
    feedback = messages.parse_feedback(text)
    assert feedback.implicit and feedback.as_message()['implicit'] is True
    rating = rating_from_feedback(feedback, request, predictor)
    assert rating.implicit and Rating.from_json(rating.to_json()).implicit
    plain = messages.parse_feedback(json.dumps({'user_id': 'u', 'scene_id': 's1', 'action': 'navigate', 'score': 0.4}))
    assert not plain.implicit and not rating_from_feedback(plain, request, predictor).implicit
    middling = messages.parse_feedback(text.replace('0.0', '0.5'))
    with pytest.raises(OutOfScaleError, match=r'top 1 \(stayed engaged\) or bottom 0'):
        check_feedback_score(middling, predictor.rating_scale)  # the node's intake and the refit's reader
    check_feedback_score(plain, predictor.rating_scale)
    with pytest.raises(messages.BadMessage):
        messages.parse_feedback(text.replace('true', '"yes"'))


def test_the_offline_refit_folds_an_implicit_outcome_in_as_implicit(tiny_checkpoint, scenes, tmp_path):
    from offline_training import refit
    from stars_ros import recording
    with recording.Recorder(tmp_path, {}, name='session') as recorder:
        for k, scene in enumerate(scenes[:4]):
            recorder.write('/stars/scene', json.dumps({'scene_id': f's{k}', 'graph': scene}), 10 ** 9 + 2 * k)
            recorder.write('/stars/feedback', json.dumps({'user_id': 'newbie', 'scene_id': f's{k}',
                                                          'action': 'navigate',
                                                          'score': 1.0, 'implicit': True}), 10 ** 9 + 2 * k + 1)
    out = tmp_path / 'refit.pt'
    assert refit.main(['--checkpoint', str(tiny_checkpoint), '--logs', str(tmp_path / 'session'), '--out',
                       str(out)]) == 0
    parent, child = Predictor.load(tiny_checkpoint), Predictor.load(out)
    foldin = FoldIn(parent)
    messages_ = [{'user_id': 'newbie', 'scene_id': f's{k}', 'action': 'navigate', 'score': 1.0, 'implicit': True}
                 for k in range(4)]
    implicit = foldin.fit([Rating(s, 'navigate', 1.0, None, feedback=m) for s, m in zip(scenes[:4], messages_)])
    explicit = foldin.fit([Rating(s, 'navigate', 1.0, None) for s in scenes[:4]])
    parent.set_user_model('newbie', implicit)
    assert np.allclose(child.score('newbie', scenes[6:9]), parent.score('newbie', scenes[6:9]), atol=1e-5)
    parent.set_user_model('newbie', explicit)
    assert not np.allclose(child.score('newbie', scenes[6:9]), parent.score('newbie', scenes[6:9]), atol=1e-4)


def test_the_ranker_refuses_an_implicit_score_that_is_no_outcome_and_folds_in_one_that_is(tiny_checkpoint, scenes):
    from core_harness import Node, drain, make_core
    node = Node()
    core = make_core(node, tiny_checkpoint)
    core.accept_scene(json.dumps({'scene_id': 's1', 'graph': scenes[0]}), 0)
    drain(core)
    feedback = {'user_id': 'u', 'scene_id': 's1', 'action': 'navigate', 'implicit': True}
    assert not core.accept_feedback(json.dumps({**feedback, 'score': 0.5}))
    assert [e['kind'] for e in node.on('stars/errors')] == ['out_of_scale']
    assert core.accept_feedback(json.dumps({**feedback, 'score': 1.0}))
    drain(core)
    (rating,) = core.personalisation.ratings('u')
    assert rating.implicit and core.predictor.personalised_from('u') == 1
    core.close()
