"""suit_ros.msg_adapters: pure ROS message <-> numpy conversions (no rclpy import)."""
