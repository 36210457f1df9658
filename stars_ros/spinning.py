"""How the package's nodes spin: ``rclpy.spin`` until a signal or a ROS shutdown."""
from __future__ import annotations

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy


def spin_until_shutdown(node) -> None:
    """Spin ``node``; SIGINT, SIGTERM and a ROS shutdown return normally. A signal can shut
    the context down between rclpy's check of it and the wait set rclpy then builds, which
    raises RCLError (seen once in CI): with the context no longer ok, that is a shutdown too."""
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except _rclpy.RCLError:
        if rclpy.ok():
            raise
