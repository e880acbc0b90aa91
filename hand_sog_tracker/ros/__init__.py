"""ROS 2 layer: the tracker node, message conversion and parameters.

Everything ROS-specific lives here; :mod:`hand_sog_tracker.core` never imports rclpy.
"""
