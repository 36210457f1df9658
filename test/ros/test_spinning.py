"""Nodes end cleanly when a signal shuts ROS down, whenever it lands."""
import pytest
import rclpy
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

from stars_ros.ros import spinning


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


class _Node:
    def __init__(self):
        self.calls = []

    def destroy_node(self):
        self.calls.append('destroyed')

    def close(self):
        self.calls.append('closed')


@pytest.mark.parametrize('ending, status', [(KeyboardInterrupt(), None), (SystemExit(0), None),
                                            (ValueError('bad rate'), 1)])
def test_run_node_ends_cleanly_and_exits_1_on_a_fatal_error(monkeypatch, ending, status):
    calls = []
    monkeypatch.setattr(rclpy, 'init', lambda args=None: calls.append('init'))
    monkeypatch.setattr(rclpy, 'try_shutdown', lambda: calls.append('shutdown'))
    node = _Node()

    def run(running):
        assert running is node
        raise ending
    if status is None:
        spinning.run_node('test', lambda: node, run, (ValueError,), ends=(SystemExit,), close=_Node.close)
    else:
        with pytest.raises(SystemExit) as exited:
            spinning.run_node('test', lambda: node, run, (ValueError,), close=_Node.close)
        assert exited.value.code == status
    assert calls == ['init', 'shutdown'] and node.calls == ['destroyed', 'closed']
