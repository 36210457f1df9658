"""The ROS 2 adapters: the nodes (ranker, scene_publisher, replay), the demo that runs them,
and their spinning and --help helpers. Only modules in this folder import rclpy; the rest of
stars_ros works without ROS (test/test_core_without_ros.py checks)."""
