"""Rigs for tests and benchmarks (as franka_ros2 keeps its in its bringup package): franky-sim."""
