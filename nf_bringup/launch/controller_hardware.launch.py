"""ROS 2 launch file for a real Panda under ros2_control (see docs/hardware.md): only the flow
controller, with gravity compensation left to Franka's driver, the stale-state watchdog on,
no simulator reset, and the safe hold between episodes. The learner runs separately.

    ros2 launch nf_bringup controller_hardware.launch.py config:=config/gear.yaml
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription([
        DeclareLaunchArgument("config", default_value="config/gear.yaml", description="task parameters file"),
        Node(package="nf_controller_node", executable="nf_controller", name="nf_controller", output="screen",
             parameters=[LaunchConfiguration("config"), {
                 "gravity_compensation": False, "state_timeout": 0.02, "reset_service": "",
                 "idle_mode": "hold", "driver_effort": "measured"}]),
    ])
