"""The peer libraries as protocol baselines: fitted on the training examples only, on the same
folds as StARS, refused before any fit when missing; the scene summary they read, by hand."""
import dataclasses
import json
import math

import numpy as np
import pytest
import yaml

from stars_ros import load_dataset
from stars_ros.data.scene_graph import featurise
from stars_ros.data.scene_summary import ABSENT_DISTANCE, SUMMARY_FEATURES, summarise
from stars_ros.errors import ConfigError
from stars_ros.evaluation import executors, peers
from stars_ros.evaluation.crowd_data import CrowdShape, write
from stars_ros.evaluation.protocol import ProtocolConfig, run_protocol
from stars_ros.evaluation.summaries import best_peer, by_model, grid_edge, peer_tests

pytest.importorskip('surprise')
pytest.importorskip('myfm')

SMALL = {'folds': 2, 'grid': [[1, 2]], 'backbones': {'mlp': {}}, 'variants': ['base', 'stars'],
         'baselines': ['population_mean', 'mf', 'surprise_svd', 'myfm', 'myfm_encoder'],
         'search': {'surprise_svd': {'n_factors': [4, 8]}, 'myfm': {'rank': [2, 3], 'n_iter': [20],
                                                                    'n_kept_samples': [10]}},
         'error': 'rmse', 'experiment': {'encoder': {'name': 'mlp', 'hidden': 8, 'layers': 1}, 'model': {'dim': 4}}}


@pytest.fixture(scope='module')
def crowd_root(tmp_path_factory):
    root = tmp_path_factory.mktemp('crowd')
    write(root, CrowdShape(users=30, scenes=24, features=6, raters_per_scene=5), seed=3)
    return root


@pytest.fixture(scope='module')
def crowd(crowd_root):
    return load_dataset(crowd_root)


def _split(data, seed=0):
    examples = data.examples
    test_example = np.random.default_rng(seed).random(examples.max() + 1) < 0.3
    return np.flatnonzero(~test_example[examples]), np.flatnonzero(test_example[examples])


@pytest.mark.parametrize('peer', peers.PEERS)
def test_a_peer_never_reads_the_scores_of_test_rows(crowd, peer):
    train, test = _split(crowd)
    experiment = ProtocolConfig.from_dict(SMALL).experiment_config('mlp', 'base').replace(
        training={'pretrain_epochs': 1, 'joint_epochs': 1}).to_dict()
    settings = '{"n_factors": 4}' if peer == 'surprise_svd' else '{"n_iter": 20, "n_kept_samples": 10, "rank": 2}'
    clean, _ = peers.peer_predictions(peer, settings, experiment, crowd, train, test)
    scores = crowd.scores.copy()
    scores[test] = np.where(scores[test] > 3, 1.0, 5.0)  # every test score turned over
    poisoned, _ = peers.peer_predictions(peer, settings, experiment, dataclasses.replace(crowd, scores=scores),
                                         train, test)
    np.testing.assert_array_equal(clean, poisoned)
    assert clean.min() >= 1.0 and clean.max() <= 5.0  # clipped to the rating scale
    assert np.std(clean) > 0  # it predicts something, not a constant


def test_peers_are_fitted_on_the_folds_of_stars_and_tested_against_it(crowd, monkeypatch):
    seen = []
    run_fit = executors.run_fit

    def watched(task, data=None):
        seen.append(task)
        return run_fit(task, data)
    monkeypatch.setattr(executors, 'run_fit', watched)
    result = run_protocol(crowd, ProtocolConfig.from_dict(SMALL))
    assert not result.failed
    examples = crowd.examples
    for task in seen:
        assert not set(examples[task.train]) & set(examples[task.test])  # examples kept whole
    finals = {(t.model, t.fold): t for t in seen if t.stage == 'final'}
    peer_labels = ['Surprise SVD (no content)', 'myFM (scene features)', 'myFM on MLP base h_i']
    for label in peer_labels:
        for fold in ('0:0', '0:1'):
            ours, theirs = finals['MLP StARS', fold], finals[label, fold]
            assert np.array_equal(theirs.train, ours.train) and np.array_equal(theirs.test, ours.test)
    for task in seen:
        if task.stage == 'inner' and task.peer:  # the selection sees the outer fold's training rows only
            assert set(task.test) <= set(finals['MLP StARS', task.fold].train)
    assert {t.peer for t in seen if t.stage == 'inner'} == {'surprise_svd', 'myfm'}  # myfm_encoder follows base
    final = by_model(result.final())
    assert [e['fold'] for e in final['myFM (scene features)']] == [e['fold'] for e in final['MLP StARS']]
    choice = {c['fold']: c for c in result.choices if c['model'] == 'myFM on MLP base h_i'}
    base = {c['fold']: c for c in result.choices if c['model'] == 'MLP base'}
    assert all(choice[f]['settings'] == base[f]['settings'] and choice[f]['follows'] == 'MLP base' for f in base)

    means = {label: np.mean([e['rmse'] for e in final[label]]) for label in peer_labels}
    assert best_peer(result, 'mlp') == min(means, key=means.get)
    tests = peer_tests(result, ('rmse',))
    assert [t['reference'] for t in tests] == [min(means, key=means.get)]
    assert math.isclose(tests[0]['delta'], np.mean([e['rmse'] for e in final['MLP StARS']]) - min(means.values()))
    assert grid_edge(result) == {'top_T2': 2, 'at_top': 4, 'choices': 4}


