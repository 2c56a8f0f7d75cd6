"""Stable normalizing-flow controller: fast evaluator, arm model, torque law (ROS-free core) and node."""
