"""The whole ROS4HRI loop without a robot: the scripted world (hri_world), the bridge
(hri_bridge) and the ranker.

    ros2 launch stars_ros hri.launch.py source:=$STARS_SOCNAV1_ROOT/raw/a.jsonl
    ros2 launch stars_ros hri.launch.py world:=false   # a robot's own ROS4HRI stack instead (docs/hri.md)

Poses travel as TF where tf2_ros exists (``pose_source:=tf``), else on hri/transforms
(``pose_source:=topic``). A ``source`` that names no file is refused before anything starts.
Recording goes to the ranker's default folder unless
``record_folder`` is set. ``store_policy:=consented`` (with ``consent_file`` and/or the latched
stars/consent) goes to the ranker and the bridge alike: one consent list for the loop
(docs/privacy.md); a ``consent_file`` that names no file is refused before anything starts.
``--show-args`` lists the arguments; one the file does not declare is named in a warning, with
the closest declared name, and ignored.

    ros2 launch stars_ros hri.launch.py world:=false store_policy:=consented consent_file:=/etc/stars/consent.txt
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.conditions import IfCondition
from launch.logging import get_logger
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from stars_ros.ros.launch_arguments import existing_file, unknown_arguments


def _tf2_available() -> bool:
    try:
        import tf2_ros  # noqa: F401
    except ImportError:
        return False
    return True


def _privacy(context) -> dict:
    """store_policy and consent_file for both the bridge and the ranker; nothing under 'all'
    (their defaults, which read no file), and no empty consent_file (launch_ros reads it as
    null and refuses it)."""
    store_policy = LaunchConfiguration('store_policy').perform(context)
    consent_file = LaunchConfiguration('consent_file').perform(context)
    if store_policy == 'all':
        return {}
    if consent_file:
        existing_file('consent_file', consent_file)  # both nodes would die on it while the launch runs on
    return {'store_policy': store_policy, **({'consent_file': consent_file} if consent_file else {})}


def _nodes(context, declared):
    for warning in unknown_arguments(context.argv, declared, 'hri.launch.py'):
        get_logger('hri.launch.py').warning(warning)
    source = LaunchConfiguration('source').perform(context)
    if source:
        existing_file('source', source)  # the world would die on it while the launch runs on
    pose_source = LaunchConfiguration('pose_source').perform(context) or ('tf' if _tf2_available() else 'topic')
    ranker = {'record_folder': LaunchConfiguration('record_folder')} if LaunchConfiguration(
        'record_folder').perform(context) else {}
    privacy = _privacy(context)
    return [
        Node(package='stars_ros', executable='hri_world', name='hri_world', output='screen',
             parameters=[{'source': LaunchConfiguration('source'), 'pose_source': pose_source,
                          'base_frame': LaunchConfiguration('base_frame')}],
             condition=IfCondition(LaunchConfiguration('world'))),
        Node(package='stars_ros', executable='hri_bridge', name='hri_bridge', output='screen',
             parameters=[{'pose_source': pose_source, 'base_frame': LaunchConfiguration('base_frame'),
                          'goal_frame': LaunchConfiguration('goal_frame'), **privacy}]),
        Node(package='stars_ros', executable='ranker', name='ranker', output='screen',
             parameters=[{**ranker, **privacy}]),
    ]


def generate_launch_description():
    declared = []

    def declare(name, **options):
        declared.append(name)
        return DeclareLaunchArgument(name, **options)
    return LaunchDescription([
        declare('source', default_value='', description='SocNav1 JSONL file placing the scripted '
                'people; empty: a generated scene'),
        declare('world', default_value='true', choices=['true', 'false'],
                description='false: no scripted world (a robot publishes ROS4HRI)'),
        declare('pose_source', default_value='', description='tf or topic; empty: tf where tf2_ros '
                'is importable'),
        declare('base_frame', default_value='base_link', description="the robot's frame"),
        declare('goal_frame', default_value='map', description='frame of stars/goal, one that does not '
                'move with the robot (map, odom)'),
        declare('record_folder', default_value='', description="the ranker's record folder; empty: "
                'its default'),
        declare('store_policy', default_value='all', choices=['all', 'consented'],
                description="whom the ranker stores and the bridge relays feedback of: 'all'; "
                "'consented': the people on the consent list only (docs/privacy.md)"),
        declare('consent_file', default_value='', description="with store_policy 'consented': ids of "
                'people who agreed to be stored, one a line; empty: stars/consent only'),
        OpaqueFunction(function=lambda context: _nodes(context, declared)),
    ])
