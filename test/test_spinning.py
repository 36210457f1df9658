"""Nodes end cleanly when a signal shuts ROS down, whenever it lands."""
import pytest
import rclpy
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

from stars_ros import spinning


def _spin_raising(error):
    def spin(node):
        raise error
    return spin


def test_a_wait_set_error_after_shutdown_is_a_clean_end(monkeypatch):
    monkeypatch.setattr(rclpy, 'spin', _spin_raising(_rclpy.RCLError('the given context is not valid')))
    monkeypatch.setattr(rclpy, 'ok', lambda: False)
    spinning.spin_until_shutdown(node=None)
    monkeypatch.setattr(rclpy, 'spin', _spin_raising(KeyboardInterrupt()))
    spinning.spin_until_shutdown(node=None)


def test_a_wait_set_error_while_ros_runs_is_raised(monkeypatch):
    monkeypatch.setattr(rclpy, 'spin', _spin_raising(_rclpy.RCLError('something else')))
    monkeypatch.setattr(rclpy, 'ok', lambda: True)
    with pytest.raises(_rclpy.RCLError):
        spinning.spin_until_shutdown(node=None)
