"""The Python front door, ``stars_ros.StarsRecommender``: the README's example run verbatim,
and the API's contract on tiny generated data sets (a second or less each)."""
import math
import pickle
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from stars_ros import Prediction, StarsRecommender, load_dataset
from stars_ros.data.scene_source import socnav1_root
from stars_ros.errors import DataError, StarsError, UnknownActionError, UnknownSceneError
from stars_ros.evaluation import crowd_data
from stars_ros.model.config import ExperimentConfig
from stars_ros.errors import NotFittedError
from stars_ros.evaluation.executors import FitTask, fit_and_predict
from stars_ros.model.metrics import regression_report
from test_support import synthetic_socnav

REPO = Path(__file__).resolve().parents[1]
TABULAR = {'encoder': {'name': 'mlp', 'hidden': 16, 'layers': 1}, 'model': {'dim': 8},
           'training': {'pretrain_epochs': 2, 'joint_epochs': 3, 'lr': 1.0e-2, 'batch_size': 32, 'threads': 1}}
GRAPH = {'encoder': {'name': 'gcn', 'hidden': 16, 'layers': 1}, 'model': {'dim': 8},
         'training': {'pretrain_epochs': 1, 'joint_epochs': 2, 'lr': 3.0e-3, 'batch_size': 64, 'threads': 1}}


def readme_example() -> str:
    text = (REPO / 'README.md').read_text()
    section = text.split('\n## Python front door\n', 1)[1].split('\n## ', 1)[0]
    found = re.search(r'```python\n(.*?)```', section, re.S)
    assert found, 'README.md: the "Python front door" section has no ```python block'
    return found.group(1)


@pytest.mark.socnav1
def test_readme_example_runs_verbatim(tmp_path, monkeypatch):
    """The README's block as written, on SocNav1, in a scratch folder holding its config."""
    if not (socnav1_root() / 'raw').is_dir():
        pytest.skip(f'needs SocNav1, not found at {socnav1_root()} (set STARS_SOCNAV1_ROOT)')
    (tmp_path / 'config').mkdir()
    shutil.copy(REPO / 'config' / 'quickstart.yaml', tmp_path / 'config')
    monkeypatch.chdir(tmp_path)
    namespace = {}
    exec(compile(readme_example(), 'README.md (Python front door)', 'exec'), namespace)
    assert (tmp_path / 'model.pt').exists()


@pytest.fixture(scope='module')
def tabular(tmp_path_factory):
    """Generic-format data: 8 raters, 24 scenes of 5 features, 2 actions, scores 1-5."""
    annotations, scenes = crowd_data.generate(crowd_data.CrowdShape(users=8, scenes=24, features=5,
                                                                    raters_per_scene=4, latent=2), seed=1)
    root = tmp_path_factory.mktemp('tabular')
    annotations[annotations.action.isin(['vacuum', 'mop'])].to_csv(root / 'annotations.csv', index=False)
    scenes.to_csv(root / 'scenes.csv', index=False)
    return load_dataset(root)


@pytest.fixture(scope='module')
def graphs(tmp_path_factory):
    """SocNav1-format data: 5 annotators, 60 small scene graphs."""
    shape = synthetic_socnav.SocNavShape(users=5, scene_pairs=30, ratings=100, min_ratings=10)
    return load_dataset(synthetic_socnav.write(tmp_path_factory.mktemp('graphs'), shape, seed=2))


@pytest.fixture(scope='module')
def fitted(tabular):
    return StarsRecommender(TABULAR).fit(tabular)


def rows_of(data, user=None):
    """(user, scene id) of the data's ratings, ``user``'s only when given."""
    return [(u, data.scene_keys[s]) for u, s in zip(data.users, data.scenes) if user in (None, u)]


def test_fit_returns_self_and_takes_a_config_object_yaml_or_dict(tabular):
    recommender = StarsRecommender(ExperimentConfig.from_dict(TABULAR))
    assert recommender.fit(tabular, np.arange(40)) is recommender
    assert set(recommender.users) <= set(tabular.users[:40].tolist())
    assert StarsRecommender(REPO / 'config' / 'quickstart.yaml').config.model.dim == 8
    assert 'not fitted' in repr(StarsRecommender())


