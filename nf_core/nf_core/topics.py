"""Names shared by the nodes (ros2_control conventions) and the lockstep handshake. ROS-free.

Lockstep handshake: the controller answers each joint state with one command and writes the
state's stamp into the command's ``layout.dim[0].label`` as ``state_stamp_ns=<int>``. A
lockstep simulator applies a command only to the state it answers, so a late or duplicated
reply (after a resend) can never shift the loop by a step. ros2_control's effort controller
ignores the layout, so real drivers are unaffected; commands without the label are accepted
as answers to the current state.
"""

from __future__ import annotations

JOINT_STATES = "joint_states"  # sensor_msgs/JointState (joint_state_broadcaster)
COMMANDS = "effort_controller/commands"  # std_msgs/Float64MultiArray (JointGroupEffortController)
CLOCK = "clock"  # rosgraph_msgs/Clock, lockstep simulated time
TASK_STATUS = "task_status"  # nf_msgs/TaskStatus (simulation only)
CONTROLLER_STATUS = "controller_status"  # nf_msgs/ControllerStatus
POLICY_PARAMETERS = "policy_parameters"  # nf_msgs/PolicyParameters, relative: each arm its own
DIAGNOSTICS = "/diagnostics"  # diagnostic_msgs/DiagnosticArray
ROLLOUTS = "rollouts"  # nf_msgs/RolloutChunk, controller -> learner
TELEOP_TARGET = "teleop/target"  # geometry_msgs/PointStamped, operator -> controller (teleop_speed > 0)

RUN_EPISODE = "run_episode"  # nf_msgs/action/RunEpisode, served by the controller
SIM_RESET = "sim_bridge/reset"  # nf_msgs/srv/ResetSim, served by the sim bridge

STATE_STAMP_LABEL = "state_stamp_ns="


def stamp_label(stamp_ns: int) -> str:
    """The label that marks a command as the answer to the state stamped ``stamp_ns`` (always the
    same length: the stamp zero-padded to 20 digits, so a serialized command can be rewritten in place)."""
    return f"{STATE_STAMP_LABEL}{stamp_ns:020d}"


def parse_stamp_label(label: str) -> int | None:
    """The state stamp (ns) a command answers, or None if the label does not carry one."""
    if not label.startswith(STATE_STAMP_LABEL):
        return None
    try:
        return int(label[len(STATE_STAMP_LABEL):])
    except ValueError:
        return None
