"""What a new user meets first: every executable's --help, where recordings go by default,
the node defaults file and the launch file agreeing with the node, the demo's own state."""
import importlib
import importlib.util
import itertools
import os
import re
import subprocess
import sys
import types
from pathlib import Path

import pytest
import yaml

from stars_ros import recording
from stars_ros.node.parameters import PARAMETERS
from stars_ros.examples import demo
from stars_ros.ros import feedback_page, hri_bridge, hri_world, replay, scene_publisher, usage
from stars_ros.errors import LaunchArgumentError
from stars_ros.state import PersonUpdate
from state_fill import fill_store

REPO = Path(__file__).resolve().parents[1]
ENTRY_POINTS = dict(re.findall(r"'(\w+) = ([\w.]+):main'", (REPO / 'setup.py').read_text()))
TABLES = {'stars_ros.ros.ranker': PARAMETERS, 'stars_ros.ros.managed_ranker': PARAMETERS,
          'stars_ros.ros.scene_publisher': scene_publisher.PARAMETERS,
          'stars_ros.ros.replay': replay.PARAMETERS, 'stars_ros.ros.hri_bridge': hri_bridge.PARAMETERS,
          'stars_ros.ros.hri_world': hri_world.PARAMETERS, 'stars_ros.ros.feedback_page': feedback_page.PARAMETERS}


TOOLS = {'sign_feedback': 'stars_ros.sign_feedback', 'recording': 'stars_ros.recording.__main__'}  # not nodes


def test_every_node_console_script_has_a_parameter_table():
    assert set(ENTRY_POINTS) >= {'ranker', 'scene_publisher', 'replay', *TOOLS}
    assert {module for name, module in ENTRY_POINTS.items() if name not in TOOLS} == set(TABLES)
    assert {name: ENTRY_POINTS[name] for name in TOOLS} == TOOLS


def _child_env(ros_home: Path) -> dict:
    return dict(os.environ, ROS_HOME=str(ros_home), ROS_DOMAIN_ID='231', ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
                PYTHONPATH=str(REPO) + os.pathsep + os.environ.get('PYTHONPATH', ''))


def _run_executable(module: str, argv: list, tmp_path: Path) -> subprocess.CompletedProcess:
    """``main()`` run as its console script runs it, in a process of its own, from an empty
    folder, ROS_HOME in tmp_path (a folder that does not exist) and ROS_LOG_DIR unset."""
    cwd = tmp_path / 'cwd'
    cwd.mkdir(exist_ok=True)
    env = _child_env(tmp_path / 'ros_home')
    env.pop('ROS_LOG_DIR', None)
    return subprocess.run([sys.executable, '-c', f'import sys; from {module} import main; sys.exit(main())', *argv],
                          cwd=cwd, env=env, capture_output=True, text=True, timeout=120)


def _call_main(module: str, argv: list, tmp_path: Path, monkeypatch, capfd) -> tuple:
    """(exit status, stdout, stderr) of ``module``'s ``main`` called here as its console script
    calls it (``argv`` as sys.argv; a tool's argparse main gets it without the program name),
    from an empty folder, ROS_HOME in tmp_path and on an unused ROS domain; output read from
    the file descriptors, rcl's own lines included."""
    cwd = tmp_path / 'cwd'
    cwd.mkdir(exist_ok=True)
    monkeypatch.chdir(cwd)
    for name, value in _child_env(tmp_path / 'ros_home').items():
        monkeypatch.setenv(name, value)
    monkeypatch.delenv('ROS_LOG_DIR', raising=False)
    monkeypatch.setattr(sys, 'argv', argv)
    main = importlib.import_module(module).main
    capfd.readouterr()
    try:
        status = main(argv[1:] if module in TOOLS.values() or module == 'stars_ros.examples.demo' else argv)
    except SystemExit as exit_:
        status = exit_.code
    out, err = capfd.readouterr()
    return status or 0, out, err


