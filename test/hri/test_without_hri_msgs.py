"""Where hri_msgs and tf2_ros are absent (no ROS install): the ranker and the bridge's core
import as ever, and the bridge module imports but says what it needs."""
import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
CHILD = '''
import importlib.abc, json, sys


class Blocked(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in ('hri_msgs', 'tf2_ros'):
            raise ImportError(f'{name} is made unimportable by this test', name=name)
        return None


sys.meta_path.insert(0, Blocked())
import stars_ros.ros.ranker, stars_ros.hri.bridge  # noqa: E401,F401
from stars_ros.ros import hri_bridge
print(json.dumps({'bridge_error': hri_bridge.HRI_MSGS_ERROR,
                  'leaked': sorted(m for m in sys.modules if m.split('.')[0] in ('hri_msgs', 'tf2_ros'))}))
'''


def test_the_ranker_and_the_core_need_neither_hri_msgs_nor_tf2_ros():
    result = subprocess.run([sys.executable, '-c', CHILD], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert report['leaked'] == []
    assert 'hri_bridge needs hri_msgs (ros-jazzy-hri-msgs' in report['bridge_error']
