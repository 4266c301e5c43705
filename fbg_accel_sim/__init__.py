"""Physics-based simulator of the acquisition board (no ROS imports)."""
