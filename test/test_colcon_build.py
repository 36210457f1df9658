"""`colcon build` of the package and of its interface package (interfaces/stars_ros_msgs,
found with `--base-paths src src/stars_ros/interfaces`: colcon does not look inside a package)
in a scratch workspace gives the install tree `ros2 run` and `ros2 launch` expect: executables
in lib/stars_ros, the ament index marker, package.xml, config, schemas, launch file and the
packaged model in share/stars_ros, and both packages import from the install space once
install/setup.bash is sourced (docs/interfaces.md).

The workspace is kept under the venv, keyed by a hash of interfaces/: a later run copies the
sources in again (modification times kept) and builds stars_ros afresh, while CMake finds
stars_ros_msgs already built and unchanged. Marked slow all the same (the first build takes
minutes)."""
import fcntl
import hashlib
import importlib.metadata
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
SKIP = shutil.ignore_patterns('.git', '.venv', 'build', 'install', 'log', '__pycache__', '*.egg-info', 'results',
                              'runs', 'stars_records', '*.mcap', '.pytest_cache')


pytestmark = pytest.mark.slow
CACHE = Path(sys.prefix) / 'stars_ros_test_cache'  # the venv's: a fresh venv builds afresh


def interfaces_key() -> str:
    """A hash of every file under interfaces/: the cached stars_ros_msgs build is reused only
    for the same interface sources."""
    digest = hashlib.sha256()
    for path in sorted((REPO / 'interfaces').rglob('*')):
        if path.is_file() and '__pycache__' not in path.parts:
            digest.update(str(path.relative_to(REPO)).encode() + b'\0' + path.read_bytes())
    return digest.hexdigest()[:16]


@pytest.fixture(scope='module')
def workspace():
    """The cached workspace for this checkout's interfaces, held (a file lock) while the
    module runs, with this checkout's sources and no stars_ros build or install of before:
    what the tests read of stars_ros is built by this run."""
    CACHE.mkdir(exist_ok=True)
    with open(CACHE / 'colcon_ws.lock', 'w') as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        root = CACHE / f'colcon_ws-{interfaces_key()}'
        for stale in CACHE.glob('colcon_ws-*'):
            if stale != root:
                shutil.rmtree(stale)  # built for other interface sources
        for earlier in (root / 'src', root / 'build' / 'stars_ros', root / 'install' / 'stars_ros', root / 'log'):
            shutil.rmtree(earlier, ignore_errors=True)
        shutil.copytree(REPO, root / 'src' / 'stars_ros', ignore=SKIP)  # copy2: modification times kept
        yield root


BASE_PATHS = ('--base-paths', 'src', 'src/stars_ros/interfaces')


@pytest.fixture(scope='module')
def built(workspace):
    """``colcon build`` of both packages run once in the workspace; every test that reads the
    install tree asks for it, so none depends on running after another."""
    return colcon(workspace, 'build', *BASE_PATHS, '--event-handlers', 'console_direct-', '--cmake-args',
                  f'-DPython3_EXECUTABLE={sys.executable}', '-DBUILD_TESTING=OFF')


def colcon(workspace, *args):
    return subprocess.run([str(BIN / 'colcon'), *args], cwd=workspace, env=_env(), capture_output=True, text=True,
                          timeout=900)


def _env():
    """The venv's ROS (the wheels) as the underlay, as sourcing /opt/ros/jazzy/setup.bash
    makes a ROS install the underlay: CMake finds ament_cmake and rosidl there."""
    return dict(os.environ, PATH=f'{BIN}{os.pathsep}{os.environ["PATH"]}', CMAKE_PREFIX_PATH=sys.prefix,
                AMENT_PREFIX_PATH=sys.prefix)


def test_colcon_sees_an_ament_python_package(workspace):
    listed = colcon(workspace, 'list')
    assert listed.returncode == 0, listed.stderr
    name, path, build_type = listed.stdout.split()
    assert (name, build_type) == ('stars_ros', '(ros.ament_python)')  # the nested package is not seen
    listed = colcon(workspace, 'list', *BASE_PATHS)
    assert listed.returncode == 0, listed.stderr
    assert [line.split()[::2] for line in listed.stdout.splitlines()] == [
        ['stars_ros', '(ros.ament_python)'], ['stars_ros_msgs', '(ros.ament_cmake)']]


