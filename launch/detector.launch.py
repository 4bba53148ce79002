"""Launch the suit_ros detector with params/detector.yaml (ros2 launch suit_ros ...)."""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    """Detector node with the installed default parameters (override with params_file:=)."""
    default = os.path.join(get_package_share_directory('suit_ros'), 'params', 'detector.yaml')
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=default),
        Node(package='suit_ros', executable='detector', name='detector', output='screen',
             parameters=[LaunchConfiguration('params_file')]),
    ])
