"""Faithfulness of removal effects and the GNNExplainer comparison, on generated data: the
figures are what they say (checked against the removal effects and scores directly), and
the command refuses a checkpoint that records no held-out split."""
import numpy as np
import pytest

from offline_training import explain_faithfulness
from stars_ros.data.scene_graph import featurise
from stars_ros.evaluation.explanations import compare_gnnexplainer, faithfulness, held_out_scenes, robot_only
from stars_ros.model.explain import removal_effects, score_parts
from stars_ros.model.vocabulary import UNKNOWN
from stars_ros.model.checkpoint import load_checkpoint
from stars_ros.model.predictor import Predictor
from stars_ros.model.training import split_rows

pytestmark = pytest.mark.filterwarnings('ignore::UserWarning')


@pytest.fixture(scope='module')
def predictor(tiny_checkpoint):
    return Predictor.load(tiny_checkpoint)


@pytest.fixture(scope='module')
def scenes(synthetic_scenes):
    return [s for s in synthetic_scenes if len(s['humans']) >= 2][:4]


def test_held_out_scenes_have_no_training_rating(synthetic):
    train, test = split_rows(synthetic, 0.2, 0)
    held = held_out_scenes(synthetic, train, test)
    assert held and not {row for row, _ in held} & set(synthetic.scenes[train].tolist())
    for row, user in held:
        assert user in synthetic.users[test][synthetic.scenes[test] == row]


def test_faithfulness_figures(predictor, scenes):
    users = ['a'] * len(scenes)
    result = faithfulness(predictor, scenes, users, 0)
    assert result['scenes'] == len(scenes) and 0.0 <= result['top_beats_random'] <= 1.0
    shares, singles = [], []
    for scene in scenes:
        (_, effects), = removal_effects(predictor, 'a', [scene])
        graph = featurise(scene)
        h = predictor.inference.encode([graph, robot_only(graph)], 2)
        full, alone = score_parts(predictor, 'a', h, np.full(2, UNKNOWN), np.zeros(2, dtype=int)).sum(0)
        shares.append((full - alone - effects[:, 0].sum()) / abs(full - alone))
        singles.append(effects[:, 0].sum())
    assert result['interaction_share_median'] == pytest.approx(np.median(shares))
    assert result['sum_of_single_effects_median'] == pytest.approx(np.median(singles))


def test_gnnexplainer_comparison_runs_and_reports(predictor, scenes, tiny_checkpoint):
    result = compare_gnnexplainer(predictor, load_checkpoint(tiny_checkpoint)[0].require_model(), scenes[:2],
                                  ['a', 'a'], 0, epochs=5)
    assert result['scenes'] == 2 and -1.0 <= result['spearman_with_removal_median'] <= 1.0
    assert 0.0 <= result['same_top_entity'] <= 1.0 and result['gnnexplainer_ms_per_scene_p50'] > 0


def test_the_command_needs_a_recorded_split(tiny_checkpoint, synthetic_root, tmp_path, capsys):
    code = explain_faithfulness.main(['--checkpoint', str(tiny_checkpoint), '--data-root', str(synthetic_root),
                                      '--out', str(tmp_path / 'out')])
    assert code == 1 and 'records no row split' in capsys.readouterr().err