def test_predict_before_fit_says_to_fit_or_load():
    with pytest.raises(NotFittedError, match='fit'):
        StarsRecommender(TABULAR).predict('u', 's000', 'mop')


@pytest.mark.parametrize('kind', ['tabular', 'graphs'])
def test_predict_is_the_score_rank_gives(kind, request, fitted):
    data = request.getfixturevalue(kind)
    recommender = fitted if kind == 'tabular' else StarsRecommender(GRAPH).fit(data)
    user, scene = rows_of(data)[0]
    content = data.store.scene(0) if kind == 'tabular' else None
    for who, where in [(user, scene), ('stranger', scene)] + ([(user, list(content))] if content is not None else []):
        ranking = recommender.rank(who, where)
        assert [r.rank for r in ranking] == list(range(1, len(recommender.actions) + 1))
        assert [r.score for r in ranking] == sorted((r.score for r in ranking), reverse=True)
        for entry in ranking:
            prediction = recommender.predict(who, where, entry.name)
            assert isinstance(prediction, float) and prediction == entry.score == prediction.est
            assert prediction.details == ranking.details
            low, high = data.scale
            assert low <= prediction <= high


def test_unknown_user_and_scene_fall_back_and_say_so(fitted, tabular):
    user, scene = rows_of(tabular)[0]
    content = list(tabular.store.scene(tabular.scene_keys.index(scene)))
    known = fitted.predict(user, scene, 'mop')
    assert 'reason' not in known.details and known.details['known_user'] and known.details['known_scene']
    assert known.user == user and known.scene == scene and known.action == 'mop'
    assert fitted.predict('stranger', scene, 'mop').details['reason'] == 'unknown user'
    assert fitted.predict(None, scene, 'mop').details['reason'] == 'unknown user'
    as_content = fitted.predict(user, content, 'mop')  # content carries no id: no q_i, b_i
    assert as_content.details['reason'] == 'unknown scene' and as_content.scene is None
    assert fitted.predict('stranger', content, 'mop').details['reason'] == 'unknown user; unknown scene'
    # the fallback is the predictor's one stranger (the prior's mean p_u, b_u), whatever the id
    assert fitted.predict('stranger', content, 'mop') == fitted.predict('another stranger', content, 'mop')
    assert fitted.rank('stranger', scene).details['reason'] == 'unknown user'


def test_a_base_model_has_no_user_or_scene_term_to_fall_back_from(tabular):
    base = StarsRecommender(ExperimentConfig.from_dict(TABULAR).replace(model={'variant': 'base'})).fit(tabular)
    user, scene = rows_of(tabular)[0]
    assert 'reason' not in base.predict('stranger', list(tabular.store.scene(0)), 'mop').details
    assert base.predict('stranger', scene, 'mop') == base.predict(user, scene, 'mop')


def test_scene_ids_the_data_lacks_and_unknown_actions_are_refused(fitted, tabular):
    with pytest.raises(UnknownSceneError, match="no scene 'nowhere'"):
        fitted.predict('u', 'nowhere', 'mop')
    with pytest.raises(UnknownActionError):
        fitted.predict('u', tabular.scene_keys[0], 'juggle')


def test_an_identifier_with_two_contents_asks_which(graphs):
    recommender = StarsRecommender(GRAPH).fit(graphs)
    doubled = [key for key in graphs.scene_keys if '#' in key]
    assert len(doubled) == 2
    with pytest.raises(UnknownSceneError, match='2 different contents'):
        recommender.predict('a', doubled[0].split('#')[0], 'navigate')
    assert recommender.predict('a', doubled[0], 'navigate').details['known_scene'] in (True, False)


