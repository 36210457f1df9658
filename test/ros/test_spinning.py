"""Nodes end cleanly when a signal shuts ROS down, whenever it lands, and within a bound when
the middleware hangs in their shutdown."""
import signal
import subprocess
import sys
import threading
import types

import pytest
import rclpy
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

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
    """run_node ignores signals while it shuts down: this process gets its own back."""
    kept = {number: signal.getsignal(number) for number in (signal.SIGINT, signal.SIGTERM)}
    yield
    for number, handler in kept.items():
        signal.signal(number, handler)


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


def test_a_middleware_that_hangs_in_destroy_node_still_closes_and_exits(monkeypatch, capsys):
    """The watchdog closes the node (its store commits) and ends the process, status 0."""
    monkeypatch.setattr(rclpy, 'init', lambda args=None: None)
    monkeypatch.setattr(spinning, 'DESTROY_WAIT_S', 0.01)
    exited, released = [], threading.Event()

    def exit_process(status):  # the process would end here: release the hung destroy_node instead
        exited.append(status)
        released.set()
    monkeypatch.setattr(spinning, 'os', types.SimpleNamespace(_exit=exit_process))
    node = _Node()
    node.destroy_node = lambda: released.wait(60)  # Fast DDS busy in set_listener
    monkeypatch.setattr(rclpy, 'try_shutdown', lambda: None)
    spinning.run_node('test', lambda: node, _spin_raising(KeyboardInterrupt()), close=_Node.close)
    assert exited == [0] and node.calls == ['closed']  # closed once, by the watchdog
    assert 'test: the middleware did not shut down within 0.01 s; closed, exiting' in capsys.readouterr().err
    assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN  # a second Ctrl-C meanwhile raises nothing


@pytest.mark.parametrize('interrupted_call', [1, 2])
def test_a_signal_whose_handler_runs_late_does_not_end_the_ending(monkeypatch, interrupted_call):
    """A SIGINT's KeyboardInterrupt raised as the ending begins (the first ``_ignore_signals``,
    before it ignored anything) or after rclpy's shutdown put Python's handler back (the
    second): the node is still destroyed, closed and ROS shut down, each once."""
    calls = []
    monkeypatch.setattr(rclpy, 'init', lambda args=None: None)
    monkeypatch.setattr(rclpy, 'try_shutdown', lambda: calls.append('shutdown'))
    ignore, seen = spinning._ignore_signals, []

    def late_signal():
        seen.append(1)
        if len(seen) == interrupted_call:
            raise KeyboardInterrupt
        ignore()
    monkeypatch.setattr(spinning, '_ignore_signals', late_signal)
    node = _Node()
    spinning.run_node('test', lambda: node, _spin_raising(KeyboardInterrupt()), close=_Node.close)
    assert calls == ['shutdown'] and node.calls == ['destroyed', 'closed']
    assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN


_INTERRUPTED_IN_PYRUN_STRING = '''
import ctypes
evaluate = ctypes.pythonapi.PyRun_String
evaluate.restype, evaluate.argtypes = ctypes.py_object, [ctypes.c_char_p, ctypes.c_int, ctypes.py_object, ctypes.py_object]

def interrupted(node=None):  # a Ctrl-C whose KeyboardInterrupt is raised in code rclpy's extension evaluates
    evaluate(b'raise KeyboardInterrupt', 257, {}, {})  # Py_file_input
'''


@pytest.mark.parametrize('ended_by, status', [('caught', -signal.SIGINT), ('run_node', 0)])
def test_a_signal_handled_inside_code_run_by_pyrun_string_still_exits_0(ended_by, status):
    """CPython exits -2 at the end of a process whose PyRun_String code ended in a
    KeyboardInterrupt, even one caught (``caught``: what a node's Ctrl-C gave in CI); a node
    that ``run_node`` ended cleanly exits 0. The process is the subject: its exit status."""
    ending = {'caught': 'try:\n    interrupted()\nexcept KeyboardInterrupt:\n    pass\n',
              'run_node': ('import rclpy\nfrom stars_ros.ros import spinning\n'
                           'rclpy.init, rclpy.try_shutdown = (lambda args=None: None), (lambda: None)\n'
                           'spinning.run_node("test", lambda: types.SimpleNamespace(destroy_node=lambda: None), '
                           'interrupted)\n')}[ended_by]
    child = subprocess.run([sys.executable, '-c', _INTERRUPTED_IN_PYRUN_STRING + 'import types\n' + ending],
                           capture_output=True, text=True, timeout=120)
    assert child.returncode == status, child.stderr
