"""What the package declares it needs: every library the code imports is in package.xml
(by its rosdep key, where rosdep has one) and pinned in a requirements file, and the
libraries without a rosdep key are the ones package.xml's comment sends to requirements.txt.
Two installs: serving's libraries (requirements.txt, install_requires, package.xml's run
dependencies) are all that the serving processes load; training's are the ``train`` extra."""
import ast
import importlib.metadata
import json
import re
import subprocess
import sys
import types
import xml.etree.ElementTree as ET
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ROS = 'ROS'  # provided by a ROS install (requirements-rclpy.txt on a machine without one)
# import name: (rosdep key or None, pip distribution pinned in requirements*.txt, or ROS)
LIBRARIES = {
    'rclpy': ('rclpy', ROS), 'rcl_interfaces': ('rcl_interfaces', ROS), 'std_msgs': ('std_msgs', ROS),
    'std_srvs': ('std_srvs', ROS), 'diagnostic_msgs': ('diagnostic_msgs', ROS),
    'visualization_msgs': ('visualization_msgs', ROS),
    'lifecycle_msgs': ('lifecycle_msgs', ROS),  # rclpy.lifecycle's (the managed ranker)
    'stars_ros_msgs': ('stars_ros_msgs', ROS),  # this repository's interfaces/stars_ros_msgs, built beside it
    'ament_index_python': ('ament_index_python', ROS), 'launch': ('launch', ROS), 'launch_ros': ('launch_ros', ROS),
    'geometry_msgs': ('geometry_msgs', ROS),  # the ranker's scenes, hri_bridge's goals and transforms
    'hri_msgs': ('hri_msgs', ROS), 'tf2_ros': ('tf2_ros', ROS),  # ROS4HRI, only in hri_bridge and hri_world
    'nav2_msgs': ('nav2_msgs', ROS), 'action_msgs': ('action_msgs', ROS),  # the bridge's NavigateToPose goals
    'numpy': ('python3-numpy', 'numpy'), 'yaml': ('python3-yaml', 'pyyaml'), 'pandas': ('python3-pandas', 'pandas'),
    'pydantic': ('python3-pydantic', 'pydantic'), 'scipy': ('python3-scipy', 'scipy'),
    'matplotlib': ('python3-matplotlib', 'matplotlib'), 'torch': (None, 'torch'),
    'aiohttp': ('python3-aiohttp', 'aiohttp'),  # the feedback page's web server
    'torch_geometric': (None, 'torch-geometric'), 'numba': (None, 'numba'), 'fastjsonschema': (None, 'fastjsonschema'),
    'mcap': (None, 'mcap'), 'mcap_ros2': (None, 'mcap-ros2-support'), 'threadpoolctl': (None, 'threadpoolctl'),
    'ray': (None, 'ray'),  # optional: the Ray executor (requirements-ray.txt)
    'surprise': (None, 'scikit-surprise'), 'myfm': (None, 'myfm'),  # optional: the peers (requirements-peers.txt)
}
OPTIONAL = {'ray', 'surprise', 'myfm'}  # offline only: neither package.xml nor a robot needs them
OPTIONAL_REQUIREMENTS = ('requirements-ray.txt', 'requirements-peers.txt')
# training, evaluation, the peers, plots and tabular serving: setup.py's `train` extra
TRAIN = {'torch', 'torch_geometric', 'pandas', 'matplotlib', 'surprise', 'myfm'}
TRAIN_REQUIREMENTS = ('requirements-train.txt', 'requirements-peers.txt')
TEST_LIBRARIES = {'pytest': ('python3-pytest', 'pytest'), 'jsonschema': ('python3-jsonschema', 'jsonschema'),
                  'referencing': ('python3-jsonschema', 'jsonschema'),  # jsonschema's own dependency
                  'rosbags': (None, 'rosbags'),
                  'playwright': (None, 'playwright'),  # the feedback page's browser test
                  'sros2': ('sros2', ROS),  # a ROS package (ros-jazzy-sros2); its tests skip without it
                  'lxml': ('python3-lxml', ROS),  # sros2's own dependency, with it from a ROS install
                  'builtin_interfaces': ('builtin_interfaces', ROS),
                  'rosgraph_msgs': ('rosgraph_msgs', ROS)}  # /clock, for nodes tested on simulated time