@pytest.mark.parametrize('kind', ['tabular', 'graphs'])
def test_fold_in_changes_that_users_predictions_and_no_one_elses(kind, request):
    data = request.getfixturevalue(kind)
    recommender = StarsRecommender(TABULAR if kind == 'tabular' else GRAPH).fit(data)
    action = data.action_names[0]
    scenes = list(dict.fromkeys(scene for _, scene in rows_of(data)))[:6]
    other = str(data.users[0])
    before = {who: [recommender.predict(who, s, action) for s in scenes] for who in ('newcomer', other)}
    high = data.scale[1]
    assert recommender.fold_in('newcomer', [(s, action, high) for s in scenes[:3]]) is recommender
    after = {who: [recommender.predict(who, s, action) for s in scenes] for who in ('newcomer', other)}
    assert after[other] == before[other]
    assert all(a > b for a, b in zip(after['newcomer'], before['newcomer']))  # rated high: scored higher
    assert after['newcomer'][0].details['folded_in'] == 3 and 'reason' not in after['newcomer'][0].details
    assert recommender.rank('newcomer', scenes[0])[0].score == max(
        recommender.predict('newcomer', scenes[0], a) for a in recommender.actions)
    # the front door serves through its predictor, as the node does
    assert recommender.predictor.personalised_from('newcomer') == 3
    assert recommender.fold_in('newcomer', []).predict('newcomer', scenes[0], action) == before['newcomer'][0]


def test_fold_in_checks_its_ratings(fitted, tabular):
    scene = tabular.scene_keys[0]
    for bad in [(scene, 'mop'), (scene, 'mop', 'high'), (scene, 'mop', 9.0), (scene, 'mop', math.nan)]:
        with pytest.raises(ValueError, match='rating 0'):
            fitted.fold_in('x', [bad])
    with pytest.raises(ValueError, match='user id'):
        fitted.fold_in(None, [(scene, 'mop', 3.0)])


def test_save_and_load_give_identical_predictions(fitted, tabular, tmp_path):
    digest = fitted.save(tmp_path / 'model.pt')
    loaded = StarsRecommender.load(tmp_path / 'model.pt', data=tabular)
    assert loaded.fingerprint == digest and fitted.fingerprint == ''
    assert loaded.config == fitted.config and loaded.users == fitted.users and loaded.actions == fitted.actions
    content = list(tabular.store.scene(3))
    for user, scene in rows_of(tabular)[:20] + [('stranger', tabular.scene_keys[0]), ('stranger', content)]:
        for action in fitted.actions:
            assert loaded.predict(user, scene, action) == fitted.predict(user, scene, action)
            assert loaded.predict(user, scene, action).details == fitted.predict(user, scene, action).details
        assert loaded.rank(user, scene) == fitted.rank(user, scene)
    without_data = StarsRecommender.load(tmp_path / 'model.pt')
    assert without_data.predict('stranger', content, 'mop') == fitted.predict('stranger', content, 'mop')
    with pytest.raises(UnknownSceneError, match='no data to look ids up in'):
        without_data.predict('stranger', tabular.scene_keys[0], 'mop')
    assert loaded.save(tmp_path / 'again.pt') == StarsRecommender.load(tmp_path / 'again.pt').fingerprint


def test_fit_leaves_torch_global_state_as_it_found_it(tabular):
    threads = torch.get_num_threads()
    torch.set_num_threads(2)  # the config trains with 1
    try:
        torch.manual_seed(1234)
        state = torch.random.get_rng_state()
        StarsRecommender(TABULAR).fit(tabular)
        assert torch.get_num_threads() == 2
        assert torch.equal(torch.random.get_rng_state(), state)
        assert torch.get_default_dtype() == torch.float32
    finally:
        torch.set_num_threads(threads)


def test_a_prediction_is_a_float_that_keeps_its_details_through_pickle(fitted, tabular):
    prediction = fitted.predict('stranger', tabular.scene_keys[0], 'mop')
    assert isinstance(prediction, Prediction) and float(prediction) + 0.0 == prediction.est
    copy = pickle.loads(pickle.dumps(prediction))
    assert copy == prediction and copy.details == prediction.details and copy.user == 'stranger'
    assert 'unknown user' in repr(prediction)


