"""The bridge's tests need hri_msgs: a ROS install provides it (ros-jazzy-hri-msgs); in the
project's .venv the test-only stand-in test/interfaces/hri_msgs (REP 155's IdsList,
EngagementLevel, Group, Gaze) is built into it by scripts/build_interfaces.sh, a no-op while
unchanged. It is never installed with stars_ros."""
import importlib
import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
STAND_IN = 'test/interfaces/hri_msgs'


@pytest.fixture(scope='session')
def hri_msgs():
    """The hri_msgs.msg module: the stand-in built into the project's .venv, else a ROS
    install's; skipped, saying why, where neither can be had."""
    if Path(sys.prefix).resolve() == (REPO / '.venv').resolve():
        result = subprocess.run(['bash', 'scripts/build_interfaces.sh', STAND_IN], cwd=REPO, capture_output=True,
                                text=True, timeout=1200)
        if result.returncode != 0:
            pytest.fail(f'building the hri_msgs stand-in failed:\n{result.stdout}\n{result.stderr}')
        importlib.invalidate_caches()
    elif importlib.util.find_spec('hri_msgs') is None:
        pytest.skip('hri_msgs is not importable (no ROS install) and this is not the project .venv, where the '
                    'stand-in is built')
    return importlib.import_module('hri_msgs.msg')