OWN = {'stars_ros', 'offline_training', 'test_support',
       *(path.stem for path in (REPO / 'test').rglob('*.py'))}  # test helpers too


def imported(folders) -> set:
    """Top-level names of the modules imported by the .py files under ``folders``."""
    names = set()
    for folder in folders:
        for path in (REPO / folder).rglob('*.py'):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Import):
                    names.update(alias.name.split('.')[0] for alias in node.names)
                elif isinstance(node, ast.ImportFrom) and node.level == 0:
                    names.add(node.module.split('.')[0])
    return names - set(sys.stdlib_module_names) - OWN


def depends(kind: str) -> set:
    return {element.text for element in ET.parse(REPO / 'package.xml').getroot().iter(kind)}


def pins(*files) -> set:
    """Distribution names pinned in requirements ``files`` (their ``-r`` includes not followed)."""
    names = set()
    for name in files:
        for line in (REPO / name).read_text().splitlines():
            line = line.split('#', 1)[0].strip()
            if line and not line.startswith('-'):
                names.add(re.split(r'[\[=<>]', line)[0].lower())
    return names


def test_every_library_the_package_imports_is_declared():
    """Serving's: run dependencies of package.xml, pinned in requirements.txt; the train
    extra's: test dependencies (the tests train), pinned in requirements-train.txt."""
    used = imported(['stars_ros', 'offline_training', 'launch'])
    assert used <= set(LIBRARIES), f'imported but not in LIBRARIES (declare it): {used - set(LIBRARIES)}'
    exec_depends, test_depends = depends('exec_depend'), depends('test_depend')
    serving_pins, train_pins = pins('requirements.txt', 'requirements-ray.txt'), pins(*TRAIN_REQUIREMENTS)
    for module in used:
        key, distribution = LIBRARIES[module]
        if module in TRAIN:
            assert key is None or (key in test_depends and key not in exec_depends), f'{module}: {key} runs'
            assert distribution in train_pins and distribution not in serving_pins, f'{module}: a serving pin'
            continue
        assert key is None or key in exec_depends, f'{module}: <exec_depend>{key}</exec_depend> missing'
        if distribution is not ROS:
            assert distribution in serving_pins, f'{module}: {distribution} is not pinned in requirements.txt'
    assert 'ros2launch' in exec_depends  # `ros2 launch stars_ros ranker.launch.py`


SERVING_PROCESSES = """
import json, sys
import numpy as np
import stars_ros.ros.ranker, stars_ros.ros.managed_ranker, stars_ros.ros.hri_bridge  # noqa: E401
import stars_ros.ros.feedback_page, stars_ros.hri.feedback_server, stars_ros.ros.replay  # noqa: E401
import stars_ros.recording.__main__, stars_ros.node.core, stars_ros.sign_feedback  # noqa: E401
import stars_ros.ros.scene_publisher, stars_ros.ros.hri_world  # noqa: E401
from stars_ros import StarsRecommender
from stars_ros.data.scene_source import random_scene
from stars_ros.resources import resolve_checkpoint
scene = random_scene(np.random.default_rng(0))
StarsRecommender.load(resolve_checkpoint('')).rank('someone', scene, uncertainty=True)
print(json.dumps(sorted({name.split('.')[0] for name in sys.modules})))
"""


def normalised(distribution: str) -> str:
    """A distribution's name as PEP 503 compares it."""
    return re.sub(r'[-_.]+', '-', distribution).lower()


