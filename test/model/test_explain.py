"""stars_ros.model.explain: the parts of a score sum to it exactly, and a planted effect is
found first, for a GNN (the tiny GCN) and a tabular (MLP) StARS."""
import csv
import copy

import numpy as np
import pytest

from stars_ros.data.ratings import load_dataset
from stars_ros.data.scene_graph import NODE_TYPES, entity_nodes, featurise, without_node
from stars_ros.model.config import ExperimentConfig
from stars_ros.model.explain import explain, removal_effects, score_parts
from stars_ros.model.vocabulary import UNKNOWN
from stars_ros.model.predictor import Predictor
from stars_ros.model.training import StarsTrainer


def _unclipped(predictor, user_id, h, scene_rows):
    theta = predictor.user_theta(user_id).astype(np.float32)
    return predictor.inference.scores(h, (theta[:-1], theta[-1]), scene_rows)


def _check_parts_sum(predictor, user_id, h, scene_rows):
    actions = np.arange(len(predictor.actions))
    served = _unclipped(predictor, user_id, h, scene_rows)
    for row in range(len(h)):
        parts = score_parts(predictor, user_id, np.repeat(h[row:row + 1], len(actions), 0),
                            np.full(len(actions), scene_rows[row]), actions)
        np.testing.assert_allclose(parts.sum(0), served[row], rtol=0, atol=1e-6)
    return served


@pytest.fixture(scope='module')
def gcn(tiny_checkpoint):
    return Predictor.load(tiny_checkpoint)


def test_gnn_parts_sum_to_the_unclipped_score(gcn, synthetic_scenes):
    h = gcn.encode(synthetic_scenes[:20])
    user = gcn.served.user_vocabulary.keys[0]
    ids = [s['identifier'] for s in synthetic_scenes[:20]]
    trained = gcn.scene_rows(ids)
    assert np.abs(score_parts(gcn, user, h, trained, np.zeros(20, dtype=np.int64))[2]).max() > 0  # b_i counts
    for scene_rows, scene_ids in ((np.full(20, UNKNOWN), None), (trained, ids)):
        served = _check_parts_sum(gcn, user, h, scene_rows)
        np.testing.assert_allclose(gcn.clip(served), gcn.score(user, synthetic_scenes[:20], scene_ids), atol=1e-6)


def test_a_strangers_personal_part_is_the_prior_means(gcn, synthetic_scenes):
    h = gcn.encode(synthetic_scenes[:3])
    _check_parts_sum(gcn, 'nobody', h, np.full(3, UNKNOWN))
    mean = np.asarray(gcn.served.user_prior['mean'])
    assert np.abs(mean).sum() > 0
    inference = gcn.inference
    actions = np.zeros(3, dtype=np.int64)
    expected = ((mean[:-1] * h * inference.action_rows[0]).sum(1) + mean[-1]) * inference.target_std[0]
    parts = score_parts(gcn, 'nobody', h, np.full(3, UNKNOWN), actions)
    np.testing.assert_allclose(parts[1], expected, atol=1e-6)
    scene_effects = removal_effects(gcn, 'nobody', synthetic_scenes[:3])
    whys = explain(gcn, 'nobody', h, np.full(3, UNKNOWN), actions, [(f, e[:, 0]) for f, e in scene_effects], 2)
    assert [w.personal_from for w in whys] == ['prior'] * 3 and all(len(w.entities) == 2 for w in whys)


def test_removing_a_node_is_featurising_the_scene_without_it(synthetic_scenes):
    scene = next(s for s in synthetic_scenes if len(s.get('humans') or ()) >= 2 and not s.get('links'))
    human_id, _, node = next(e for e in entity_nodes(scene) if e[1] == 'human')
    reduced = copy.deepcopy(scene)
    reduced['humans'] = [h for h in reduced['humans'] if h['id'] != human_id]
    expected, removed = featurise(reduced), without_node(featurise(scene), node)
    np.testing.assert_array_equal(removed.x, expected.x)
    np.testing.assert_array_equal(removed.edge_index, expected.edge_index)
    np.testing.assert_array_equal(removed.edge_type, expected.edge_type)


