"""nf_bags: record rollouts of the node stack as rosbag2 MCAP bags, replay them, read them offline,
re-simulate recorded episodes. See bags/README.md."""