def test_what_serving_loads_is_pinned_in_requirements_txt():
    """The executables' modules and the packaged model loaded and ranking, in a fresh
    interpreter: every distribution whose modules that loads is requirements.txt's (or one
    of theirs), or ROS's, so ``pip install stars_ros`` serves."""
    done = subprocess.run([sys.executable, '-c', SERVING_PROCESSES], capture_output=True, text=True,
                          timeout=120, cwd=REPO, check=True)
    loaded = set(json.loads(done.stdout.splitlines()[-1])) - set(sys.stdlib_module_names) - OWN
    wanted, unread = set(), {'setuptools', *pins('requirements.txt')}  # install_requires
    while unread:  # and what they require, and so on,
        name = unread.pop()
        wanted.add(name)
        try:
            requires = importlib.metadata.requires(name) or ()
        except importlib.metadata.PackageNotFoundError:
            continue  # required on other Pythons only: it loads nothing here
        # their extras too: a library imports an optional one where it is installed (aiohttp's
        # backports.zstd here, which rosbags brings), and serves without it where it is not
        names = {normalised(re.split(r'[\s\[=<>;~!(]', requirement)[0]) for requirement in requires}
        unread.update(names - wanted)
    providers = importlib.metadata.packages_distributions()
    for module in sorted(loaded):
        distributions = {normalised(name) for name in providers.get(module, ())}
        if LIBRARIES.get(module, (None, None))[1] is ROS or not distributions or any(
                name.startswith('ros-') for name in distributions):
            continue  # ROS's: rclpy's wheels and what they bring, the interface packages built into the venv
        assert distributions & wanted, f'serving loads {module} ({distributions}): not in requirements.txt'
    assert not loaded & TRAIN


def test_every_library_the_tests_import_is_declared():
    used = imported(['test', 'test_support']) - imported(['stars_ros', 'offline_training', 'launch'])
    known = {**LIBRARIES, **TEST_LIBRARIES}
    assert used <= set(known), f'imported by tests but not declared: {used - set(known)}'
    declared, dev_pins = depends('test_depend') | depends('exec_depend'), pins(
        'requirements.txt', *TRAIN_REQUIREMENTS, *OPTIONAL_REQUIREMENTS, 'requirements-dev.txt')
    for module in used:
        key, distribution = known[module]
        assert key is None or key in declared, f'{module}: <test_depend>{key}</test_depend> missing'
        assert distribution is ROS or distribution in dev_pins, f'{module}: {distribution} is not pinned'
    assert not depends('exec_depend') & {key for key, _ in TEST_LIBRARIES.values()}, 'a test library at run time'


def test_package_xml_names_the_libraries_rosdep_does_not_cover():
    """Its comment says which libraries requirements.txt installs because rosdep has no key."""
    text = (REPO / 'package.xml').read_text()
    for module, (key, distribution) in LIBRARIES.items():
        if key is None and module not in OPTIONAL:
            assert re.search(rf'\b{re.escape(distribution)}\b', text), f'{distribution} not named in package.xml'


def test_install_requires_are_the_serving_pins_and_train_the_extra(monkeypatch):
    """setup.py's install_requires: requirements.txt as it stands (setuptools besides); its
    ``train`` extra: requirements-train.txt with the file it includes."""
    captured = {}
    monkeypatch.setitem(sys.modules, 'setuptools', types.SimpleNamespace(
        setup=lambda **kwargs: captured.update(kwargs), find_packages=lambda **kwargs: []))
    exec(compile((REPO / 'setup.py').read_text(), 'setup.py', 'exec'), {'__file__': str(REPO / 'setup.py')})

    def lines(name):
        return [line.split('#', 1)[0].strip() for line in (REPO / name).read_text().splitlines()]
    assert captured['install_requires'] == ['setuptools', *filter(None, lines('requirements.txt'))]
    train = [line for line in lines('requirements-train.txt') if line and not line.startswith('-r')]
    assert captured['extras_require'] == {'train': [*filter(None, lines('requirements-peers.txt')), *train]}
    assert all('==' in pin for pin in captured['install_requires'][1:] + captured['extras_require']['train'])
    assert 'torch' not in pins('requirements.txt') and 'torch' in pins('requirements-train.txt')


def test_requirements_dev_installs_serving_and_train():
    """The README's commands (scripts/setup_venv.sh, which installs requirements-dev.txt)
    install both."""
    text = (REPO / 'requirements-dev.txt').read_text()
    assert '-r requirements.txt' in text and '-r requirements-train.txt' in text
