"""PPO learner for the normalizing-flow policy (ROS-free core) and its node."""