def test_the_front_door_imports_from_the_package_root():
    import stars_ros
    assert {'StarsRecommender', 'load_dataset'} <= set(dir(stars_ros))
    with pytest.raises(AttributeError):
        stars_ros.no_such_name  # noqa: B018


def test_load_dataset_by_name_reads_socnav1_where_the_setting_says(tmp_path, monkeypatch):
    root = synthetic_socnav.write(tmp_path / 'elsewhere', synthetic_socnav.SocNavShape(users=3, scene_pairs=6,
                                                                                         ratings=20, min_ratings=4))
    monkeypatch.setenv('STARS_SOCNAV1_ROOT', str(root))
    assert socnav1_root() == root
    assert load_dataset('socnav1').source == str(root / 'raw')
    assert load_dataset(root, kind='socnav1').fingerprint == load_dataset('SocNav1').fingerprint
    monkeypatch.setenv('STARS_SOCNAV1_ROOT', str(tmp_path / 'missing'))
    with pytest.raises(DataError, match='STARS_SOCNAV1_ROOT'):
        load_dataset('socnav1')
    with pytest.raises(ValueError, match='unknown kind'):
        load_dataset(root, kind='csv')


def test_predict_batch_is_predict_one_by_one(fitted, tabular):
    content = list(tabular.store.scene(2))
    requests = [(user, scene, action) for user, scene in rows_of(tabular)[:6] for action in fitted.actions]
    requests += [('stranger', content, 'mop'), (None, tabular.scene_keys[1], 'vacuum')]
    batch = fitted.predict_batch(requests)
    assert len(batch) == len(requests)
    for (user, scene, action), prediction in zip(requests, batch):
        one = fitted.predict(user, scene, action)
        assert prediction == pytest.approx(one, abs=1e-6) and prediction.details == one.details
        assert (prediction.user, prediction.action) == (user, action)


def test_score_sd_and_why_come_when_asked(fitted, tabular):
    user, scene = rows_of(tabular)[0]
    plain = fitted.predict(user, scene, 'mop')
    assert plain.score_sd is None and plain.why is None
    full = fitted.predict(user, scene, 'mop', uncertainty=True, explain=True)
    assert full == plain and full.score_sd > 0
    assert full.why.content + full.why.personal + full.why.scene == pytest.approx(float(full), abs=1e-4)
    assert len(full.why.entities) == tabular.store.feature_dim  # a tabular scene's entities: its features
    ranking = fitted.rank(user, scene, uncertainty=True)
    assert all(entry.score_sd > 0 for entry in ranking) and 0 <= ranking.p_first_is_best <= 1
    assert fitted.rank(user, scene).p_first_is_best is None


def test_a_base_model_gives_why_but_no_score_sd(tabular):
    base = StarsRecommender(ExperimentConfig.from_dict(TABULAR).replace(model={'variant': 'base'})).fit(tabular)
    scene = tabular.scene_keys[0]
    assert base.predict('u', scene, 'mop', explain=True).why.personal_from == 'none'
    with pytest.raises(StarsError, match='personalised'):
        base.predict('u', scene, 'mop', uncertainty=True)


def test_rank_scenes_orders_candidates_by_the_actions_score(fitted, tabular):
    user, _ = rows_of(tabular)[0]
    candidates = [list(tabular.store.scene(k)) for k in range(4)]
    with pytest.raises(UnknownActionError, match="say which 'action'"):
        fitted.rank_scenes(user, candidates)
    ranking = fitted.rank_scenes(user, candidates, action='mop')
    assert sorted(entry.name for entry in ranking) == ['0', '1', '2', '3']
    for entry in ranking:
        assert entry.score == pytest.approx(fitted.predict(user, candidates[int(entry.name)], 'mop'), abs=1e-6)
    by_id = fitted.rank_scenes(user, list(tabular.scene_keys[:3]), action='vacuum', uncertainty=True)
    assert {entry.name for entry in by_id} == set(tabular.scene_keys[:3]) and by_id.p_first_is_best is not None


