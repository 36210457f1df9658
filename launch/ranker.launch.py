"""Launch the ranker with the packaged defaults (config/ranker.yaml).

    ros2 launch stars_ros ranker.launch.py record_folder:=/tmp/stars top_k:=3
    ros2 launch stars_ros ranker.launch.py checkpoint:=$(ros2 pkg prefix --share stars_ros)/models/socnav1_gat_stars.pt
    ros2 launch stars_ros ranker.launch.py record:=false
    ros2 launch stars_ros ranker.launch.py namespace:=robot1 fleet_sharing:=true fleet_topic:=/fleet/user_model
    ros2 launch stars_ros ranker.launch.py feedback_key_file:=/etc/stars/keys.txt

Leave ``checkpoint`` empty to serve the packaged SocNav1 GAT-StARS model and
``record_folder`` empty for the node's default, ``$ROS_HOME/stars_ros/records/{node}``. A robot
of a fleet runs in its ``namespace`` and remaps stars/user_model to ``fleet_topic``. An empty
launch argument is refused on the command line (``record_folder:=''``), so recording is
turned off with ``record:=false``. ``ros2 launch stars_ros ranker.launch.py --show-args``
lists the arguments.
"""
from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

OPTIONAL = {  # launch argument = node parameter; empty (the default): the node's own default
    'checkpoint': 'checkpoint file; empty: the packaged default model',
    'record_folder': 'folder for the MCAP recordings; empty: the node default $ROS_HOME/stars_ros/records/{node}',
    'top_k': 'publish only the best k entries of each ranking; empty: the node default (0: all)',
    'fleet_sharing': 'true: share folded-in users on stars/user_model; empty: the node default (false)',
    'feedback_key_file': 'keys that sign feedback (docs/security.md); empty: feedback is not authenticated',
}


def _ranker(context):
    """The node, given only the arguments that were set: launch_ros reads an empty
    substitution as YAML null and refuses it, and left out, the node's own default holds."""
    parameters = {name: LaunchConfiguration(name) for name in OPTIONAL if LaunchConfiguration(name).perform(context)}
    if LaunchConfiguration('record').perform(context) == 'false':
        parameters['record_folder'] = ''  # a plain '' stays a string
    defaults = Path(get_package_share_directory('stars_ros')) / 'config' / 'ranker.yaml'
    namespace, fleet_topic = (LaunchConfiguration(name).perform(context) for name in ('namespace', 'fleet_topic'))
    return [Node(package='stars_ros', executable='ranker', name='ranker', output='screen',
                 parameters=[str(defaults), parameters], **({'namespace': namespace} if namespace else {}),
                 remappings=[('stars/user_model', fleet_topic)] if fleet_topic else [])]


def generate_launch_description():
    return LaunchDescription([
        *[DeclareLaunchArgument(name, default_value='', description=text) for name, text in OPTIONAL.items()],
        DeclareLaunchArgument('record', default_value='true', choices=['true', 'false'],
                              description='false: do not record (record_folder is ignored)'),
        DeclareLaunchArgument('namespace', default_value='', description="the robot's namespace, e.g. robot1"),
        DeclareLaunchArgument('fleet_topic', default_value='',
                              description='remap stars/user_model to this fleet-wide topic, e.g. /fleet/user_model'),
        OpaqueFunction(function=_ranker),
    ])
