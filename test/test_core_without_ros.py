"""The core works without ROS: every module of stars_ros outside stars_ros/ros/, and the front
door (``from stars_ros import StarsRecommender``), import in a process where rclpy and the ROS
message packages cannot be imported."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ROS_PACKAGES = ('rclpy', 'std_msgs', 'std_srvs', 'diagnostic_msgs', 'rcl_interfaces', 'geometry_msgs', 'lifecycle_msgs',
                'stars_ros_msgs', 'hri_msgs', 'tf2_ros')

CHILD = '''
import importlib, importlib.abc, json, pkgutil, sys

BLOCKED = set(sys.argv[1].split(','))


class NoRos(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in BLOCKED:
            raise ImportError(f'{name} is made unimportable by this test', name=name)
        return None


sys.meta_path.insert(0, NoRos())
import stars_ros
from stars_ros import StarsRecommender, load_dataset  # noqa: F401 - the front door, without ROS

found = [m.name for m in pkgutil.walk_packages(stars_ros.__path__, 'stars_ros.') if not m.name.endswith('.__main__')]
core = [name for name in found if name != 'stars_ros.ros' and not name.startswith('stars_ros.ros.')]
failed = {}
for name in core:
    try:
        importlib.import_module(name)
    except Exception as error:  # noqa: BLE001 - every failure is reported
        failed[name] = f'{type(error).__name__}: {error}'
try:
    importlib.import_module('stars_ros.ros.ranker')
    adapter = 'imported'
except ImportError as error:
    adapter = str(error)
leaked = sorted(m for m in sys.modules if m.split('.')[0] in BLOCKED)
print(json.dumps({'found': found, 'core': core, 'failed': failed, 'adapter': adapter, 'leaked': leaked}))
'''


@pytest.mark.slow
def test_every_core_module_imports_without_ros():
    result = subprocess.run([sys.executable, '-c', CHILD, ','.join(ROS_PACKAGES)], cwd=REPO, capture_output=True,
                            text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert report['failed'] == {}
    assert report['leaked'] == []
    assert {'stars_ros.personalisation.online', 'stars_ros.state.store', 'stars_ros.node.core',
            'stars_ros.personalisation.foldin', 'stars_ros.model.predictor', 'stars_ros.recording.bag',
            'stars_ros.model.encoders.graph'} <= set(report['core'])
    assert {'stars_ros.ros.ranker', 'stars_ros.ros.scene_publisher', 'stars_ros.ros.replay'} <= set(report['found'])
    assert 'made unimportable by this test' in report['adapter']  # the blocker works: the node needs rclpy