def test_test_scores_held_out_rows_as_the_fitted_model_does(tabular, tmp_path):
    rows = np.arange(len(tabular))
    recommender = StarsRecommender(TABULAR).fit(tabular, rows[:150])
    figures = recommender.test(tabular, rows[150:])
    assert figures['n'] == len(rows) - 150 and figures['mse'] >= 0 and set(figures) >= {'rmse', 'pearson_r', 'ccc'}
    assert recommender.test(rows=rows[150:]) == figures  # the data it was fitted on
    recommender.save(tmp_path / 'model.pt', metrics=figures)
    loaded = StarsRecommender.load(tmp_path / 'model.pt')
    assert loaded.test(tabular, rows[150:]) == pytest.approx(figures)
    assert loaded.checkpoint_metadata['metrics'] == figures
    with pytest.raises(ValueError, match='needs data'):
        loaded.test()


def test_test_scores_a_stranger_as_predict_serves_them(tabular, tmp_path):
    """``test`` scores each rating as ``predict`` serves it: a person the model was not trained
    on gets the prior's mean, the row the node serves a stranger, not the zero row."""
    stranger = tabular.users[0]
    fitted = StarsRecommender(TABULAR).fit(tabular, np.flatnonzero(tabular.users != stranger))
    # a prior mean away from zero (this small fit's is zero), else the two rows would agree anyway
    fitted.fitted.user_prior['mean'] = torch.linspace(-0.5, 0.5, TABULAR['model']['dim'] + 1, dtype=torch.float64)
    fitted.save(tmp_path / 'model.pt')
    recommender = StarsRecommender.load(tmp_path / 'model.pt', data=tabular)
    theirs = np.flatnonzero(tabular.users == stranger)
    served = np.array([recommender.predict(stranger, tabular.scene_keys[tabular.scenes[row]],
                                           tabular.action_names[tabular.actions[row]]) for row in theirs])
    assert recommender.test(tabular, theirs) == regression_report(tabular.scores[theirs], served,
                                                                  tabular.actions[theirs])
    predictor, dim = recommender.predictor, TABULAR['model']['dim']
    h = predictor.encode([tabular.store.scene(s) for s in tabular.scenes[theirs]])
    keys = [tabular.scene_keys[s] for s in tabular.scenes[theirs]]
    zero = (np.zeros(dim, np.float32), np.float32(0))
    zero_row = predictor.inference.scores(h, zero, predictor.scene_rows(keys))
    assert not np.allclose(zero_row[np.arange(len(theirs)), tabular.actions[theirs]], served, atol=1e-5)


@pytest.mark.parametrize('kind, strangers', [('tabular', 'prior_mean'), ('graphs', 'base_encoder')])
def test_evaluates_predictions_are_what_the_saved_fit_serves_exactly(kind, strangers, request, tmp_path):
    """The one scoring path: ``evaluate``'s prediction of a test rating (``executors.fit_and_predict``)
    is exactly ``StarsRecommender.load`` of that fit's checkpoint's ``predict`` of it, for a
    known person's held-out ratings and for a stranger's, on a tabular and a graph backbone."""
    data = request.getfixturevalue(kind)
    config = ExperimentConfig.from_dict(TABULAR if kind == 'tabular' else GRAPH).replace(
        model={'strangers': strangers})
    stranger, known = data.users[0], data.users[-1]
    theirs, mine = np.flatnonzero(data.users == stranger), np.flatnonzero(data.users == known)
    test = np.sort(np.concatenate([theirs, mine[::3]]))
    train = np.setdiff1d(np.arange(len(data)), test)
    task = FitTask('StARS', '0:0', 'final', config.to_dict(), train, test)
    fitted, predictions, _ = fit_and_predict(task, data)
    fitted.recommender.save(tmp_path / 'fit.pt')
    loaded = StarsRecommender.load(tmp_path / 'fit.pt', data=data)
    served = [loaded.predict(data.users[row], data.scene_keys[data.scenes[row]],
                             data.action_names[data.actions[row]]) for row in test]
    assert predictions.tolist() == [float(score) for score in served]
    assert loaded.predictor.hands_over(stranger) == (strangers == 'base_encoder')
    assert loaded.predictor.knows_user(known) and not loaded.predictor.knows_user(stranger)


