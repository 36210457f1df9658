"""The node's fold-in orchestration without ROS, on the tiny checkpoint: which feedback
becomes a rating, the solve and its bounds, eviction, a reload after a refit, the state
store across a restart, and the scene memory feedback is matched against."""

import math

import numpy as np
import pytest

from stars_ros import messages
from stars_ros.personalisation import online as personalisation
from stars_ros.personalisation import stack
from stars_ros.errors import SceneGraphError, StarsError
from stars_ros.personalisation.foldin import FoldIn, Rating
from stars_ros.messages import Feedback
from stars_ros.personalisation.online import Personalisation
from stars_ros.personalisation.scene_memory import SceneMemory
from stars_ros.model.predictor import Predictor
from stars_ros.data.scene_source import read_scenes, scene_request
from stars_ros.node.batching import Pending, rank_batch
from stars_ros.state import PersonUpdate, StateStore, loaded
from state_fill import fill_store


class Log:
    """Stands in for the node's report and logger."""

    def __init__(self):
        self.reports, self.lines = [], []

    def __call__(self, kind, detail):
        self.reports.append((kind, detail))

    def info(self, line):
        self.lines.append(('info', line))

    def warning(self, line):
        self.lines.append(('warning', line))


@pytest.fixture()
def predictor(tiny_checkpoint):
    return Predictor.load(tiny_checkpoint)


@pytest.fixture(scope='module')
def scenes(synthetic_root):
    return read_scenes(synthetic_root / 'raw' / 'h.jsonl')[:6]


def _personalisation(predictor, log, max_ratings=200, max_users=1000, **kwargs):
    return Personalisation(predictor, max_ratings, max_users, log, log, **kwargs)


def _rank(core: Personalisation, scene_id: str, payload: dict) -> str:
    """Receive and rank a request as the node does; returns its text."""
    text = messages.dumps(payload)
    core.scenes.received(scene_id, text)
    [scored] = rank_batch(core.predictor, [Pending(messages.parse_scene_request(text), None, 0, text)])
    core.scenes.ranked(scene_id, text, core.predictor, scored.h, scored.plain)
    return text


def _rate(core, user_id, scene, score=1.0, **rated) -> str | None:
    scene_id = scene['identifier']
    if core.scenes.get(scene_id)[0] is None:
        _rank(core, scene_id, scene_request(scene_id, scene))
    return core.add_feedback(Feedback(user_id, scene_id, score, **(rated or {'action': 'navigate'})))


def test_feedback_on_a_ranked_scene_is_solved_from_its_h_and_served(predictor, scenes, monkeypatch):
    log = Log()
    core = _personalisation(predictor, log)
    expected = FoldIn(predictor).fit([Rating(scenes[0], 'navigate', 1.0, scenes[0]['identifier'])], 'newcomer', 0.5)
    _rank(core, scenes[0]['identifier'], scene_request(scenes[0]['identifier'], scenes[0]))

    def encode(*args, **kwargs):
        raise AssertionError('the solve encoded a scene its ranking had encoded')
    monkeypatch.setattr(predictor, 'encode', encode)
    assert _rate(core, 'newcomer', scenes[0]) is None and list(core.pending) == ['newcomer']
    user_id, model = core.solve_next(min_ratings=1, regularisation=0.5)
    assert user_id == 'newcomer' and model.n_ratings == 1 and model.regularisation == 0.5
    assert np.allclose(model.p, expected.p, atol=1e-5) and model.b == pytest.approx(expected.b, abs=1e-5)
    assert predictor.user_model('newcomer') is model and predictor.personalised_from('newcomer') == 1
    assert core.solve_next() is None and not core.pending and log.reports == []


