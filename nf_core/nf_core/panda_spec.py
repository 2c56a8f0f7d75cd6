"""Facts about the Franka Emika Panda and the held parts (gear, peg), shared by the controller and the simulator.

Units: metres, kilograms, radians, newton-metres, seconds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

JOINT_NAMES = tuple(f"panda_joint{i}" for i in range(1, 8))
FINGER_JOINT_NAMES = ("panda_finger_joint1", "panda_finger_joint2")
FINGER_OPENING = 0.0  # m, locked finger joint position (each finger)

# Franka datasheet limits.
TORQUE_LIMITS = np.array([87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0])  # Nm
TORQUE_RATE_LIMIT = 1000.0  # Nm/s, per joint
Q_MIN = np.array([-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973])  # rad
Q_MAX = np.array([2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973])  # rad
DQ_MAX = np.array([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61])  # rad/s

# Plausibility of a measured joint state (``control_loop.ControlLoop``, every mode): a reading
# outside these bounds is not the state of a working Panda (sensor fault, spoofed message) and
# latches the safe hold on the last valid state. The position margin covers the simulator's soft
# joint limits and encoder offsets; the velocity factor leaves room for what the simulator (which
# does not enforce velocity limits) really does, while refusing readings no arm produces (the
# datasheet limits are 2.175 / 2.61 rad/s; enforcing them is the robot's own reflex). Smaller
# factors refuse valid simulated states (fast joints after a reset or with explored gains); 10 x
# still refuses garbage (1e6 rad/s, a wrong unit) at once.
Q_PLAUSIBLE_MARGIN = float(np.deg2rad(5.0))  # rad beyond the datasheet joint limits
DQ_PLAUSIBLE_FACTOR = 10.0  # x DQ_MAX
Q_PLAUSIBLE_MIN = Q_MIN - Q_PLAUSIBLE_MARGIN  # rad
Q_PLAUSIBLE_MAX = Q_MAX + Q_PLAUSIBLE_MARGIN  # rad
DQ_PLAUSIBLE_MAX = DQ_PLAUSIBLE_FACTOR * DQ_MAX  # rad/s
# Reach: the Panda's TCP stays within 855 mm of joint 2 (333 mm above the base) plus the held part;
# a goal farther than this from the base frame's origin cannot be reached by any configuration.
MAX_REACH = 1.2  # m

# Drive-side joint dynamics, used by the simulator and by the controller's rigid-body model.
# Armature: reflected rotor inertia (rotor inertia x gear ratio^2, roughly 1e-5 kg m^2 x 100^2),
# added to the diagonal of the joint-space mass matrix (the value MuJoCo Menagerie uses for
# the Panda). Pinocchio's ``model.armature`` must hold the same numbers so both mass matrices agree.
JOINT_ARMATURE = np.array([0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1])  # kg m^2
# Viscous joint friction: tau_friction = -JOINT_DAMPING * dq. The order of the viscous
# coefficients identified on a real Panda (Gaz et al., RA-L 2019: 0.01-0.23 Nm s/rad).
# Passive in the simulator; not part of the rigid-body bias forces.
JOINT_DAMPING = np.array([0.1, 0.1, 0.1, 0.1, 0.05, 0.05, 0.05])  # Nm s/rad

# Held gear: welded to the hand frame ``panda_hand`` (z along the approach direction).
HAND_FRAME = "panda_hand"
GEAR_BORE_RADIUS = 0.015  # m (30 mm bore)
GEAR_OUTER_RADIUS = 0.030  # m (60 mm outer diameter)
GEAR_DEPTH = 0.020  # m
GEAR_MASS = 0.12  # kg (aluminium ring, 60/30 mm, 20 mm thick)
# Gear centre of mass in the hand frame: the gear's top face sits at the fingertips.
GEAR_COM_IN_HAND = np.array([0.0, 0.0, 0.1134])  # m
# Tool-centre point: centre of the gear's bottom face (the bore mouth), in the hand frame.
TCP_IN_HAND = np.array([0.0, 0.0, 0.1234])  # m
TCP_FRAME = "gear_tcp"


def gear_inertia() -> np.ndarray:
    """Rotational inertia (3x3, kg m^2) of the gear ring about its centre of mass, hand axes."""
    m, r1, r2, h = GEAR_MASS, GEAR_BORE_RADIUS, GEAR_OUTER_RADIUS, GEAR_DEPTH
    izz = 0.5 * m * (r1**2 + r2**2)
    ixx = m * (3.0 * (r1**2 + r2**2) + h**2) / 12.0
    return np.diag([ixx, ixx, izz])

# Orientation of the hand frame for insertion, in the world frame: approach axis (hand z)
# pointing down, hand x along world x (the Panda's usual "home" orientation).
INSERTION_ROTATION = np.diag([1.0, -1.0, -1.0])


def panda_urdf_path() -> str:
    """Path of the Panda URDF shipped by example-robot-data (the one file MuJoCo and Pinocchio load)."""
    import importlib.metadata
    import sys
    from pathlib import Path

    rel = "share/example-robot-data/robots/panda_description/urdf/panda.urdf"
    try:
        files = importlib.metadata.files("example-robot-data") or []
    except importlib.metadata.PackageNotFoundError:
        files = []
    for f in files:
        if str(f).endswith(rel) and Path(f.locate()).is_file():
            return str(f.locate())
    for entry in sys.path:  # any cmeel prefix on the path
        candidate = Path(entry) / "cmeel.prefix" / rel
        if candidate.is_file():
            return str(candidate)
    raise FileNotFoundError(
        "panda.urdf not found: install the 'example-robot-data' package (make setup); it ships the "
        "Panda URDF under cmeel.prefix/share/example-robot-data"
    )


# Peg (peg-in-hole task): a 23 mm aluminium rod, 60 mm long, held with 10 mm of it between the
# fingertip pads; its tip sits 40 mm below the fingertips so the fingers stay clear of the hole
# block at full insertion.
PEG_RADIUS = 0.0115  # m
PEG_LENGTH = 0.060  # m
PEG_TOP_IN_HAND = 0.0934  # m, z of the peg's upper face in the hand frame
PEG_MASS = 2700.0 * np.pi * PEG_RADIUS**2 * PEG_LENGTH  # kg, aluminium (about 0.067 kg)
PEG_COM_IN_HAND = np.array([0.0, 0.0, PEG_TOP_IN_HAND + 0.5 * PEG_LENGTH])  # m
PEG_TCP_IN_HAND = np.array([0.0, 0.0, PEG_TOP_IN_HAND + PEG_LENGTH])  # m, tip centre
PEG_TCP_FRAME = "peg_tcp"


def peg_inertia() -> np.ndarray:
    """Rotational inertia (3x3, kg m^2) of the solid peg about its centre of mass, hand axes."""
    m, r, h = PEG_MASS, PEG_RADIUS, PEG_LENGTH
    ixx = m * (3.0 * r**2 + h**2) / 12.0
    return np.diag([ixx, ixx, 0.5 * m * r**2])


@dataclass(frozen=True)
class HeldPartInertia:
    """A part held rigidly by the hand: mass properties and tool-centre point (hand frame), and the names
    the simulator gives it. The one held-part type of the controller's arm model and the simulator."""

    mass: float  # kg
    com_in_hand: np.ndarray  # m, centre of mass in the panda_hand frame
    inertia: np.ndarray  # kg m^2, 3x3 about the centre of mass, hand axes
    tcp_in_hand: np.ndarray  # m, the point the controller drives to x_ref
    kind: str = "gear"  # "gear" or "peg"
    body: str = "gear"  # MuJoCo body name of the part
    tcp_site: str = TCP_FRAME  # MuJoCo site name at the part's leading face (the TCP)
    name: str = ""  # the part as one line (held_part: gear | peg | a task file's part); "": its kind


GEAR_PART = HeldPartInertia(GEAR_MASS, GEAR_COM_IN_HAND, gear_inertia(), TCP_IN_HAND, "gear", "gear", TCP_FRAME)
PEG_PART = HeldPartInertia(PEG_MASS, PEG_COM_IN_HAND, peg_inertia(), PEG_TCP_IN_HAND, "peg", "peg", PEG_TCP_FRAME)
HELD_PARTS = {"gear": GEAR_PART, "peg": PEG_PART}
