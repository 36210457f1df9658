"""Nodes end cleanly when a signal shuts ROS down, whenever it lands, and within a bound when
the middleware hangs in their shutdown."""
import signal
import subprocess
import sys
import threading

import pytest
import rclpy
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

from ros_helpers import die_with_the_tests, domain_id, ros_env
from stars_ros.ros import spinning


def _spin_raising(error):
    def spin(node):
        raise error
    return spin


SIGNAL_IN_CPP = [_rclpy.RCLError('the given context is not valid'),
                 RuntimeError("Unable to convert call argument '0' to Python object")]


@pytest.mark.parametrize('error', SIGNAL_IN_CPP)
def test_an_error_of_rclpy_as_a_signal_shuts_ros_down_is_a_clean_end(monkeypatch, error):
    """Shut down already, or by rclpy's thread a moment later (the third check)."""
    monkeypatch.setattr(rclpy, 'spin', _spin_raising(error))
    checks = []

    def ok():
        checks.append(1)
        return len(checks) < 3
    monkeypatch.setattr(rclpy, 'ok', ok)
    spinning.spin_until_shutdown(node=None)
    assert len(checks) == 3
    monkeypatch.setattr(rclpy, 'spin', _spin_raising(KeyboardInterrupt()))
    spinning.spin_until_shutdown(node=None)


@pytest.mark.parametrize('error', SIGNAL_IN_CPP)
def test_an_error_of_rclpy_while_ros_runs_is_raised(monkeypatch, error):
    monkeypatch.setattr(rclpy, 'spin', _spin_raising(error))
    monkeypatch.setattr(rclpy, 'ok', lambda: True)
    monkeypatch.setattr(spinning, 'SIGNAL_SHUTDOWN_WAIT_S', 0.05)
    with pytest.raises(type(error)):
        spinning.spin_until_shutdown(node=None)


@pytest.fixture(autouse=True)
def signal_handlers():
    """``init`` puts in its own Python handlers: this process gets its own back, unsignalled."""
    kept = {number: signal.getsignal(number) for number in (signal.SIGINT, signal.SIGTERM)}
    spinning.SIGNALLED.clear()
    yield
    spinning.SIGNALLED.clear()
    for number, handler in kept.items():
        signal.signal(number, handler)


class _Node:
    def __init__(self):
        self.calls = []

    def destroy_node(self):
        self.calls.append('destroyed')

    def close(self):
        self.calls.append('closed')


def _fake_ros(monkeypatch, calls: list):
    monkeypatch.setattr(rclpy, 'init', lambda args=None, **options: calls.append(('init', options)))
    monkeypatch.setattr(rclpy, 'try_shutdown', lambda: calls.append('shutdown'))


@pytest.mark.parametrize('ending, status', [(KeyboardInterrupt(), None), (SystemExit(0), None),
                                            (ValueError('bad rate'), 1)])
def test_run_node_ends_cleanly_and_exits_1_on_a_fatal_error(monkeypatch, ending, status):
    calls = []
    _fake_ros(monkeypatch, calls)
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
    assert calls == [('init', {'signal_handler_options': rclpy.signals.SignalHandlerOptions.ALL}), 'shutdown']
    assert node.calls == ['destroyed', 'closed']


def test_a_signal_is_noted_and_raises_nothing_and_one_before_rclpy_shuts_ros_down(monkeypatch):
    """After ``init``, the Python handler rclpy passes a signal on to only notes it; a signal
    that came before rclpy's handlers were in (here: during ``rclpy.init``) shuts ROS down."""
    calls = []
    monkeypatch.setattr(rclpy, 'init', lambda args=None, **options: signal.raise_signal(signal.SIGTERM))
    monkeypatch.setattr(rclpy, 'try_shutdown', lambda: calls.append('shutdown'))
    spinning.init()
    assert spinning.SIGNALLED.is_set() and calls == ['shutdown']
    signal.raise_signal(signal.SIGINT)  # no KeyboardInterrupt


def test_an_error_of_a_node_starting_as_a_signal_shuts_ros_down_is_a_clean_end(monkeypatch):
    calls = []
    _fake_ros(monkeypatch, calls)
    monkeypatch.setattr(rclpy, 'ok', lambda: False)
    spinning.SIGNALLED.set()

    def make_node():
        raise _rclpy.RCLError('the given context is not valid')
    spinning.run_node('test', make_node)
    assert calls[-1] == 'shutdown'
    spinning.SIGNALLED.clear()  # no signal: the same error is raised
    with pytest.raises(_rclpy.RCLError):
        spinning.run_node('test', make_node)


def test_an_error_destroying_the_node_is_raised_once_it_is_closed_and_ros_shut_down(monkeypatch):
    calls = []
    _fake_ros(monkeypatch, calls)
    node = _Node()

    def destroy_node():
        raise RuntimeError('destroyed already')
    node.destroy_node = destroy_node
    with pytest.raises(RuntimeError, match='destroyed already'):
        spinning.run_node('test', lambda: node, _spin_raising(KeyboardInterrupt()), close=_Node.close)
    assert node.calls == ['closed'] and calls[-1] == 'shutdown'


def test_a_middleware_that_hangs_in_destroy_node_still_closes_and_returns(monkeypatch, capsys):
    """The node is closed (its store commits) and the ending returns, saying why."""
    calls = []
    _fake_ros(monkeypatch, calls)
    monkeypatch.setattr(spinning, 'DESTROY_WAIT_S', 0.05)
    released = threading.Event()
    node = _Node()
    node.destroy_node = lambda: released.wait(60)  # Fast DDS busy in set_listener
    try:
        spinning.run_node('test', lambda: node, _spin_raising(KeyboardInterrupt()), close=_Node.close)
        assert node.calls == ['closed'] and 'shutdown' not in calls
        expected = 'test: the middleware did not shut down within 0.05 s; closed, exiting'
        assert expected in capsys.readouterr().err
    finally:
        released.set()


_BUSY_NODE = '''
import sys, time
from rclpy.node import Node
from stars_ros.ros import spinning

class Busy(Node):
    def __init__(self):
        super().__init__('busy')
        self.create_timer(0.001, self.work)

    def work(self):  # Python code running when the signals land
        end = time.monotonic() + 0.05
        while time.monotonic() < end:
            pass
        print('working', flush=True)

spinning.run_node('busy', Busy, close=lambda node: print('closed', flush=True))
'''


@pytest.mark.parametrize('signals', [[signal.SIGINT], [signal.SIGINT, signal.SIGINT, signal.SIGTERM]])
def test_signals_landing_in_a_busy_callback_end_the_process_with_status_0(signals):
    """The process is the subject: its exit status and what it printed."""
    child = subprocess.Popen([sys.executable, '-c', _BUSY_NODE], env=ros_env(domain_id(16)), text=True,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, preexec_fn=die_with_the_tests)
    try:
        assert child.stdout.readline().strip() == 'working'
        for number in signals:
            child.send_signal(number)
        output, _ = child.communicate(timeout=60)
    finally:
        if child.poll() is None:
            child.kill()
    assert child.returncode == 0, output
    assert 'closed' in output and 'Traceback' not in output and 'KeyboardInterrupt' not in output, output