def _check_help(executable: str, module: str, status: int, out: str, err: str, ros_home: Path, cwd: Path,
                child: bool = False):
    """``child``: run in a process of its own, whose record_folder default follows the
    ROS_HOME it was given (in-process, the table's default was read at import)."""
    assert status == 0, err
    assert not ros_home.exists() and not list(cwd.iterdir())
    assert '[INFO]' not in err and '[INFO]' not in out
    if executable in TOOLS:
        assert out.startswith('usage: ')
        return
    if executable == 'demo':
        for option in ('--checkpoint', '--scenes', '--placements', '--record-folder', 'a new temporary folder'):
            assert option in ' '.join(out.split())
        return
    assert f'usage: ros2 run stars_ros {executable}' in out and '-p NAME:=VALUE' in out
    for name, (default, description, *_) in TABLES[module].items():
        if name == 'record_folder' and child:
            default = str(ros_home / 'stars_ros' / 'records' / '{node}')  # the ROS_HOME it was given
        assert f'  {name} (default {usage.shown_value(default)})\n      {description}\n' in out


def test_the_ranker_answers_help_as_a_process_that_starts_nothing(tmp_path):
    """The console script's whole path, in a process of its own: rclpy.init would create
    ROS_HOME/log for rcl's log files, and a node would record under ROS_HOME; neither may
    appear. The other executables are checked in-process (next test)."""
    shown = _run_executable(ENTRY_POINTS['ranker'], ['--help'], tmp_path)
    _check_help('ranker', ENTRY_POINTS['ranker'], shown.returncode, shown.stdout, shown.stderr, tmp_path / 'ros_home',
                tmp_path / 'cwd', child=True)


@pytest.mark.parametrize('executable', [*ENTRY_POINTS, 'demo'])
def test_help_exits_0_prints_the_parameters_and_starts_nothing(executable, tmp_path, monkeypatch, capfd):
    """``main`` with --help, called in-process with rclpy.init refused: it answers before
    ROS starts, writes nothing to an empty folder and creates no ROS_HOME."""
    import rclpy

    def refused(*args, **kwargs):
        raise AssertionError('rclpy.init was called to print the help')
    monkeypatch.setattr(rclpy, 'init', refused)
    module = ENTRY_POINTS.get(executable, 'stars_ros.examples.demo')
    status, out, err = _call_main(module, [executable, '--help'], tmp_path, monkeypatch, capfd)
    _check_help(executable, module, status, out, err, tmp_path / 'ros_home', tmp_path / 'cwd')


BAD_ROS_ARGS = {  # what a user can get wrong after --ros-args, and the reason the one line gives
    'no such params file': (['--params-file', 'nowhere/ranker.yaml'], "Couldn't parse params file"),
    'params file of broken YAML': (['--params-file', '{broken}'], "Couldn't parse params file"),
    'unknown ROS argument': (['--no-such-option'], "unknown ROS arguments: '--no-such-option'"),
    'override without a value': (['-p', 'rate'], "Couldn't parse parameter override rule: '-p rate'"),
    'a value of the wrong type': (['-p', '{numeric}:=[1, 2]'], "expecting type"),
}
# rcl refuses these in rclpy.init, before any node exists: checked in-process. A value of the
# wrong type is refused while the node declares its parameters, then the node is destroyed and
# ROS shut down (signal handlers and a shutdown watchdog included): checked in a process.
REFUSED_BY_RCL = [case for case in BAD_ROS_ARGS if case != 'a value of the wrong type']


def _bad_argv(executable: str, case: str, tmp_path: Path) -> tuple:
    module = ENTRY_POINTS[executable]
    broken = tmp_path / 'broken.yaml'
    broken.write_text('/**:\n  ros__parameters:\n    top_k: [1, "two"\n')
    numeric = next(name for name, (default, *_) in TABLES[module].items()
                   if isinstance(default, (int, float)) and not isinstance(default, bool))
    argv, reason = BAD_ROS_ARGS[case]
    return ['--ros-args', '-p', "record_folder:=''", *[arg.format(broken=broken, numeric=numeric) for arg in argv]], \
        reason