def test_a_missing_library_stops_the_run_before_any_fit(crowd, monkeypatch):
    find_spec = peers.importlib.util.find_spec
    monkeypatch.setattr(peers.importlib.util, 'find_spec', lambda name: None if name == 'myfm' else find_spec(name))
    monkeypatch.setattr(executors, 'run_fit', lambda *a, **k: pytest.fail('a fit ran'))
    with pytest.raises(ConfigError, match=r"need myfm, which is not installed: pip install -r requirements-peers"):
        run_protocol(crowd, ProtocolConfig.from_dict(SMALL))


def test_peer_settings_and_needs_are_checked_with_the_config():
    with pytest.raises(ConfigError, match=r'^search\.myfm\.rank: Input should be greater than or equal to 1'):
        ProtocolConfig.from_dict({**SMALL, 'search': {'myfm': {'rank': [0]}}})
    with pytest.raises(ConfigError, match=r'^search\.surprise_svd\.n_factor: unknown key'):
        ProtocolConfig.from_dict({**SMALL, 'search': {'surprise_svd': {'n_factor': [4]}}})
    with pytest.raises(ConfigError, match='n_kept_samples'):
        ProtocolConfig.from_dict({**SMALL, 'search': {'myfm': {'n_iter': [5], 'n_kept_samples': [10]}}})
    with pytest.raises(ConfigError, match='myfm_encoder takes the h_i'):
        ProtocolConfig.from_dict({**SMALL, 'variants': ['stars']})


def test_the_scene_summary_by_hand():
    scene = {'identifier': 's', 'robot': {'id': 0},
             'humans': [{'id': 1, 'xPos': 300, 'yPos': 400, 'orientation': 90},
                        {'id': 2, 'xPos': 0, 'yPos': -100, 'orientation': 0}],
             'objects': [{'id': 3, 'xPos': -200, 'yPos': 0, 'orientation': 0}],
             'links': [[1, 3, 'interact']],
             'room': [[-500, -500], [500, -500], [500, 500], [-500, 500], [-500, -500]]}
    summary = dict(zip(SUMMARY_FEATURES, summarise(featurise(scene).x)))
    assert (summary['humans'], summary['objects'], summary['walls'], summary['interactions']) == (2, 1, 4, 1)
    assert summary['nearest_human_distance'] == pytest.approx(1.0)  # human 2, 1 m behind
    assert summary['nearest_human_sin_bearing'] == pytest.approx(0.0, abs=1e-12)
    assert summary['nearest_human_cos_bearing'] == pytest.approx(-1.0)
    assert summary['nearest_human_cos_orientation'] == pytest.approx(1.0)
    assert summary['nearest_object_distance'] == pytest.approx(2.0)
    assert summary['nearest_wall_distance'] == pytest.approx(5.0)  # a segment's mid-point
    assert summary['room_size'] == pytest.approx(10.0)  # a 10 m × 10 m room
    alone = dict(zip(SUMMARY_FEATURES, summarise(featurise({**scene, 'humans': [], 'links': []}).x)))
    assert alone['humans'] == 0 and alone['nearest_human_distance'] == ABSENT_DISTANCE


def test_the_cli_tables_put_the_peers_beside_stars_and_a_missing_library_keeps_a_run(crowd_root, tmp_path,
                                                                                       monkeypatch):
    from offline_training import evaluate
    config = tmp_path / 'peers.yaml'
    config.write_text(yaml.safe_dump({**SMALL, 'name': 'peers'}))
    out = tmp_path / 'out'
    # --allow-dirty: what the test shows does not depend on the checkout having uncommitted changes
    assert evaluate.main(['--config', str(config), '--data-root', str(crowd_root), '--out', str(out),
                          '--allow-dirty']) == 0
    tables = (out / 'tables.md').read_text()
    for row in ('| Surprise SVD (no content) |', '| myFM (scene features) |', '| myFM on MLP base h_i |',
                '| MLP StARS |', '## StARS − the best peer library', 'chose T2 = 2, the top of the grid, in 4 of 4'):
        assert row in tables
    results = json.loads((out / 'results.json').read_text())
    assert [t['metric'] for t in results['peer_tests']] == ['rmse', 'pearson_r', 'ccc']
    records = (out / 'records.jsonl').read_text()

    find_spec = peers.importlib.util.find_spec
    monkeypatch.setattr(peers.importlib.util, 'find_spec', lambda name: None if name == 'surprise' else find_spec(name))
    assert evaluate.main(['--config', str(config), '--data-root', str(crowd_root), '--out', str(out),
                          '--allow-dirty', '--resume']) == 2
    assert (out / 'records.jsonl').read_text() == records  # refused before anything was written