def test_colcon_build_installs_what_ros2_run_needs(workspace, built):
    assert built.returncode == 0, built.stdout + built.stderr
    prefix = workspace / 'install' / 'stars_ros'
    for executable in ('ranker', 'managed_ranker', 'scene_publisher', 'replay', 'sign_feedback', 'recording'):
        path = prefix / 'lib' / 'stars_ros' / executable
        assert path.is_file() and os.access(path, os.X_OK), path
    share = prefix / 'share'
    assert (share / 'ament_index' / 'resource_index' / 'packages' / 'stars_ros').is_file()
    for relative in ('package.xml', 'config/ranker.yaml', 'config/socnav1_gat.yaml', 'launch/ranker.launch.py',
                     'msg_schemas/scene_graph.schema.json', 'msg_schemas/scene_request.schema.json',
                     'msg_schemas/ranking.schema.json', 'msg_schemas/feedback.schema.json',
                     'models/socnav1_gat_stars.pt', 'models/README.md', 'config/security/ranker.policy.xml'):
        assert (share / 'stars_ros' / relative).is_file(), relative
    python_dirs = list((prefix / 'lib').glob('python3*/site-packages/stars_ros'))
    assert python_dirs and (python_dirs[0] / 'ros' / 'ranker.py').is_file()
    [installed] = importlib.metadata.distributions(name='stars_ros', path=[str(python_dirs[0].parent)])
    pins = [line.split('#', 1)[0].strip() for line in (REPO / 'requirements.txt').read_text().splitlines()]
    serving = [requirement for requirement in installed.requires if 'extra ==' not in requirement]
    assert serving == ['setuptools', *filter(None, pins)]  # install_requires, as pip would see them
    assert any(requirement.startswith('torch==') and 'extra == "train"' in requirement
               for requirement in installed.requires)  # torch comes with the train extra only
    assert {path.name for path in (share / 'stars_ros' / 'config').glob('*.yaml')} == {
        'ranker.yaml', 'socnav1_gat.yaml', 'quickstart.yaml'}  # the shipped configs, not the evaluation's


def test_source_install_setup_bash_finds_the_built_package(workspace, built):
    """README: `source install/setup.bash` after `colcon build`; colcon writes setup.bash only
    with colcon-bash installed (requirements-dev.txt), else sourcing fails: no such file."""
    assert built.returncode == 0, built.stdout + built.stderr
    prefix = workspace / 'install' / 'stars_ros'
    code = 'import stars_ros.resources as r; print(r.__file__); print(r.share_path("launch/ranker.launch.py"))'
    env = _env()
    env.pop('STARS_ROS_SHARE', None)
    sourced = subprocess.run(['bash', '-c', f'source install/setup.bash && echo "$AMENT_PREFIX_PATH" && '
                              f"python -c '{code}'"], cwd=workspace, env=env, capture_output=True, text=True,
                             timeout=120)
    assert sourced.returncode == 0, sourced.stderr
    ament_prefix_path, module, launch_file = sourced.stdout.split()
    assert str(prefix) in ament_prefix_path.split(os.pathsep)
    assert module.startswith(str(prefix)) and launch_file.startswith(str(prefix / 'share' / 'stars_ros'))


def test_both_packages_import_from_the_install_space(workspace, built):
    """The typed messages and the node's adapter of them come from install/, not from the
    venv this test runs in (which has stars_ros_msgs built into it too)."""
    assert built.returncode == 0, built.stdout + built.stderr
    code = ('import stars_ros_msgs.srv as s, stars_ros.ros.typed_interface as t; '
            'from rclpy.serialization import serialize_message; '
            'serialize_message(s.RankActions.Request()); print(s.__file__); print(t.__file__)')
    sourced = subprocess.run(['bash', '-c', f"source install/setup.bash && python -c '{code}'"], cwd=workspace,
                             env=_env(), capture_output=True, text=True, timeout=120)
    assert sourced.returncode == 0, sourced.stderr
    messages_module, adapter = sourced.stdout.split()
    assert messages_module.startswith(str(workspace / 'install' / 'stars_ros_msgs')), messages_module
    assert adapter.startswith(str(workspace / 'install' / 'stars_ros')), adapter


def test_installed_ranker_finds_its_packaged_files(workspace, built):
    """The built package resolves the default checkpoint and schemas from its share/
    folder (the way it does under `ros2 run`), not from this checkout."""
    assert built.returncode == 0, built.stdout + built.stderr
    prefix = workspace / 'install' / 'stars_ros'
    site = next((prefix / 'lib').glob('python3*/site-packages'))
    code = ('from stars_ros.resources import resolve_checkpoint, share_path; '
            'print(resolve_checkpoint("")); print(share_path("msg_schemas/scene_graph.schema.json"))')
    env = dict(os.environ, PYTHONPATH=str(site), AMENT_PREFIX_PATH=str(prefix))
    env.pop('STARS_ROS_SHARE', None)
    result = subprocess.run([sys.executable, '-c', code], cwd=workspace, env=env, capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr
    checkpoint, schema = result.stdout.split()
    assert checkpoint.startswith(str(prefix / 'share' / 'stars_ros')), checkpoint
    assert schema.startswith(str(prefix / 'share' / 'stars_ros')), schema
