"""Facts about the Franka Emika Panda and the held gear, shared by the controller and the simulator.

Units: metres, kilograms, radians, newton-metres, seconds.
"""

from __future__ import annotations

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
