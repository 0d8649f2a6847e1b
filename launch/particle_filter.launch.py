"""Launch the particle_filter node with a parameter file (full ROS 2 installs only: needs
``launch`` and ``launch_ros``, which the PyPI-wheel virtual environment does not have).

    ros2 launch localization particle_filter.launch.py
    ros2 launch localization particle_filter.launch.py params_file:=/path/real_params.yaml use_sim_time:=true
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory("localization"), "config", "params.yaml")
    return LaunchDescription([
        DeclareLaunchArgument("params_file", default_value=default_params,
                              description="ROS 2 parameter file of the particle_filter node "
                                          "(config/params.yaml: simulator; config/real_params.yaml: the car)"),
        DeclareLaunchArgument("use_sim_time", default_value="false",
                              description="use /clock (bag replay with --clock, simulators)"),
        Node(
            package="localization",
            executable="particle_filter",
            name="particle_filter",
            output="screen",
            emulate_tty=True,
            parameters=[LaunchConfiguration("params_file"),
                        {"use_sim_time": LaunchConfiguration("use_sim_time")}],
        ),
    ])