def test_entity_nodes_are_in_featurises_order(synthetic_scenes):
    scene = next(s for s in synthetic_scenes if s.get('links') and s.get('objects'))
    graph = featurise(scene)
    kinds = [NODE_TYPES[k] for k in graph.x[:, :len(NODE_TYPES)].argmax(1)]
    assert [(kind, node) for _, kind, node in entity_nodes(scene)] == list(zip(kinds[1:], range(1, len(kinds))))


def _human(identifier, x_cm, y_cm):
    return {'id': identifier, 'xPos': x_cm, 'yPos': y_cm, 'orientation': 0.0}


def test_a_planted_human_is_ranked_first(gcn, monkeypatch):
    """A hand-built scene and an encoder whose h is the sum of exp(-distance) of its humans:
    the human 0.5 m ahead drives the score, the walls, room and objects do nothing."""
    scene = {'identifier': 'planted', 'room': [[-500, -500], [500, -500], [500, 500], [-500, 500]],
             'humans': [_human(7, 300, 400), _human(3, 0, 50), _human(9, -400, -300)],
             'objects': [{'id': 4, 'xPos': 100, 'yPos': 100, 'orientation': 0.0}], 'links': [[7, 4, 'interact']]}
    human_row, distance = NODE_TYPES.index('human'), 6 + 2

    def closeness(graphs):
        return np.stack([np.full(gcn.inference.dim, np.exp(-g.x[g.x[:, human_row] == 1, distance]).sum())
                         for g in graphs]).astype(np.float32)

    monkeypatch.setattr(gcn.inference, '_encode', closeness)
    user = gcn.served.user_vocabulary.keys[0]
    (found, effects), = removal_effects(gcn, user, [scene])
    for column in range(len(gcn.actions)):
        order = np.argsort(-np.abs(effects[:, column]))
        assert found[order[0]][:2] == (3, 'human'), effects[:, column]
        others = [k for k, entity in enumerate(found) if entity[1] != 'human']
        np.testing.assert_allclose(effects[others, column], 0, atol=1e-6)


@pytest.fixture(scope='module')
def planted_mlp(tmp_path_factory):
    """An MLP-StARS on tabular scenes whose score is driven by feature 0 alone (a user's
    taste sets its sign)."""
    rng = np.random.default_rng(3)
    root = tmp_path_factory.mktemp('planted_tabular')
    x = rng.normal(size=(120, 4))
    with (root / 'scenes.csv').open('w', newline='') as handle:
        writer = csv.writer(handle)
        writer.writerow(['scene', 'f0', 'f1', 'f2', 'f3'])
        writer.writerows([f's{i}'] + list(row) for i, row in enumerate(x))
    with (root / 'annotations.csv').open('w', newline='') as handle:
        writer = csv.writer(handle)
        writer.writerow(['user', 'scene', 'action', 'score'])
        for u in range(8):
            for i in rng.choice(120, size=50, replace=False):
                writer.writerow([f'u{u}', f's{i}', 'pass', f'{np.clip(3 + (1 if u % 2 else -1) * x[i, 0], 1, 5):.3f}'])
    data = load_dataset(root)
    config = ExperimentConfig.from_dict({'encoder': {'name': 'mlp', 'hidden': 16, 'layers': 2},
                                         'model': {'variant': 'stars', 'dim': 8},
                                         'training': {'pretrain_epochs': 5, 'joint_epochs': 40, 'lr': 1e-2,
                                                      'batch_size': 64, 'threads': 1}})
    return Predictor.from_model(StarsTrainer(config).fit(data, np.arange(len(data))))


def test_tabular_parts_sum_and_the_planted_feature_is_first(planted_mlp):
    rows = np.array([[1.5, 0.2, -0.1, 0.3], [-1.2, 0.0, 0.4, -0.2], [2.0, 0.0, 0.0, 0.0]], dtype=np.float32)
    h = planted_mlp.encode(rows)
    for user in ('u0', 'u1', 'nobody'):
        _check_parts_sum(planted_mlp, user, h, np.full(3, UNKNOWN))
    for user in ('u0', 'u1'):
        for found, effects in removal_effects(planted_mlp, user, rows):
            assert [entity[1] for entity in found] == ['feature'] * 4
            assert found[int(np.argmax(np.abs(effects[:, 0])))][0] == 0, effects[:, 0]