def test_a_person_served_around_the_plain_encoder_is_solved_without_another_pass_of_either_encoder(
        tiny_base_stranger_checkpoint, scenes, monkeypatch):
    """Ranking a person served around the plain encoder keeps that encoder's scores with h
    (``Scored.plain``), for an action's scene and for a candidate scene: the solve after their
    feedback passes neither encoder again and gives the hand-over fold-in computed from scratch."""
    predictor = Predictor.load(tiny_base_stranger_checkpoint)
    core = _personalisation(predictor, Log())
    placements = scene_request('placements', scenes[1], placements=3)
    _rank(core, scenes[0]['identifier'], scene_request(scenes[0]['identifier'], scenes[0]))
    _rank(core, 'placements', placements)

    def encoded(*args, **kwargs):
        raise AssertionError('the solve passed a scene its ranking had encoded through an encoder')
    for method in ('encode', 'encoder_input', 'stranger_scores'):
        monkeypatch.setattr(predictor, method, encoded)
    assert _rate(core, 'newcomer', scenes[0]) is None
    assert core.add_feedback(Feedback('newcomer', 'placements', 0.25,
                                      candidate=placements['candidates'][2]['candidate'])) is None
    user_id, model = core.solve_next(min_ratings=2)
    monkeypatch.undo()
    ratings = core.histories.ratings('newcomer')
    assert user_id == 'newcomer' and len(ratings) == 2 and ratings[1].scene_id is None
    expected = FoldIn(Predictor.load(tiny_base_stranger_checkpoint)).fit(ratings, 'newcomer')
    assert np.allclose(model.p, expected.p, atol=1e-6) and model.b == pytest.approx(expected.b, abs=1e-6)
    assert np.allclose(model.covariance, expected.covariance, atol=1e-9)


def test_feedback_that_names_no_usable_rating_says_why(predictor, scenes):
    log = Log()
    core = _personalisation(predictor, log)
    unknown = core.add_feedback(Feedback('ann', 'never-seen', 1.0, action='navigate'))
    assert "scene 'never-seen', which this node has not ranked (or no longer remembers)" in unknown
    placements = scene_request('placements', scenes[1], placements=3)
    _rank(core, 'placements', placements)
    assert 'ranked candidate scenes' in core.add_feedback(Feedback('ann', 'placements', 1.0, action='navigate'))
    assert "had no candidate 'elsewhere'" in core.add_feedback(Feedback('ann', 'placements', 1.0,
                                                                         candidate='elsewhere'))
    assert 'its request no longer passes' in core.add_feedback(
        Feedback('ann', 'placements', 1.0, candidate=placements['candidates'][0]['candidate']), max_bytes=16)
    assert not core.pending and len(core.histories) == 0
    label = placements['candidates'][2]['candidate']
    assert core.add_feedback(Feedback('ann', 'placements', 0.5, candidate=label)) is None
    [rating] = core.histories.ratings('ann')
    assert rating.scene == placements['candidates'][2]['graph'] and rating.scene_id is None


@pytest.mark.parametrize('strangers', ['prior_mean', 'base_encoder'])
def test_a_restored_person_is_encoded_a_few_scenes_a_call_and_once(strangers, request, synthetic_root, tmp_path):
    """A person restored with 40 ratings whose scenes the store holds no h of: the executor
    is held for PREPARE_ROWS encodings at a time, not a whole history. The store then keeps
    the h it computed, so the next time that person is restored unsolved, they are solved
    in two calls (their 40 rows from the stored h, then the solve), to the same model,
    without the encoder. With a plain encoder for strangers each row also takes a pass of it,
    which the store does not keep: the second restore is spread like the first."""
    checkpoint = request.getfixturevalue('tiny_checkpoint' if strangers == 'prior_mean'
                                         else 'tiny_base_stranger_checkpoint')
    many = [scene for name in 'ab' for scene in read_scenes(synthetic_root / 'raw' / f'{name}.jsonl')][:40]
    predictor = Predictor.load(checkpoint)
    ratings = [Rating(scene, 'navigate', (k % 5) / 4, scene['identifier'], f'r{k}') for k, scene in enumerate(many)]
    fill_store(tmp_path, predictor.fingerprint, [PersonUpdate('ann', None, predictor.fingerprint, ratings, 0, [],
                                                              False)])

    def restored(predictor):
        core = _personalisation(predictor, Log(), store=_store(tmp_path, pytest.fail))
        core.restore()
        assert list(core.pending) == ['ann']
        calls = 0
        while (solved := core.solve_next()) is None:
            assert list(core.pending) == ['ann']  # first in line until solved
            calls += 1
        core.flush()
        core.store.close()
        return calls, solved

    calls, (user_id, model) = restored(predictor)
    assert calls == math.ceil(40 / personalisation.PREPARE_ROWS) - 1
    expected = FoldIn(predictor).fit(ratings, 'ann')
    assert user_id == 'ann' and model.n_ratings == 40
    np.testing.assert_allclose(model.p, expected.p, rtol=1e-6, atol=1e-9)

    unsolved = [PersonUpdate('ann', None, predictor.fingerprint, ratings, 0, [], False)]
    fill_store(tmp_path, predictor.fingerprint, unsolved)  # to be solved again: the h it needs are stored
    predictor = Predictor.load(checkpoint)
    predictor.encode = lambda scenes: pytest.fail('a stored h was encoded again')
    calls, (_, again) = restored(predictor)
    assert calls == (1 if strangers == 'prior_mean' else math.ceil(40 / personalisation.PREPARE_ROWS) - 1)
    np.testing.assert_array_equal(again.p, model.p)


