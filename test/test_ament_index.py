"""After scripts/setup_venv.sh the venv is an ament prefix holding stars_ros, as a colcon
install folder would: with AMENT_PREFIX_PATH set to .venv, ament_index_python (what `ros2 run`
and `ros2 launch` ask) finds the package's prefix, its share folder with package.xml and the
launch files, and its executables under lib/stars_ros."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # runs setup_venv.sh and starts the ranker for its --help
REPO = Path(__file__).resolve().parents[1]
VENV = REPO / '.venv'
EXECUTABLES = ('ranker', 'managed_ranker', 'scene_publisher', 'replay', 'sign_feedback', 'recording', 'hri_bridge',
               'hri_world', 'feedback_page')

FIND = """
import json, os
from ament_index_python.packages import get_package_prefix, get_package_share_directory
print(json.dumps([get_package_prefix('stars_ros'), get_package_share_directory('stars_ros')]))
"""


@pytest.fixture(scope='module')
def registered():
    if Path(sys.prefix).resolve() != VENV.resolve():
        pytest.skip('this runs in the project .venv, which scripts/setup_venv.sh registers')
    subprocess.run(['bash', 'scripts/setup_venv.sh'], cwd=REPO, check=True, capture_output=True, timeout=1200)
    return VENV


def test_ament_index_finds_the_package_its_share_and_executables(registered):
    import json
    env = dict(os.environ, AMENT_PREFIX_PATH=str(registered))
    found = subprocess.run([sys.executable, '-c', FIND], env=env, capture_output=True, text=True, check=True)
    prefix, share = (Path(p) for p in json.loads(found.stdout))
    assert prefix.resolve() == registered.resolve()
    assert (share / 'package.xml').is_file()
    assert {'ranker.launch.py', 'hri.launch.py'} <= {p.name for p in (share / 'launch').iterdir()}
    for name in EXECUTABLES:
        executable = prefix / 'lib' / 'stars_ros' / name
        assert executable.is_file() and os.access(executable, os.X_OK), executable
    assert 'usage' in subprocess.run([str(prefix / 'lib' / 'stars_ros' / 'ranker'), '--help'], env=env,
                                     capture_output=True, text=True, timeout=120).stdout.lower()
