"""Records every topic to a rosbag2 MCAP directory and replays it with the recorded timing."""
