"""The shared core: what every node and tool of the stack agrees on (topics and QoS, policy
parameters, flow spec, episode, reward, arm and part specs) and the ROS runtime helpers."""
