"""Bring up a simulated valve rig: valve_hardware + valve_controller (separate processes), and optionally
valve_identification running a plan and valve_monitor watching the valve's health.

    ros2 launch piezo_valve_ros rig.launch.py [namespace:=valve1] [params:=/path/to/rig.yaml] \
        [identify:=true plan:=train,refit,validate] [composed:=true] [monitor:=true]
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory("piezo_valve_ros"), "config", "rig.yaml")
    namespace = LaunchConfiguration("namespace")
    params = LaunchConfiguration("params")
    composed = LaunchConfiguration("composed")
    return LaunchDescription([
        DeclareLaunchArgument("namespace", default_value="", description="namespace of the valve"),
        DeclareLaunchArgument("params", default_value=default_params, description="parameters file"),
        DeclareLaunchArgument("composed", default_value="false",
                              description="hardware and controller in one process (valve_composed)"),
        Node(package="piezo_valve_ros", executable="valve_hardware", name="valve_hardware",
             namespace=namespace, parameters=[params], output="screen", condition=UnlessCondition(composed)),
        Node(package="piezo_valve_ros", executable="valve_controller", name="valve_controller",
             namespace=namespace, parameters=[params], output="screen", condition=UnlessCondition(composed)),
        # one process, two nodes (valve_hardware, valve_controller): no name remap here, it would rename both
        Node(package="piezo_valve_ros", executable="valve_composed", namespace=namespace, parameters=[params],
             output="screen", condition=IfCondition(composed)),
        DeclareLaunchArgument("identify", default_value="false", description="start valve_identification"),
        DeclareLaunchArgument("plan", default_value="train,refit,validate", description="identification plan"),
        Node(package="piezo_valve_ros", executable="valve_identification", name="valve_identification",
             namespace=namespace, parameters=[params, {"plan": LaunchConfiguration("plan")}], output="screen",
             condition=IfCondition(LaunchConfiguration("identify"))),
        DeclareLaunchArgument("monitor", default_value="false", description="start valve_monitor"),
        Node(package="piezo_valve_ros", executable="valve_monitor", name="valve_monitor", namespace=namespace,
             parameters=[params], output="screen", condition=IfCondition(LaunchConfiguration("monitor"))),
    ])