def _check_refusal(executable: str, reason: str, status: int, out: str, err: str):
    """The reason on one line, no traceback, no node, status 2."""
    assert status == 2, err
    assert out == '' and len(err.splitlines()) == 1, err
    assert err.startswith(f'{executable}: error: ') and reason in err, err
    assert ', at /' not in err  # rcl's source locations are left out


@pytest.mark.parametrize('case', REFUSED_BY_RCL)
def test_ranker_ros_args_rcl_refuses_end_in_one_line_on_stderr_and_status_2(case, tmp_path, monkeypatch, capfd):
    """What `ros2 run stars_ros ranker --ros-args ...` prints when rcl cannot parse the
    arguments: ``main`` called in-process (rclpy.init fails, nothing is left to shut down)."""
    argv, reason = _bad_argv('ranker', case, tmp_path)
    _check_refusal('ranker', reason, *_call_main(ENTRY_POINTS['ranker'], ['ranker', *argv], tmp_path, monkeypatch,
                                                  capfd))


@pytest.mark.parametrize('case', REFUSED_BY_RCL)
@pytest.mark.parametrize('executable', ['scene_publisher', 'replay'])
def test_other_executables_ros_args_rcl_refuses_end_in_one_line_and_status_2(executable, case, tmp_path, monkeypatch,
                                                                            capfd):
    argv, reason = _bad_argv(executable, case, tmp_path)
    _check_refusal(executable, reason, *_call_main(ENTRY_POINTS[executable], [executable, *argv], tmp_path,
                                                   monkeypatch, capfd))


@pytest.mark.parametrize('executable', ['ranker', 'scene_publisher', 'replay'])
def test_a_value_of_the_wrong_type_ends_the_process_in_one_line_and_status_2(executable, tmp_path):
    """The node refuses the value while declaring its parameters: as a process, run as its
    console script runs it, since the node's shutdown is part of what is checked."""
    argv, reason = _bad_argv(executable, 'a value of the wrong type', tmp_path)
    done = _run_executable(ENTRY_POINTS[executable], argv, tmp_path)
    _check_refusal(executable, reason, done.returncode, done.stdout, done.stderr)


def test_scene_publisher_names_the_source_file_it_did_not_find(tmp_path):
    done = _run_executable('stars_ros.ros.scene_publisher', ['--ros-args', '-p', 'source:=raw/a.jsonl'], tmp_path)
    assert done.returncode == 1 and len(done.stderr.splitlines()) == 1, done.stderr
    assert f"source {tmp_path / 'cwd' / 'raw' / 'a.jsonl'}: no such file" in done.stderr


def test_help_is_asked_for_only_before_ros_args():
    assert usage.asked_for_help(['ranker', '--help']) and usage.asked_for_help(['ranker', '-h'])
    assert usage.asked_for_help(['ranker', '-h', '--ros-args', '-p', 'top_k:=3'])
    assert not usage.asked_for_help(['ranker', '--ros-args', '-p', 'user_id:=--help'])
    assert not usage.asked_for_help(['ranker'])


def test_default_record_folder_is_under_ros_home(monkeypatch, tmp_path):
    monkeypatch.setenv('ROS_HOME', str(tmp_path / 'ros'))
    assert recording.default_folder() == tmp_path / 'ros' / 'stars_ros' / 'records'
    monkeypatch.setenv('HOME', str(tmp_path / 'home'))
    for unset in ('', None):
        if unset is None:
            monkeypatch.delenv('ROS_HOME')
        else:
            monkeypatch.setenv('ROS_HOME', unset)
        assert recording.default_folder() == tmp_path / 'home' / '.ros' / 'stars_ros' / 'records'
    monkeypatch.setenv('ROS_HOME', '~/elsewhere')
    assert recording.default_folder() == tmp_path / 'home' / 'elsewhere' / 'stars_ros' / 'records'


