"""ROS 2 launch file (full ROS 2 Jazzy installs; mirrors ``run_stack`` / ``make run``): the sim
bridge in lockstep composed with the flow controller in one process (``nf_sim_stack``: two nodes,
the 1 kHz tick a direct call) and the learner, all reading one parameters file.
``separate:=true`` starts the sim and the controller as two processes over topics instead.

    ros2 launch nf_bringup gear_learning.launch.py config:=config/gear.yaml out_dir:=runs/launch

Not runnable in the pip environment (no ``launch`` wheels): use ``make run`` there.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description() -> LaunchDescription:
    config = LaunchConfiguration("config")
    separate = LaunchConfiguration("separate")
    lockstep_controller = {"idle_mode": "pause", "max_consecutive_misses": 0}  # the lockstep sim waits
    return LaunchDescription([
        DeclareLaunchArgument("config", default_value="config/gear.yaml", description="task parameters file"),
        DeclareLaunchArgument("out_dir", default_value="runs/launch", description="learner output folder"),
        DeclareLaunchArgument("iterations", default_value="10", description="PPO iterations"),
        DeclareLaunchArgument("separate", default_value="false",
                              description="true: sim and controller as two processes over topics"),
        # Both nodes in one process; their parameters come from the file's sim_bridge and
        # nf_controller sections, the controller's lockstep settings as ROS arguments.
        Node(package="nf_bringup", executable="nf_sim_stack", output="screen",  # no name: it holds two nodes
             parameters=[config], condition=UnlessCondition(separate),
             arguments=["--ros-args", "-p", "nf_controller:idle_mode:=pause",
                        "-p", "nf_controller:max_consecutive_misses:=0"]),
        Node(package="sim_bridge_node", executable="sim_bridge", name="sim_bridge", output="screen",
             parameters=[config], condition=IfCondition(separate)),
        Node(package="nf_controller_node", executable="nf_controller", name="nf_controller", output="screen",
             parameters=[config, lockstep_controller], condition=IfCondition(separate)),
        Node(package="learner_node", executable="learner", name="learner_node", output="screen",
             parameters=[config, {"out_dir": LaunchConfiguration("out_dir"),
                                  "iterations": LaunchConfiguration("iterations")}]),
    ])
