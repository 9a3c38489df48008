"""ROS 2 interop over rmw_zenoh without ROS installed (docs/ros2.md): the agent's belief as ROS 2
topics, and frames built from a robot's ROS 2 odometry and detections. Needs the optional extra
``ros2`` (rosbags), imported only when the interop is switched on."""
