"""Launch the ranker with the packaged defaults (config/ranker.yaml), or a params file of yours.

    ros2 launch stars_ros ranker.launch.py record_folder:=/tmp/stars top_k:=3
    ros2 launch stars_ros ranker.launch.py params_file:=/etc/stars/ranker.yaml log_level:=debug use_sim_time:=true
    ros2 launch stars_ros ranker.launch.py record:=false
    ros2 launch stars_ros ranker.launch.py namespace:=robot1 fleet_sharing:=true fleet_topic:=/fleet/user_model
    ros2 launch stars_ros ranker.launch.py managed:=true   # unconfigured until a lifecycle manager configures it

Every parameter of the node is an argument (``--show-args`` lists them with their meaning);
left empty, the params file's value holds (the packaged one holds every default). A value
that is not one of its parameter's type or range is refused before the node starts, as
``ros2 run ... -p`` refuses it (``top_k:=abc``: "top_k:=abc is not an integer"), and a
``params_file`` or ``checkpoint`` that names no file is refused before the node starts. An empty
launch argument is refused on the command line (``record_folder:=''``), so recording is
turned off with ``record:=false``. A robot of a fleet runs in its ``namespace`` and remaps
stars/user_model to ``fleet_topic``. ``managed:=true`` starts the managed (lifecycle) ranker,
``ros2 run stars_ros managed_ranker``: configure loads the checkpoint, activate serves.
An argument the file does not declare (``top_kk:=3``) is named in a warning, with the closest
declared name, and ignored, as the node names a parameter it does not declare.
"""
from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.logging import get_logger
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import LifecycleNode, Node

from stars_ros.node.parameters import PARAMETERS
from stars_ros.ros.launch_arguments import existing_file, parameter_value, unknown_arguments

LOG_LEVELS = ['debug', 'info', 'warn', 'error', 'fatal']


def _ranker(context, declared):
    """The node, given only the parameters whose arguments were set, each as its own type:
    launch_ros reads an empty substitution as YAML null and refuses it, and left out, the
    params file's value holds. First, a warning for each given argument not ``declared``."""
    for warning in unknown_arguments(context.argv, declared, 'ranker.launch.py'):
        get_logger('ranker.launch.py').warning(warning)

    def argument(name):
        return LaunchConfiguration(name).perform(context)
    parameters = {name: parameter_value(name, argument(name), PARAMETERS) for name in PARAMETERS if argument(name)}
    if argument('record') == 'false':
        parameters['record_folder'] = ''  # a plain '' stays a string
    parameters['use_sim_time'] = argument('use_sim_time') == 'true'
    for name in ('params_file', 'checkpoint'):
        if argument(name):
            existing_file(name, argument(name))  # the node would die on it while the launch runs on
    params_file = argument('params_file') or str(Path(get_package_share_directory('stars_ros')) / 'config'
                                                 / 'ranker.yaml')
    namespace, fleet_topic, managed = argument('namespace'), argument('fleet_topic'), argument('managed') == 'true'
    options = dict(package='stars_ros', executable='managed_ranker' if managed else 'ranker', name='ranker',
                   output='screen', parameters=[params_file, parameters],
                   ros_arguments=['--log-level', argument('log_level')],
                   remappings=[('stars/user_model', fleet_topic)] if fleet_topic else [])
    if managed:
        return [LifecycleNode(namespace=namespace, **options)]
    return [Node(**({'namespace': namespace} if namespace else {}), **options)]


def generate_launch_description():
    declared = []

    def declare(name, **options):
        declared.append(name)
        return DeclareLaunchArgument(name, **options)
    return LaunchDescription([
        *[declare(name, default_value='', description=f'{spec[1]} (empty: the params file\'s value)')
          for name, spec in PARAMETERS.items()],
        declare('params_file', default_value='',
                description="the node's params file; empty: the packaged config/ranker.yaml"),
        declare('log_level', default_value='info', choices=LOG_LEVELS,
                description="the node's log level"),
        declare('use_sim_time', default_value='false', choices=['true', 'false'],
                description='true: the node reads time from /clock (bag replays, simulators)'),
        declare('managed', default_value='false', choices=['true', 'false'],
                description='true: the managed (lifecycle) ranker, which serves once configured and '
                'activated'),
        declare('record', default_value='true', choices=['true', 'false'],
                description='false: do not record (record_folder is ignored)'),
        declare('namespace', default_value='', description="the robot's namespace, e.g. robot1"),
        declare('fleet_topic', default_value='',
                description='remap stars/user_model to this fleet-wide topic, e.g. /fleet/user_model'),
        OpaqueFunction(function=lambda context: _ranker(context, declared)),
    ])
