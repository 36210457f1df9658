"""launch/hri.launch.py run as ros2 launch runs it, on stand-ins for launch and launch_ros
(they do not install from PyPI): the scripted world, the bridge and the ranker, poses through
hri/transforms where tf2_ros is absent, and world:=false for a robot's own ROS4HRI stack."""
import importlib.util
import sys
import types
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


class Recorded:
    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


class Configuration:
    def __init__(self, name):
        self.name = name

    def perform(self, context):
        return context.launch_configurations[self.name]


class Logger:
    """Stands in for launch.logging.get_logger: keeps the warnings logged."""

    warnings = []

    def __init__(self, name):
        self.name = name

    def warning(self, message):
        self.warnings.append(message)


def launched(monkeypatch, **given) -> dict:
    """The nodes of ``ros2 launch stars_ros hri.launch.py name:=value ...`` (``given``), by
    executable: every given argument a configuration and in argv, as launch makes them."""
    Logger.warnings = []
    stand_ins = {'launch': {'LaunchDescription': Recorded},
                 'launch.actions': {'DeclareLaunchArgument': Recorded, 'OpaqueFunction': Recorded},
                 'launch.logging': {'get_logger': Logger},
                 'launch.conditions': {'IfCondition': Recorded},
                 'launch.substitutions': {'LaunchConfiguration': Configuration},
                 'launch_ros': {}, 'launch_ros.actions': {'Node': Recorded}}
    for name, attributes in stand_ins.items():
        monkeypatch.setitem(sys.modules, name, types.SimpleNamespace(**attributes))
    spec = importlib.util.spec_from_file_location('hri_launch', REPO / 'launch' / 'hri.launch.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    entities = module.generate_launch_description().args[0]
    declared = {e.args[0]: e.kwargs for e in entities if 'default_value' in e.kwargs}
    configurations = {**{name: kwargs['default_value'] for name, kwargs in declared.items()}, **given}
    opaque = next(e for e in entities if 'function' in e.kwargs)
    nodes = opaque.kwargs['function'](types.SimpleNamespace(
        launch_configurations=configurations, argv=[f'{name}:={value}' for name, value in given.items()]))
    return {node.kwargs['executable']: node.kwargs for node in nodes}


def test_the_loop_runs_world_bridge_and_ranker_with_the_pose_source_this_machine_has(monkeypatch):
    nodes = launched(monkeypatch)
    assert set(nodes) == {'hri_world', 'hri_bridge', 'ranker'}
    expected = 'tf' if importlib.util.find_spec('tf2_ros') else 'topic'
    assert nodes['hri_bridge']['parameters'][0]['pose_source'] == expected
    assert nodes['hri_world']['parameters'][0]['pose_source'] == expected
    assert nodes['hri_world']['condition'].args[0].name == 'world'
    assert nodes['ranker']['parameters'] == [{}]  # its own defaults
    nodes = launched(monkeypatch, pose_source='tf', record_folder='/data/bags')
    assert nodes['hri_bridge']['parameters'][0]['pose_source'] == 'tf'
    assert nodes['ranker']['parameters'][0]['record_folder'].name == 'record_folder'


def test_store_policy_goes_to_the_bridge_and_the_ranker_alike(monkeypatch, tmp_path):
    consent_file = tmp_path / 'consent.txt'
    consent_file.write_text('alice\n')
    nodes = launched(monkeypatch, store_policy='consented', consent_file=str(consent_file))
    privacy = {'store_policy': 'consented', 'consent_file': str(consent_file)}
    assert privacy.items() <= nodes['hri_bridge']['parameters'][0].items()
    assert nodes['ranker']['parameters'] == [privacy]
    nodes = launched(monkeypatch, store_policy='consented')  # the latched stars/consent only
    assert nodes['ranker']['parameters'] == [{'store_policy': 'consented'}]
    assert 'store_policy' not in launched(monkeypatch)['hri_bridge']['parameters'][0]  # 'all': their defaults


def test_a_misspelt_argument_is_named_and_the_loop_starts_without_it(monkeypatch):
    nodes = launched(monkeypatch, pose_sorce='topic')
    assert Logger.warnings == ["launch argument 'pose_sorce' is not one of hri.launch.py's: ignored (did you "
                               "mean 'pose_source'?); `ros2 launch stars_ros hri.launch.py --show-args` "
                               'lists them']
    assert set(nodes) == {'hri_world', 'hri_bridge', 'ranker'}
    launched(monkeypatch, pose_source='topic', world='false', store_policy='all')
    assert Logger.warnings == []
