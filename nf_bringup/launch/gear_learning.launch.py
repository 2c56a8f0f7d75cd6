"""ROS 2 launch file (full ROS 2 Jazzy installs; mirrors ``run_stack`` / ``make run``): the sim
bridge in lockstep, the flow controller and the learner, all reading one parameters file.

    ros2 launch launch/gear_learning.launch.py config:=config/gear.yaml out_dir:=runs/launch

Not runnable in the pip environment (no ``launch`` wheels): use ``make run`` there.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description() -> LaunchDescription:
    config = LaunchConfiguration("config")
    return LaunchDescription([
        DeclareLaunchArgument("config", default_value="config/gear.yaml", description="task parameters file"),
        DeclareLaunchArgument("out_dir", default_value="runs/launch", description="learner output folder"),
        DeclareLaunchArgument("iterations", default_value="10", description="PPO iterations"),
        Node(package="sim_bridge_node", executable="sim_bridge", name="sim_bridge", output="screen",
             parameters=[config]),
        Node(package="nf_controller_node", executable="nf_controller", name="nf_controller", output="screen",
             parameters=[config, {"idle_mode": "pause", "max_consecutive_misses": 0}]),  # lockstep sim waits
        Node(package="learner_node", executable="learner", name="learner_node", output="screen",
             parameters=[config, {"out_dir": LaunchConfiguration("out_dir"),
                                  "iterations": LaunchConfiguration("iterations")}]),
    ])
