"""Launch the ranker with the packaged defaults (config/ranker.yaml).

    ros2 launch stars_ros ranker.launch.py checkpoint:=/path/to/model.pt record_folder:=/tmp/stars

Leave ``checkpoint`` empty to serve the packaged SocNav1 GAT-StARS model.
"""
from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    defaults = Path(get_package_share_directory('stars_ros')) / 'config' / 'ranker.yaml'
    arguments = {
        'checkpoint': ('', 'checkpoint file; empty: the packaged default model'),
        'record_folder': ('stars_records', 'folder for the MCAP recordings; empty: do not record'),
        'top_k': ('0', 'publish only the best k entries of each ranking; 0: all'),
    }
    return LaunchDescription([
        *[DeclareLaunchArgument(name, default_value=default, description=text)
          for name, (default, text) in arguments.items()],
        Node(
            package='stars_ros',
            executable='ranker',
            name='ranker',
            output='screen',
            parameters=[str(defaults), {name: LaunchConfiguration(name) for name in arguments}],
        ),
    ])