def test_a_user_is_served_once_they_have_min_ratings(predictor, scenes):
    core = _personalisation(predictor, Log())
    _rate(core, 'ann', scenes[0])
    assert core.solve_next(min_ratings=2) is None and predictor.user_model('ann') is None and not core.pending
    _rate(core, 'ann', scenes[1], 0.0)
    assert core.solve_next(min_ratings=2)[1].n_ratings == 2


def test_the_user_who_rated_least_recently_goes_back_to_the_checkpoint(predictor, scenes):
    log = Log()
    core = _personalisation(predictor, log, max_ratings=2, max_users=1)
    for scene in scenes[:3]:
        _rate(core, 'ann', scene)
    assert len(core.histories.ratings('ann')) == 2 and core.histories.dropped('ann') == 1
    core.solve_next()
    _rate(core, 'bob', scenes[3])
    assert predictor.user_model('ann') is None and 'ann' not in core.histories
    assert log.reports == [('user_models', "folded-in user 'ann' dropped: more than fold_in_max_users = 1 users "
                                           'rated more recently (their feedback stays in the MCAP log for the '
                                           'offline refit)')]


def test_a_rating_the_model_cannot_encode_leaves_the_history_reported(predictor, scenes, monkeypatch):
    log = Log()
    core = _personalisation(predictor, log)
    _rate(core, 'ann', scenes[0])
    _rate(core, 'ann', scenes[1])
    bad = core.histories.ratings('ann')[1].scene
    encode = core.foldin.encode

    def refusing(batch):
        if any(scene is bad for scene in batch):
            raise SceneGraphError('a node outside the room')
        return encode(batch)
    monkeypatch.setattr(core.foldin, 'encode', refusing)
    user_id, model = core.solve_next()
    assert model.n_ratings == 1 and core.histories.dropped('ann') == 1
    assert log.reports == [('scene_graph', "feedback of 'ann' not folded in: a node outside the room")]


def test_a_reload_keeps_only_the_feedback_a_refit_did_not_absorb(predictor, tiny_checkpoint, scenes):
    core = _personalisation(predictor, Log())
    for user_id, rated in (('ann', scenes[:2]), ('bob', scenes[2:3])):
        for scene in rated:
            _rate(core, user_id, scene)
    while core.solve_next() is not None:
        pass
    refit = Predictor.load(tiny_checkpoint)
    refit.metadata = {**refit.metadata, 'provenance': {'refit': {'ratings_per_user': {'ann': 1, 'bob': 1}}}}
    core.use(refit)
    assert core.predictor is refit and core.foldin.predictor is refit
    assert list(core.pending) == ['ann'] and 'bob' not in core.histories
    assert [r.scene_id for r in core.histories.ratings('ann')] == [scenes[1]['identifier']]
    user_id, model = core.solve_next()
    assert user_id == 'ann' and refit.user_model('ann') is model and model.n_ratings == 1
    assert refit.user_model('bob') is None


def _store(folder, log):
    return StateStore(folder, '/ranker', lambda text: log('recording', text))


