"""posecorr in a ROS 2 robot cell: `posecorr ros2 MODEL` corrects a tracker's PoseStamped
stream with the C runtime and swaps models while it runs (`node.py`). Needs the extra
`posecorr[ros2]` (rclpy and the message packages from PyPI; no ROS install)."""
