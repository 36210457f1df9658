"""One serving model: the ranker's core and the front door (``StarsRecommender.load``) serve
a checkpoint through the same ``ServedModel``, so they give identical scores, ``score_sd`` and
fold-in results; a checkpoint is read without torch, as ``torch.load`` reads it; and the
serving process imports no torch, torch-geometric, pandas or training."""
import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from stars_ros import StarsRecommender, messages
from stars_ros.data.scene_source import read_scenes, scene_request
from stars_ros.model.checkpoint import read_checkpoint
from stars_ros.model.tensor_file import read_tensor_file
from stars_ros.resources import DEFAULT_CHECKPOINT, share_path
from core_harness import Node, drain, make_core


@pytest.fixture(scope='module')
def scenes(synthetic_root):
    return read_scenes(synthetic_root / 'raw' / 'c.jsonl')[:3]


def _entries(ranking) -> dict:
    return {entry['action']: (entry['score'], entry['score_sd']) for entry in ranking}


@pytest.mark.parametrize('strangers', ['prior_mean', 'base_encoder'])
def test_the_node_and_the_front_door_give_identical_scores_sds_and_fold_ins(strangers, request, scenes):
    checkpoint = request.getfixturevalue('tiny_checkpoint' if strangers == 'prior_mean'
                                        else 'tiny_base_stranger_checkpoint')
    node = Node()
    core = make_core(node, checkpoint)
    front_door = StarsRecommender.load(checkpoint)
    scene_ids = [f'fresh-{k}' for k in range(len(scenes))]  # no trained q_i: both score the content alone
    for user in ('a', 'newcomer'):  # a trained person and a stranger
        for scene, scene_id in zip(scenes, scene_ids):
            reply, refusal = core.rank_now(messages.dumps(scene_request(scene_id, scene, user)), 0)
            assert refusal is None
            served = _entries(reply['ranking'])
            ranked = {r.name: (r.score, r.score_sd) for r in front_door.rank(user, scene, uncertainty=True)}
            assert served == ranked  # bit for bit: one model, one arithmetic
    ratings = [(scenes[0], 'navigate', 0.9), (scenes[1], 'navigate', 0.2)]
    for (_, action, score), scene_id in zip(ratings, scene_ids):
        core.accept_feedback(messages.dumps({'user_id': 'newcomer', 'scene_id': scene_id, 'action': action,
                                             'score': score}))
        drain(core)
    front_door.fold_in('newcomer', ratings)
    node_model, door_model = core.predictor.user_model('newcomer'), front_door.predictor.user_model('newcomer')
    assert node_model.n_ratings == door_model.n_ratings == 2
    assert np.array_equal(node_model.p, door_model.p) and node_model.b == door_model.b
    assert np.array_equal(node_model.covariance, door_model.covariance)
    reply, _ = core.rank_now(messages.dumps(scene_request('fresh-9', scenes[2], 'newcomer')), 0)
    assert _entries(reply['ranking']) == {r.name: (r.score, r.score_sd)
                                          for r in front_door.rank('newcomer', scenes[2], uncertainty=True)}
    core.close()


@pytest.mark.parametrize('which', ['tiny', 'packaged'])
def test_a_checkpoint_reads_without_torch_as_torch_load_reads_it(which, tiny_checkpoint):
    path = tiny_checkpoint if which == 'tiny' else share_path(DEFAULT_CHECKPOINT)
    expected, read = torch.load(path, weights_only=True), read_tensor_file(path)

    def same(a, b):
        if torch.is_tensor(a):
            return isinstance(b, np.ndarray) and b.dtype == a.numpy().dtype and np.array_equal(a.numpy(), b)
        if isinstance(a, dict):
            return isinstance(b, dict) and list(a) == list(b) and all(same(a[k], b[k]) for k in a)
        if isinstance(a, (list, tuple)):
            return type(a) is type(b) and len(a) == len(b) and all(map(same, a, b))
        return a == b and type(a) is type(b)
    assert same(expected, read)
    assert read_checkpoint(path)['digest'] == expected['digest']  # the digest verifies over the arrays


def test_a_strided_or_shared_tensor_is_read_as_torch_wrote_it(tmp_path):
    base = torch.arange(24, dtype=torch.float64).reshape(4, 6)
    content = {'transposed': base.T, 'slice': base[1:3, ::2], 'shared': base, 'scalar': torch.tensor(2.5),
               'flags': torch.tensor([True, False]), 'ids': torch.arange(3)}
    torch.save(content, tmp_path / 'views.pt')
    read = read_tensor_file(tmp_path / 'views.pt')
    for name, tensor in content.items():
        assert np.array_equal(read[name], tensor.numpy()) and read[name].shape == tuple(tensor.shape)
    read['shared'][0, 0] = -1.0  # each array is its own copy
    assert read['transposed'][0, 0] == 0.0


def test_serving_imports_neither_torch_nor_pyg_pandas_or_training():
    """The ranker's module and the packaged model loaded, in a fresh interpreter."""
    code = ('import sys, json; import stars_ros.ros.ranker; from stars_ros import StarsRecommender; '
            'from stars_ros.model.predictor import Predictor; from stars_ros.resources import resolve_checkpoint; '
            "Predictor.load(resolve_checkpoint('')); StarsRecommender.load(resolve_checkpoint('')); "
            "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'torch_geometric', "
            "'pandas') or m.startswith(('stars_ros.model.training', 'stars_ros.model.encoders', 'scipy.stats')))))")
    done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == []


def test_the_ranker_module_leaves_the_core_to_after_its_node_exists():
    """``ros2 run stars_ros ranker`` creates its node, and so its DDS participant, before the half
    second the core's import and the checkpoint take: peers starting with it find it during
    their initial announcements (docs/performance.md, what bounds the first answer)."""
    code = ("import sys, json; import stars_ros.ros.ranker; "
            "print(json.dumps(sorted(m for m in sys.modules if m.startswith(('stars_ros.node.core', "
            "'stars_ros.personalisation', 'stars_ros.model.predictor', 'numba')))))")
    done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == []
