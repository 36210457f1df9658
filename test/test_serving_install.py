"""A serving install (``pip install stars_ros``, without the ``train`` extra): in a fresh
interpreter where torch, torch-geometric, pandas and matplotlib cannot be imported, as on a
robot that installed only requirements.txt, ``import stars_ros`` and the front door load and
rank graph checkpoints (the packaged GAT, the tiny GCN), the executables' modules import, and
a tabular checkpoint is refused with an error naming the extra."""
import json
import subprocess
import sys

import pytest

from stars_ros import StarsRecommender
from stars_ros.errors import INSTALL_TRAIN
from stars_ros.evaluation import crowd_data

TRAIN_ONLY = ('torch', 'torch_geometric', 'pandas', 'matplotlib')  # requirements-train.txt's libraries
BLOCKER = f"""
import sys


class TrainExtraAbsent:
    '''Finds none of the train extra's libraries, as on an install without them.'''

    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in {TRAIN_ONLY!r}:
            raise ModuleNotFoundError(f"No module named '{{name}}'", name=name)
        return None


sys.meta_path.insert(0, TrainExtraAbsent())
"""
SERVE = BLOCKER + """
import json
import numpy as np
import stars_ros
from stars_ros import StarsRecommender
from stars_ros.data.scene_source import random_scene
from stars_ros.errors import TrainExtraMissing
from stars_ros.resources import resolve_checkpoint
import stars_ros.ros.ranker, stars_ros.ros.managed_ranker, stars_ros.ros.hri_bridge  # noqa: E401
import stars_ros.ros.feedback_page, stars_ros.ros.replay, stars_ros.recording.__main__  # noqa: E401
import stars_ros.ros.scene_publisher, stars_ros.ros.hri_world, stars_ros.sign_feedback  # noqa: E401

graph_checkpoint, tabular_checkpoint = sys.argv[1:3]
scene = random_scene(np.random.default_rng(0))
ranked = {}
for path in (resolve_checkpoint(''), graph_checkpoint):
    recommender = StarsRecommender.load(path)
    ranked[path] = [entry.name for entry in recommender.rank('someone', scene, uncertainty=True)]
try:
    StarsRecommender.load(tabular_checkpoint)
    refusal = None
except TrainExtraMissing as error:
    refusal = str(error)
print(json.dumps({'ranked': ranked, 'refusal': refusal,
                  'loaded': sorted(m for m in sys.modules if m.split('.')[0] in %r)}))
""" % (TRAIN_ONLY,)


@pytest.fixture(scope='module')
def tabular_checkpoint(tmp_path_factory):
    """A tiny MLP (tabular) checkpoint fitted on generated crowd data."""
    from stars_ros.data.ratings import load_dataset

    shape = crowd_data.CrowdShape(users=8, scenes=24, features=5, raters_per_scene=4, latent=2)
    root = crowd_data.write(tmp_path_factory.mktemp('crowd'), shape, seed=1)
    config = {'encoder': {'name': 'mlp', 'hidden': 8, 'layers': 1}, 'model': {'dim': 4},
              'training': {'pretrain_epochs': 1, 'joint_epochs': 1, 'batch_size': 64, 'threads': 1}}
    path = tmp_path_factory.mktemp('tabular') / 'mlp.pt'
    StarsRecommender(config).fit(load_dataset(root)).save(path)
    return path


def test_a_serving_install_serves_graph_checkpoints_and_names_the_extra_for_a_tabular_one(tiny_checkpoint,
                                                                                      tabular_checkpoint):
    done = subprocess.run([sys.executable, '-c', SERVE, str(tiny_checkpoint), str(tabular_checkpoint)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout.splitlines()[-1])
    assert result['loaded'] == []  # nothing of the train extra was imported, or even found
    assert len(result['ranked']) == 2 and all(result['ranked'].values())
    assert result['refusal'] is not None and INSTALL_TRAIN in result['refusal']
    assert "tabular backbone 'mlp'" in result['refusal'] and 'torch' in result['refusal']


def test_the_blocker_refuses_what_a_serving_install_lacks():
    """The stand-in for a serving install is one: torch cannot be imported under it."""
    done = subprocess.run([sys.executable, '-c', BLOCKER + 'import torch'], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 1 and "No module named 'torch'" in done.stderr