def test_folded_in_users_survive_a_restart_with_the_same_checkpoint_only(tiny_checkpoint, scenes, tmp_path):
    first = _personalisation(Predictor.load(tiny_checkpoint), Log(), store=_store(tmp_path, pytest.fail))
    _rate(first, 'ann', scenes[0])
    _rate(first, 'bob', scenes[0])  # folded in, never solved: solved again after the restart
    _rate(first, 'ann', scenes[1], 0.25)
    _, model = first.solve_next()
    first.flush()  # a clean shutdown writes the models solved since their last write
    assert first.store.close() == []
    log = Log()
    restarted = _personalisation(Predictor.load(tiny_checkpoint), log, store=_store(tmp_path, log))
    restarted.restore()
    restored = restarted.predictor.user_model('ann')
    assert np.array_equal(restored.p, model.p) and restored.b == model.b and restored.n_ratings == 2
    assert np.array_equal(loaded(restored.covariance), model.covariance)  # read when first used
    assert [r.score for r in restarted.histories.ratings('ann')] == [1.0, 0.25]
    assert list(restarted.pending) == ['bob'] and restarted.predictor.user_model('bob') is None
    assert log.lines == [('info', f'restored 1 folded-in users from {tmp_path / "state.db"} (1 to solve again)')]
    assert not log.reports
    restarted.store.close()
    other_checkpoint = Predictor.load(tiny_checkpoint)
    other_checkpoint.fingerprint = '0' * 64
    other = _personalisation(other_checkpoint, log, store=_store(tmp_path, log))
    other.restore()
    assert not other.predictor.user_models and len(other.histories) == 0
    [(kind, detail)] = log.reports
    assert kind == 'user_models' and detail.endswith('folded-in users are not restored')
    other.store.close()


def test_a_restored_persons_ratings_are_read_at_first_use_and_then_reported_once(tiny_checkpoint, scenes,
                                                                                  tmp_path):
    first = _personalisation(Predictor.load(tiny_checkpoint), Log(), store=_store(tmp_path, pytest.fail))
    _rate(first, 'ann', scenes[0])
    _rate(first, 'bob', scenes[1])
    first.solve_next(), first.solve_next()
    assert first.store.close() == []
    reads = []
    restarted = _personalisation(Predictor.load(tiny_checkpoint), Log(), store=_store(tmp_path, pytest.fail),
                                 after_person_read=lambda: reads.append(len(reads)))
    restarted.restore()
    assert reads == []  # a restart reads people, not their ratings
    assert [r.score for r in restarted.histories.ratings('ann')] == [1.0]
    assert len(reads) == 1
    restarted.histories.ratings('ann')
    _rate(restarted, 'ann', scenes[2])
    assert len(reads) == 1  # once per person
    assert len(restarted.histories.ratings('bob')) == 1 and len(reads) == 2
    restarted.store.close()


def test_a_model_without_users_serves_without_fold_in(predictor, scenes, monkeypatch):
    def refuse(predictor, **options):
        raise StarsError("fold-in needs a personalised model; this one is 'base'")
    monkeypatch.setattr(stack, 'FoldIn', refuse)
    log = Log()
    core = _personalisation(predictor, log)
    assert core.foldin is None and log.lines == [('warning', 'no online fold-in with this checkpoint: fold-in needs '
                                                             "a personalised model; this one is 'base'")]
    assert _rate(core, 'ann', scenes[0]) is None
    assert core.solve_next() is None and not predictor.user_models


def test_scene_memory_keeps_the_latest_requests_and_ignores_a_stale_ranking():
    memory = SceneMemory(size=2)
    for scene_id in ('a', 'b', 'c'):
        memory.received(scene_id, f'text {scene_id}')
    assert memory.get('a') == (None, None) and len(memory) == 2
    memory.received('b', 'newer b')
    memory.ranked('b', 'text b', 'predictor', 'h')  # the older request under that id
    assert memory.get('b') == ('newer b', None)
    memory.ranked('b', 'newer b', 'predictor', 'h', 'plain')
    assert memory.get('b') == ('newer b', ('predictor', 'h', 'plain'))
    memory.received('d', 'text d')  # b was received last, so c goes
    assert memory.get('c') == (None, None) and memory.get('b')[0] == 'newer b'
