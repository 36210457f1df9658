"""The ranker node's logic without ROS: request batching and scoring, diagnostics figures,
and ``RankerCore``, which ``stars_ros.ros.ranker`` wraps in an rclpy node."""
