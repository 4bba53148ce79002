"""suit_ros.ops."""
