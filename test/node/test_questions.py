"""Uncertainty and questions in the ranker's work without ROS, on the generated data's tiny
checkpoint: every ranking entry carries score_sd and the ranking p_first_is_best, both shrink
as a person's feedback arrives, and a question request is answered with the candidate the
A-optimal criterion picks, or refused with a reason."""
import numpy as np
import pytest

from stars_ros import messages
from stars_ros.data.scene_source import placement_candidates, scene_request
from core_harness import Node, make_core


def _scene(core, scene, user_id, scene_id):
    core.accept_scene(messages.dumps(scene_request(scene_id, scene, user_id)), 0)
    while core.work():
        pass


def _feedback(core, user_id, scene_id, score):
    assert core.accept_feedback(messages.dumps({'user_id': user_id, 'scene_id': scene_id, 'action': 'navigate',
                                                'score': score}))
    while core.work():
        pass


def test_every_entry_carries_score_sd_and_it_shrinks_with_feedback_the_population_explains(tiny_checkpoint,
                                                                                           synthetic_scenes):
    node = Node()
    core = make_core(node, tiny_checkpoint)
    probe = synthetic_scenes[40]
    _scene(core, probe, 'newcomer', 'probe-0')
    before = node.on('stars/ranking')[-1]
    messages.check('ranking', before)
    assert all(entry['score_sd'] > 0 for entry in before['ranking'])
    assert before['p_first_is_best'] == 1.0  # one action: the first is the only one
    for k, scene in enumerate(synthetic_scenes[:12]):  # answers as served: the small prior scales win
        _scene(core, scene, 'newcomer', f'rated-{k}')
        _feedback(core, 'newcomer', f'rated-{k}', node.on('stars/ranking')[-1]['ranking'][0]['score'])
    _scene(core, probe, 'newcomer', 'probe-1')
    after = node.on('stars/ranking')[-1]
    assert after['personalised_from'] == 12
    assert after['ranking'][0]['score_sd'] < before['ranking'][0]['score_sd']


def test_candidate_scenes_carry_the_probability_that_the_first_is_best(tiny_checkpoint, synthetic_scenes):
    node = Node()
    core = make_core(node, tiny_checkpoint)
    candidates = placement_candidates(synthetic_scenes[3], 4)
    core.accept_scene(messages.dumps({'scene_id': 'placements', 'user_id': 'newcomer', 'candidates': candidates}), 0)
    while core.work():
        pass
    ranking = node.on('stars/ranking')[-1]
    messages.check('ranking', ranking)
    assert 0 < ranking['p_first_is_best'] <= 1
    assert len({entry['score_sd'] for entry in ranking['ranking']}) > 1  # each candidate its own spread


def test_a_question_request_picks_the_candidate_the_criterion_ranks_first(tiny_checkpoint, synthetic_scenes):
    node = Node()
    core = make_core(node, tiny_checkpoint)
    offered = [scene_request(f'ask-{k}', scene) for k, scene in enumerate(synthetic_scenes[50:56])]
    assert core.accept_question_request(messages.dumps({'user_id': 'newcomer', 'candidates': offered}))
    while core.work():
        pass
    answer, = node.on('stars/question')
    messages.check('question', answer)
    assert answer['user_id'] == 'newcomer' and answer['action'] == 'navigate' and answer['candidates'] == 6
    # the criterion by hand over the same rows: the largest predictive variance; its expected
    # variance reduction over the targets (the six candidates)
    personalisation = core.personalisation
    predictor, uncertainty = personalisation.predictor, personalisation.uncertainty
    h = predictor.encode(synthetic_scenes[50:56]).astype(np.float64)
    x, _ = predictor.inference.linear_form(h, np.full(6, -1), np.zeros(6, dtype=np.int64))
    covariance = uncertainty.covariance('newcomer')
    weight, noise = predictor.inference.target_std[0] ** 2, uncertainty.foldin.noise[0]
    variances = [weight * (x[k] @ covariance @ x[k] + noise) for k in range(6)]
    best = int(np.argmax(variances))
    assert answer['scene_id'] == f'ask-{best}'
    assert answer['score_sd'] == pytest.approx(np.sqrt(variances[best]))
    gain = weight * np.sum((x @ covariance @ x[best]) ** 2) / (x[best] @ covariance @ x[best] + noise)
    assert answer['expected_variance_reduction'] == pytest.approx(gain)
    # the answer, given as feedback, is folded in: the asked scene was remembered
    _feedback(core, 'newcomer', answer['scene_id'], 0.9)
    assert core.predictor.personalised_from('newcomer') == 1


def test_without_candidates_the_question_comes_from_recent_scenes_or_is_refused(tiny_checkpoint, synthetic_scenes):
    node = Node()
    core = make_core(node, tiny_checkpoint)
    assert core.accept_question_request(messages.dumps({'user_id': 'newcomer'}))
    while core.work():
        pass
    assert not node.on('stars/question')
    refusal = node.on('stars/errors')[-1]
    assert refusal['kind'] == 'no_question' and refusal['level'] == 'warning'
    for k, scene in enumerate(synthetic_scenes[:3]):
        _scene(core, scene, 'someone', f'seen-{k}')
    core.accept_question_request(messages.dumps({'user_id': 'newcomer'}))
    while core.work():
        pass
    answer, = node.on('stars/question')
    assert answer['scene_id'] in {'seen-0', 'seen-1', 'seen-2'} and answer['candidates'] == 3


def test_a_bad_question_request_is_refused_by_kind(tiny_checkpoint):
    node = Node()
    core = make_core(node, tiny_checkpoint)
    assert not core.accept_question_request('{"candidates": []}')
    assert not core.accept_question_request('not json')
    assert [e['kind'] for e in node.on('stars/errors')] == ['schema', 'malformed_json']
