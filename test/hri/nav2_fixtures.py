"""The NavigateToPose tests need nav2_msgs: a ROS install provides it (ros-jazzy-nav2-msgs); in
the project's .venv the test-only stand-in test/interfaces/nav2_msgs (Nav2 Jazzy's
NavigateToPose) is built into it by scripts/build_interfaces.sh, a no-op while unchanged."""
import importlib
import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
STAND_IN = 'test/interfaces/nav2_msgs'


@pytest.fixture(scope='session')
def navigate_to_pose():
    """The NavigateToPose action type: the stand-in built into the project's .venv, else a ROS
    install's; skipped, saying why, where neither can be had."""
    if Path(sys.prefix).resolve() == (REPO / '.venv').resolve():
        result = subprocess.run(['bash', 'scripts/build_interfaces.sh', STAND_IN], cwd=REPO, capture_output=True,
                                text=True, timeout=1200)
        if result.returncode != 0:
            pytest.fail(f'building the nav2_msgs stand-in failed:\n{result.stdout}\n{result.stderr}')
        importlib.invalidate_caches()
    elif importlib.util.find_spec('nav2_msgs') is None:
        pytest.skip('nav2_msgs is not importable (no ROS install with ros-jazzy-nav2-msgs) and this is not the '
                    'project .venv, where the stand-in is built')
    return importlib.import_module('nav2_msgs.action').NavigateToPose
