"""ROS 2 launch file (full ROS 2 Jazzy installs) for what ``make run`` runs: the sim bridge in lockstep
composed with the flow controller in one process (``nf_sim_stack``: two nodes, the 1 kHz tick a direct
call) and the learner, all reading the same parameters files: ``config/sim.yaml`` (the simulated
stack's settings), then the task file (default ``config/gear_learn.yaml``, make run's; its iterations).
The files are installed to this package's share/config, so it runs outside the repository.
``separate:=true`` starts the sim and the controller as two processes over topics instead.

    ros2 launch nf_bringup gear_learning.launch.py out_dir:=runs/launch
    ros2 launch nf_bringup gear_learning.launch.py config:=/path/to/my_task.yaml

Not runnable in the pip environment (no ``launch`` wheels): use ``make run`` there (no recorder here).
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description() -> LaunchDescription:
    share = os.path.join(get_package_share_directory("nf_bringup"), "config")
    files = [os.path.join(share, "sim.yaml"), LaunchConfiguration("config")]
    separate = LaunchConfiguration("separate")
    return LaunchDescription([
        DeclareLaunchArgument("config", default_value=os.path.join(share, "gear_learn.yaml"),
                              description="task parameters file (after config/sim.yaml)"),
        DeclareLaunchArgument("out_dir", default_value="runs/launch", description="learner output folder"),
        DeclareLaunchArgument("separate", default_value="false",
                              description="true: sim and controller as two processes over topics"),
        Node(package="nf_bringup", executable="nf_sim_stack", output="screen",  # no name: it holds two nodes
             parameters=files, condition=UnlessCondition(separate)),
        Node(package="sim_bridge_node", executable="sim_bridge", name="sim_bridge", output="screen",
             parameters=files, condition=IfCondition(separate)),
        Node(package="nf_controller_node", executable="nf_controller", name="nf_controller", output="screen",
             parameters=files, condition=IfCondition(separate)),
        Node(package="nf_bringup", executable="robot_state", name="robot_state", output="screen",
             parameters=files),  # the cell's robot description and transforms, for viewers and the bag
        Node(package="learner_node", executable="learner", name="learner_node", output="screen",
             parameters=[*files, {"out_dir": LaunchConfiguration("out_dir"), "policy_subscribers": 1}]),
    ])
