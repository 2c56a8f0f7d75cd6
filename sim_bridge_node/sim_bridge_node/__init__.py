"""MuJoCo scenes and environments standing in for the Panda (ROS-free core) and the bridge node."""
