"""suit_ros.data."""
