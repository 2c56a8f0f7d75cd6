"""Every QoS profile of the stack, once. Publishers and subscribers of a topic take the same one.

- ``STATE``: the joint-state / command pair of a control loop (ros2_control's depth 10, reliable).
- ``PUBLISH``: publishers of the 1 kHz monitoring topics (joint states, commands, clock, task
  status). A reliable keep-last writer drops the oldest samples for a reader more than ``depth``
  behind, and a recorder on a busy 2-core machine can be off the CPU for tens of ms: 1000 samples
  (about 1 s at 1 kHz) cost memory only, a keep-last writer never blocks.
- ``POLICY``: policy parameters, latched (transient local) with depth 1: the topic carries the
  latest policy; a node that joins late gets it, never a backlog of older ones.
- ``ROLLOUTS``: rollout chunks (reliable, deep enough for a whole 5 s episode in flight).
- ``DIAGNOSTICS``: ``/diagnostics`` (reliable, depth 10).
"""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

PUBLISH_DEPTH = 1000

STATE = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
PUBLISH = QoSProfile(depth=PUBLISH_DEPTH, reliability=ReliabilityPolicy.RELIABLE)
POLICY = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
ROLLOUTS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
DIAGNOSTICS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
