"""suit_ros.model."""