def test_the_ranker_records_under_ros_home_in_a_folder_of_its_own_by_default():
    assert PARAMETERS['record_folder'][0] == str(recording.default_folder() / '{node}')
    assert Path(PARAMETERS['record_folder'][0]).is_absolute()
    default = PARAMETERS['record_folder'][0]
    assert recording.node_folder(default, '/robot1/ranker') == recording.default_folder() / 'robot1' / 'ranker'
    assert recording.node_folder(default, '/ranker') == recording.default_folder() / 'ranker'
    assert recording.node_folder('/data/stars', '/robot1/ranker') == Path('/data/stars')


def test_ranker_yaml_holds_the_node_defaults():
    """config/ranker.yaml repeats the node's defaults for users to edit; it must not differ,
    and it leaves record_folder to the node (its default depends on ROS_HOME)."""
    values = yaml.safe_load((REPO / 'config' / 'ranker.yaml').read_text())['/**']['ros__parameters']
    assert set(values) == set(PARAMETERS) - {'record_folder'}
    for name, value in values.items():
        default = PARAMETERS[name][0]
        assert (type(value), value) == (type(default), default), name


def documented_parameter_table() -> dict:
    """docs/parameters.md's table of the ranker's parameters: name -> (default cell, set-at cell)."""
    lines = (REPO / 'docs' / 'parameters.md').read_text().splitlines()
    start = lines.index('| parameter | default | set at | meaning |') + 2
    rows = {}
    for line in itertools.takewhile(lambda line: line.startswith('|'), lines[start:]):
        name, default, set_at = (cell.strip() for cell in line.strip('|').split('|')[:3])
        rows[name.strip('`')] = (default.strip('`'), set_at)
    return rows


def test_the_documented_parameter_table_is_the_nodes():
    """One row per parameter, in PARAMETERS order, with its default (as -p or a params file
    writes it) and whether it can change while the node runs; config/ranker.yaml holds the
    same defaults (test above)."""
    table = documented_parameter_table()
    assert list(table) == list(PARAMETERS)
    for name, (default, set_at) in table.items():
        value, _, read_only, _ = PARAMETERS[name]
        if name == 'record_folder':
            assert default == '$ROS_HOME/stars_ros/records/{node}'  # the value depends on the environment
        else:
            assert (type(yaml.safe_load(default)), yaml.safe_load(default)) == (type(value), value), name
        assert set_at == ('start' if read_only else 'any time'), name


class _Recorded:
    """Stands in for a launch action or description: keeps what the file passed."""

    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


class _LaunchConfiguration:
    def __init__(self, name):
        self.name = name

    def perform(self, context):
        return context.launch_configurations[self.name]


class _Logger:
    """Stands in for launch.logging.get_logger: keeps what is logged, by level."""

    logged = []

    def __init__(self, name):
        self.name = name

    def warning(self, message):
        self.logged.append(('warning', self.name, message))