@pytest.mark.parametrize('kind', ['tabular', 'graphs'])
def test_strangers_served_the_base_encoder_get_the_plain_encoders_scores(kind, request):
    """With ``model.strangers`` 'base_encoder' a person the model was not trained on is scored
    as the plain encoder fitted on the same ratings scores everyone; the trained people
    exactly as by the same model serving strangers the prior's mean."""
    data = request.getfixturevalue(kind)
    config = ExperimentConfig.from_dict(TABULAR if kind == 'tabular' else GRAPH)
    stranger = data.users[0]
    train, theirs = np.flatnonzero(data.users != stranger), np.flatnonzero(data.users == stranger)
    served = StarsRecommender(config.replace(model={'strangers': 'base_encoder'})).fit(data, train)
    base = StarsRecommender(config.replace(model={'variant': 'base'})).fit(data, train)
    prior_mean = StarsRecommender(config).fit(data, train)
    assert served.test(data, theirs) == base.test(data, theirs) != prior_mean.test(data, theirs)
    others = np.flatnonzero(data.users == data.users[-1])
    assert served.test(data, others) == prior_mean.test(data, others) != base.test(data, others)


@pytest.mark.parametrize('kind', ['tabular', 'graphs'])
def test_a_stranger_is_served_the_base_encoder_until_their_first_rating(kind, request, tmp_path):
    """Served as ``test`` scores them: predict and rank give a stranger the plain encoder's
    scores, its explanation is all content, its score_sd the prior's and its
    p_first_is_best centred on those scores; from the first rating on, the fold-in takes over
    from the plain encoder (by hand: its score plus σ xᵀ(θ − θ₀), θ the posterior of targets
    z − (z_plain − xᵀθ₀)); a saved and loaded checkpoint serves the same."""
    data = request.getfixturevalue(kind)
    config = ExperimentConfig.from_dict(TABULAR if kind == 'tabular' else GRAPH)
    served = StarsRecommender(config.replace(model={'strangers': 'base_encoder'})).fit(data)
    base = StarsRecommender(config.replace(model={'variant': 'base'})).fit(data)
    prior_mean = StarsRecommender(config).fit(data)
    served.save(tmp_path / 'model.pt')
    loaded = StarsRecommender.load(tmp_path / 'model.pt', data=data)
    (user, scene), action = rows_of(data)[0], data.action_names[0]
    for model in (served, loaded):
        assert model.predict('stranger', scene, action) == base.predict('stranger', scene, action)
        assert model.predict(user, scene, action) == prior_mean.predict(user, scene, action)
        ranking = model.rank('stranger', scene, uncertainty=True, explain=kind == 'tabular')
        expected = base.rank('stranger', scene)
        assert [(r.name, r.score) for r in ranking] == [(r.name, r.score) for r in expected]
        as_prior = {r.name: r for r in prior_mean.rank('stranger', scene, uncertainty=True)}
        for entry in ranking:
            assert entry.score_sd == pytest.approx(as_prior[entry.name].score_sd)
            if entry.why is not None:  # graph scenes are explained from their dicts (below)
                assert entry.why.personal_from == 'base_encoder' and entry.why.personal == 0
                assert model.predictor.clip(np.array([entry.why.content])) == pytest.approx(entry.score, abs=1e-9)
    # p_first_is_best draws θ around the mean of a Spread centred on the scores served
    from stars_ros.personalisation.foldin import FoldIn
    from stars_ros.personalisation.uncertainty import Uncertainty
    predictor = served.predictor
    h = predictor.encode([data.store.scene(0)]).astype(np.float64)
    columns = np.arange(len(data.action_names))
    served_z = np.linspace(-1.0, 1.0, len(columns))
    spread = Uncertainty(FoldIn(predictor)).spread(predictor, 'stranger', np.repeat(h, len(columns), 0),
                                                   np.full(len(columns), -1), columns, served_z=served_z)
    assert spread.x @ spread.theta + spread.c == pytest.approx(served_z)
    high, column = data.scale[1], 0
    inference, theta0 = predictor.inference, FoldIn(predictor).population
    mean, sd = inference.target_mean[column], inference.target_std[column]

    def linear_and_plain(scene_id):  # x, c of the scene's rating of ``action``, and the plain encoder's z
        content = data.store.scene(list(data.scene_keys).index(scene_id))
        h = predictor.encode([content]).astype(np.float64)
        x, c = inference.linear_form(h, predictor.scene_rows([scene_id]), np.array([column]))
        plain = predictor.stranger_scores(predictor.encoder_input([content]), 1)[0, column]
        return x, c, (plain - mean) / sd

    other = next(key for _, key in rows_of(data) if key != scene)
    for model in (served, loaded):
        model.fold_in('newcomer', [(scene, action, high)])
        x, _, plain_z = linear_and_plain(scene)
        theta, _ = FoldIn(model.predictor).posterior(x, np.array([(high - mean) / sd - plain_z + x[0] @ theta0]),
                                                      np.array([column]))
        for key in (scene, other):
            x, _, plain_z = linear_and_plain(key)
            expected = model.predictor.clip(np.array([mean + sd * (plain_z + x[0] @ (theta - theta0))]))[0]
            assert model.predict('newcomer', key, action) == pytest.approx(expected, abs=1e-5)
        assert model.predict('newcomer', scene, action) != base.predict('stranger', scene, action)
    if kind == 'tabular':
        content = data.store.scene(list(data.scene_keys).index(scene))
        plain = predictor.stranger_scores(predictor.encoder_input([content]), 1)[0]
        for entry in served.rank('newcomer', content, explain=True):
            why = entry.why
            assert why.personal_from == 'folded_in' and why.personal != 0 and why.scene == 0
            assert why.content == pytest.approx(plain[data.action_names.index(entry.name)], abs=1e-6)
            assert served.predictor.clip(np.array([why.content + why.personal]))[0] == pytest.approx(entry.score,
                                                                                                    abs=1e-6)
    else:  # a data set's scene id gives a featurised graph, which names no entities to explain
        with pytest.raises(StarsError, match='needs its content'):
            served.rank('newcomer', scene, explain=True)
    served.fold_in('newcomer', [])  # nothing folded in: a stranger again
    assert served.predict('newcomer', scene, action) == base.predict('stranger', scene, action)


def test_refit_makes_folded_in_users_trained_ones(fitted, tabular):
    from stars_ros.personalisation.foldin import Rating
    scenes = [(tabular.scene_keys[k], list(tabular.store.scene(k))) for k in range(4)]
    ratings = {'newcomer': [Rating(content, 'mop', 5.0, key) for key, content in scenes]}
    refitted = fitted.refit(ratings)
    assert set(refitted.solved) == {'newcomer'} and not refitted.failed and refitted.ratings == 0
    child = refitted.recommender
    assert 'newcomer' in child.users and 'newcomer' not in fitted.users
    fitted.fold_in('newcomer', [(key, 'mop', 5.0) for key, _ in scenes])
    try:
        for key, _ in scenes:
            assert child.predict('newcomer', key, 'mop') == pytest.approx(fitted.predict('newcomer', key, 'mop'),
                                                                          abs=1e-5)
            assert child.predict('newcomer', key, 'mop').details['known_user']
    finally:
        fitted.fold_in('newcomer', [])
    tuned = fitted.refit(ratings, epochs=1)
    assert tuned.ratings == 4 and len(tuned.losses) == 1
