"""Localization on the car: nav2 map_server with a map of the package, the particle filter with the
car's parameters, optionally RViz (full ROS 2 installs: needs launch, launch_ros, nav2_map_server,
nav2_lifecycle_manager and, for rviz:=true, rviz2).

    ros2 launch localization localization_car.launch.py                        # maps/basement_fixed, real_params
    ros2 launch localization localization_car.launch.py map:=stata_basement rviz:=true
    ros2 launch localization localization_car.launch.py map:=/path/to/my_map.yaml lifecycle:=true
    ros2 launch localization localization_car.launch.py params_file:=/path/params.yaml \\
        set_initial_pose:=true initial_pose_x:=0.8 initial_pose_y:=-0.3 initial_pose_yaw:=1.26
    ros2 launch localization localization_car.launch.py publish_tf:=map_to_particle_filter_frame

TF (REP-105): ``publish_tf:=map_to_odom`` (the default here) makes the node broadcast map → odom,
so with the VESC driver's odom → base_link and the laser mount (robot_state_publisher or a
static transform base_link → laser) the tree is map → odom → base_link → laser: nav2 gets its
map → odom, RViz (fixed frame map, view following base_link) places the scans in their own
frame. ``publish_tf:=map_to_particle_filter_frame`` is the course's map → base_link_pf beside
the odometry tree; ``none`` broadcasts nothing.

``map`` is a map name of the package's maps/ (``basement_fixed``, ``stata_basement``,
``building_31``) or the path of a map_server YAML. map_server is a lifecycle node: a
nav2_lifecycle_manager configures and activates it (and the particle filter too with
``lifecycle:=true``, which starts the ``particle_filter_lifecycle`` executable).
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

PACKAGE = "localization"
DEFAULT_MAP = "basement_fixed"


def resolve_map(value: str, share: str) -> str:
    """A map_server YAML path, or a map name looked up in the package's maps/."""
    if value.endswith((".yaml", ".yml")) or os.sep in value:
        return os.path.abspath(os.path.expanduser(value))
    return os.path.join(share, "maps", f"{value}.yaml")


def _nodes(context):
    share = get_package_share_directory(PACKAGE)
    get = lambda name: LaunchConfiguration(name).perform(context)  # noqa: E731
    map_yaml = resolve_map(get("map"), share)
    if not os.path.isfile(map_yaml):
        raise RuntimeError(f"map not found: {map_yaml} (map:=NAME of {os.path.join(share, 'maps')} or a YAML path)")
    use_sim_time = get("use_sim_time").lower() in ("true", "1")
    lifecycle = get("lifecycle").lower() in ("true", "1")
    pf_params = {"use_sim_time": use_sim_time, "publish_tf": get("publish_tf")}
    if get("set_initial_pose").lower() in ("true", "1"):
        pf_params.update({"set_initial_pose": True, "initial_pose.x": float(get("initial_pose_x")),
                          "initial_pose.y": float(get("initial_pose_y")),
                          "initial_pose.yaw": float(get("initial_pose_yaw"))})
    managed = ["map_server"] + (["particle_filter"] if lifecycle else [])
    return [
        Node(package="nav2_map_server", executable="map_server", name="map_server", output="screen",
             parameters=[{"yaml_filename": map_yaml, "topic_name": "map", "frame_id": "map",
                          "use_sim_time": use_sim_time}]),
        Node(package="nav2_lifecycle_manager", executable="lifecycle_manager", name="lifecycle_manager_localization",
             output="screen",
             parameters=[{"autostart": True, "node_names": managed, "bond_timeout": 0.0,
                          "use_sim_time": use_sim_time}]),
        Node(package=PACKAGE, executable="particle_filter_lifecycle" if lifecycle else "particle_filter",
             name="particle_filter", output="screen", emulate_tty=True,
             parameters=[get("params_file"), pf_params]),
    ]


def generate_launch_description():
    share = get_package_share_directory(PACKAGE)
    return LaunchDescription([
        DeclareLaunchArgument("map", default_value=DEFAULT_MAP,
                              description="map name in the package's maps/ (basement_fixed, stata_basement, "
                                          "building_31) or a map_server YAML path"),
        DeclareLaunchArgument("params_file", default_value=os.path.join(share, "config", "real_params.yaml"),
                              description="parameter file of the particle filter (default: the car's, "
                                          "config/real_params.yaml)"),
        DeclareLaunchArgument("rviz", default_value="false", description="also start RViz with rviz/localization.rviz"),
        DeclareLaunchArgument("lifecycle", default_value="false",
                              description="start particle_filter_lifecycle, managed by the lifecycle manager"),
        DeclareLaunchArgument("use_sim_time", default_value="false", description="use /clock (bag replay)"),
        DeclareLaunchArgument("publish_tf", default_value="map_to_odom",
                              description="the node's TF: map_to_odom (REP-105: map -> odom, for nav2), "
                                          "map_to_particle_filter_frame (map -> base_link_pf) or none"),
        DeclareLaunchArgument("set_initial_pose", default_value="false",
                              description="start from initial_pose_x/y/yaw instead of waiting for /initialpose"),
        DeclareLaunchArgument("initial_pose_x", default_value="0.0", description="m, map frame"),
        DeclareLaunchArgument("initial_pose_y", default_value="0.0", description="m, map frame"),
        DeclareLaunchArgument("initial_pose_yaw", default_value="0.0", description="rad, map frame"),
        OpaqueFunction(function=_nodes),
        Node(package="rviz2", executable="rviz2", name="rviz2", output="screen",
             arguments=["-d", os.path.join(share, "rviz", "localization.rviz")],
             condition=IfCondition(LaunchConfiguration("rviz"))),
    ])
