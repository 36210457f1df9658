"""After scripts/setup_venv.sh the venv is an ament prefix holding stars_ros, as a colcon
install folder would: with AMENT_PREFIX_PATH set to .venv, ament_index_python (what `ros2 run`
and `ros2 launch` ask) finds the package's prefix, its share folder with package.xml and the
launch files, and its executables under lib/stars_ros. The share folder is laid out as
`colcon build --symlink-install` lays it out (scripts/link_share.py): real folders of links to
files, which os.walk, as `ros2 launch` finds launch files, walks into."""
import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
VENV = REPO / '.venv'
EXECUTABLES = ('ranker', 'managed_ranker', 'scene_publisher', 'replay', 'sign_feedback', 'recording', 'hri_bridge',
               'hri_world', 'feedback_page')

FIND = """
import json, os
from ament_index_python.packages import get_package_prefix, get_package_share_directory
print(json.dumps([get_package_prefix('stars_ros'), get_package_share_directory('stars_ros')]))
"""


SHIPPED_CONFIGS = {'ranker.yaml', 'socnav1_gat.yaml', 'quickstart.yaml'}


def launch_files_found(share: Path) -> set:
    """The launch files under ``share`` as ros2launch finds them: os.walk, links to folders not entered."""
    return {name for _, _, files in os.walk(share) for name in files if name.endswith('.launch.py')}


def linked_folders(share: Path) -> list:
    return [str(Path(root) / name) for root, folders, _ in os.walk(share) for name in folders
            if (Path(root) / name).is_symlink()]


def test_the_share_folder_holds_real_folders_of_links_to_the_shipped_files(tmp_path):
    spec = importlib.util.spec_from_file_location('link_share', REPO / 'scripts' / 'link_share.py')
    link_share = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(link_share)
    share = tmp_path / 'share' / 'stars_ros'
    share.mkdir(parents=True)
    (share / 'launch').symlink_to(REPO / 'launch')  # the layout scripts/setup_venv.sh made before
    assert launch_files_found(share) == set()  # what `ros2 launch` found in it: nothing
    link_share.link_share(tmp_path)
    assert not linked_folders(share) and launch_files_found(share) == {'ranker.launch.py', 'hri.launch.py'}
    for path in share.rglob('*'):
        linked_to_its_file = path.resolve() == REPO / path.relative_to(share)
        assert (path.is_dir() and not path.is_symlink()) or linked_to_its_file, path
    assert {path.name for path in (share / 'config').glob('*.yaml')} == SHIPPED_CONFIGS
    assert [path.name for path in (share / 'config' / 'security').iterdir()] == ['ranker.policy.xml']
    assert (share / 'models' / 'socnav1_gat_stars.pt').is_file() and (share / 'package.xml').is_file()
    assert (tmp_path / 'share' / 'ament_index' / 'resource_index' / 'packages' / 'stars_ros').is_file()
    link_share.link_share(tmp_path)  # again over its own layout: the same
    assert launch_files_found(share) == {'ranker.launch.py', 'hri.launch.py'}


@pytest.fixture(scope='module')
def registered():
    if Path(sys.prefix).resolve() != VENV.resolve():
        pytest.skip('this runs in the project .venv, which scripts/setup_venv.sh registers')
    subprocess.run(['bash', 'scripts/setup_venv.sh'], cwd=REPO, check=True, capture_output=True, timeout=1200)
    return VENV


@pytest.mark.slow  # runs setup_venv.sh and starts the ranker for its --help
def test_ament_index_finds_the_package_its_share_and_executables(registered):
    import json
    env = dict(os.environ, AMENT_PREFIX_PATH=str(registered))
    found = subprocess.run([sys.executable, '-c', FIND], env=env, capture_output=True, text=True, check=True)
    prefix, share = (Path(p) for p in json.loads(found.stdout))
    assert prefix.resolve() == registered.resolve()
    assert (share / 'package.xml').is_file()
    assert {'ranker.launch.py', 'hri.launch.py'} <= launch_files_found(share) and not linked_folders(share)
    for name in EXECUTABLES:
        executable = prefix / 'lib' / 'stars_ros' / name
        assert executable.is_file() and os.access(executable, os.X_OK), executable
    assert 'usage' in subprocess.run([str(prefix / 'lib' / 'stars_ros' / 'ranker'), '--help'], env=env,
                                     capture_output=True, text=True, timeout=120).stdout.lower()