def _run_launch_file(monkeypatch, **given) -> tuple:
    """launch/ranker.launch.py run as ``ros2 launch stars_ros ranker.launch.py name:=value ...``
    runs it with ``given`` arguments, on stand-ins for launch and launch_ros (they do not
    install from PyPI): every given argument a launch configuration and in the context's argv,
    as launch makes them. The declared arguments and the ranker Node's keyword arguments (its
    ``kind``: Node or LifecycleNode); what the file logged is in ``_Logger.logged``."""
    _Logger.logged = []
    stand_ins = {'launch': {'LaunchDescription': _Recorded},
                 'launch.actions': {'DeclareLaunchArgument': _Recorded, 'OpaqueFunction': _Recorded},
                 'launch.logging': {'get_logger': _Logger},
                 'launch.substitutions': {'LaunchConfiguration': _LaunchConfiguration},
                 'launch_ros': {}, 'launch_ros.actions': {'Node': type('Node', (_Recorded,), {}),
                                                           'LifecycleNode': type('LifecycleNode', (_Recorded,), {})}}
    for name, attributes in stand_ins.items():
        monkeypatch.setitem(sys.modules, name, types.SimpleNamespace(**attributes))
    import ament_index_python.packages
    monkeypatch.setattr(ament_index_python.packages, 'get_package_share_directory', lambda package: '/share/' + package)
    spec = importlib.util.spec_from_file_location('ranker_launch', REPO / 'launch' / 'ranker.launch.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    entities = module.generate_launch_description().args[0]
    declared = {e.args[0]: e.kwargs for e in entities if 'default_value' in e.kwargs}
    configurations = {**{name: kwargs['default_value'] for name, kwargs in declared.items()}, **given}
    for name, kwargs in declared.items():
        assert configurations[name] in kwargs.get('choices', [configurations[name]]), f'launch refuses {name}'
    opaque = next(e for e in entities if 'function' in e.kwargs)
    context = types.SimpleNamespace(launch_configurations=configurations,
                                    argv=[f'{name}:={value}' for name, value in given.items()])
    [node] = opaque.kwargs['function'](context)
    return declared, {**node.kwargs, 'kind': type(node).__name__}


LAUNCH_ONLY = {'record', 'namespace', 'fleet_topic', 'params_file', 'log_level', 'use_sim_time', 'managed'}


def test_launch_arguments_are_node_parameters_and_record_false_turns_recording_off(monkeypatch):
    declared, node = _run_launch_file(monkeypatch)
    assert set(declared) - LAUNCH_ONLY == set(PARAMETERS)  # every parameter is an argument
    assert declared['record']['choices'] == ['true', 'false']
    assert 'namespace' not in node and node['remappings'] == []
    assert (node['package'], node['executable']) == ('stars_ros', 'ranker')
    defaults_file, overrides = node['parameters']
    assert defaults_file == '/share/stars_ros/config/ranker.yaml'
    assert overrides == {'use_sim_time': False}  # the node's own defaults, record_folder under ROS_HOME included
    assert node['ros_arguments'] == ['--log-level', 'info']
    _, node = _run_launch_file(monkeypatch, record='false')
    assert node['parameters'][1] == {'record_folder': '', 'use_sim_time': False}
    _, node = _run_launch_file(monkeypatch, record_folder='/data/bags', top_k='3', max_batch='8', explain='true',
                               log_throttle='2.5')
    assert node['parameters'][1] == {'record_folder': '/data/bags', 'top_k': 3, 'max_batch': 8, 'explain': True,
                                     'log_throttle': 2.5, 'use_sim_time': False}  # each as its parameter's type
    _, node = _run_launch_file(monkeypatch, namespace='robot1', fleet_sharing='true', fleet_topic='/fleet/user_model')
    assert node['namespace'] == 'robot1' and node['remappings'] == [('stars/user_model', '/fleet/user_model')]
    assert node['parameters'][1]['fleet_sharing'] is True


def test_launch_takes_a_params_file_log_level_sim_time_and_a_managed_ranker(monkeypatch):
    params_file = str(REPO / 'config' / 'ranker.yaml')  # a file that is there: a missing one is refused
    declared, node = _run_launch_file(monkeypatch, params_file=params_file, log_level='debug', use_sim_time='true')
    assert declared['log_level']['choices'] == ['debug', 'info', 'warn', 'error', 'fatal']
    assert node['parameters'] == [params_file, {'use_sim_time': True}]
    assert node['ros_arguments'] == ['--log-level', 'debug']
    _, node = _run_launch_file(monkeypatch, managed='true')
    assert (node['kind'], node['executable'], node['namespace']) == ('LifecycleNode', 'managed_ranker', '')


@pytest.mark.parametrize('given, refusal', [
    ({'top_k': 'abc'}, 'top_k:=abc is not an integer'), ({'top_k': '-1'}, 'top_k:=-1 is outside its range'),
    ({'explain': 'maybe'}, 'explain:=maybe is not a boolean'), ({'log_throttle': 'nan'}, 'not a finite number'),
    ({'max_batch': '1.5'}, 'max_batch:=1.5 is not an integer')])
def test_launch_refuses_a_value_its_parameter_cannot_take(monkeypatch, given, refusal):
    with pytest.raises(LaunchArgumentError, match=re.escape(refusal)):
        _run_launch_file(monkeypatch, **given)


def test_a_misspelt_launch_argument_is_named_with_the_closest_declared_one(monkeypatch):
    """``ros2 launch stars_ros ranker.launch.py top_kk:=3``: launch sets top_kk as a
    configuration nobody reads; the file warns, naming it and top_k, as the node warns of a
    misspelt parameter, and starts the node with top_k as the params file has it."""
    _, node = _run_launch_file(monkeypatch, top_kk='3', record='false')
    assert _Logger.logged == [('warning', 'ranker.launch.py', "launch argument 'top_kk' is not one of "
                               "ranker.launch.py's: ignored (did you mean 'top_k'?); "
                               '`ros2 launch stars_ros ranker.launch.py --show-args` lists them')]
    assert 'top_k' not in node['parameters'][1] and 'top_kk' not in node['parameters'][1]
    _run_launch_file(monkeypatch, zzz='1')
    assert _Logger.logged == [('warning', 'ranker.launch.py', "launch argument 'zzz' is not one of "
                               "ranker.launch.py's: ignored; `ros2 launch stars_ros ranker.launch.py "
                               "--show-args` lists them")]
    _run_launch_file(monkeypatch, top_k='3', params_file=str(REPO / 'config' / 'ranker.yaml'), managed='true')
    assert _Logger.logged == []  # every declared argument, a parameter's or the file's own, is known


def test_unknown_arguments_reads_the_command_line_as_ros2_launch_gives_it():
    from stars_ros.ros.launch_arguments import unknown_arguments
    warnings = unknown_arguments(['top_kk:=3', 'top_k:=2', 'top_kk:=4', 'not-an-argument', 'a:=b:=c'],
                                 ['top_k', 'explain'], 'ranker.launch.py')
    assert [warning.split("'")[1] for warning in warnings] == ['top_kk', 'a']  # once each; values may hold :=
    assert "(did you mean 'top_k'?)" in warnings[0] and 'did you mean' not in warnings[1]
    assert unknown_arguments([], ['top_k'], 'ranker.launch.py') == []


def test_demo_scores_print_with_the_digits_that_tell_them_apart():
    def reply(*scores):
        return {'ranking': [{'candidate': f'c{k}', 'score': s} for k, s in enumerate(scores)]}
    assert demo.score_decimals(reply(0.5, 0.25)) == 3
    assert demo.score_decimals(reply(0.41237, 0.41231, 0.2)) == 4
    assert demo.score_decimals(reply(0.5, 0.25), reply(0.412347, 0.412341)) == 5  # the same digits on both lines
    assert demo.score_decimals(reply(0.7, 0.7, 0.1)) == 3  # ties stay ties
    assert demo.ranking_line('a', reply(0.41237, 0.41231), 4) == '    a: c0 0.4124 > c1 0.4123'


def test_demo_records_into_a_folder_of_its_own_unless_told(tmp_path, capsys):
    assert demo.record_folder(None, tmp_path / 'run') == tmp_path / 'run' / 'records'
    given = tmp_path / 'mine'
    given.mkdir()
    assert demo.record_folder(given, tmp_path / 'run') == given and not capsys.readouterr().out
    fill_store(given, 'f' * 64, [PersonUpdate('ann', None, 'f' * 64, [], 0, [], False)])
    demo.record_folder(given, tmp_path / 'run')
    assert 'holds folded-in users of an earlier run' in capsys.readouterr().out
