"""How the package's nodes run: ``rclpy.spin`` until a signal or a ROS shutdown, and the
life of a node executable from ``rclpy.init`` to a clean shutdown, bounded in time."""
from __future__ import annotations

import ctypes
import os
import re
import signal
import sys
import threading
from typing import Callable

import rclpy
from rclpy.exceptions import NameValidationException, ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.logging import LoggingSeverity, get_logger, get_logger_level, set_logger_level

from stars_ros.errors import CommandLineError
from stars_ros.waiting import wait_for

USAGE_ERROR = 2  # the exit status of a command line rcl or a parameter declaration refuses
DESTROY_WAIT_S = 3.0  # longest wait for the middleware to destroy a node and shut down before closing anyway
CLOSE_WAIT_S = 12.0  # longest wait for ``close`` then (the state store joins its writer for up to 10 s)
SIGNAL_SHUTDOWN_WAIT_S = 1.0  # how long an error out of rclpy.spin may take to turn out to be a signal's shutdown
_PY_EVAL_INPUT = 258  # Py_eval_input (Python.h)


def _rcl_message(error: Exception) -> str:
    """rcl's message without its source locations (", at /path/arguments.c:415")."""
    text = re.sub(r', at \S+\.c:\d+', '', str(error))
    return text.removeprefix('failed to initialize rcl: ')


def init(args=None) -> None:
    """``rclpy.init(args)``; ``--ros-args`` rcl refuses (a params file it cannot open or parse,
    an override, remap or log level it cannot read, an unknown ROS argument) raise
    ``CommandLineError`` with rcl's reason. rcl's own "Failed to parse global arguments" log
    line is held back: the error says more."""
    previous = get_logger_level('rcl')
    set_logger_level('rcl', LoggingSeverity.FATAL)
    try:
        rclpy.init(args=args)
    except _rclpy.UnknownROSArgsError as error:
        raise CommandLineError(f'unknown ROS arguments: {str(error).strip("[]")}') from None
    except _rclpy.RCLError as error:
        raise CommandLineError(_rcl_message(error)) from None
    finally:
        if get_logger_level('rcl') == LoggingSeverity.FATAL:  # not set by the arguments (--log-level rcl:=...)
            set_logger_level('rcl', previous)


def spin_until_shutdown(node) -> None:
    """Spin ``node``; SIGINT, SIGTERM and a ROS shutdown return normally. A signal can land
    inside rclpy's C++ code: between its check of the context and the wait set it then builds
    (RCLError, seen once in CI), or while it converts a message it takes (RuntimeError "Unable
    to convert call argument", seen in a clean-clone run). An error of either kind is a
    shutdown too when the context stops being ok within SIGNAL_SHUTDOWN_WAIT_S (rclpy shuts it
    down on its own thread); otherwise it is raised."""
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (_rclpy.RCLError, RuntimeError):
        if not _shutting_down():
            raise


def _shutting_down() -> bool:
    """Whether ROS's context is, or within SIGNAL_SHUTDOWN_WAIT_S becomes, shut down."""
    return wait_for(lambda: not rclpy.ok(), SIGNAL_SHUTDOWN_WAIT_S, interval=0.01)


def run_node(name: str, make_node: Callable, run: Callable = spin_until_shutdown, fatal: tuple = (),
             args=None, ends: tuple = (), close: Callable | None = None) -> None:
    """``rclpy.init(args)``, ``run(make_node())``, then destroy the node, ``close(node)`` and
    shut ROS down, however it ended. A signal, or one of ``ends`` (exceptions the node ends
    with on purpose), is a normal end; one of ``fatal`` is logged as ``name``'s fatal error
    and exits with status 1. ``--ros-args`` that rcl refuses, and parameter values or names
    the node refuses while it declares them, print one line, ``name: error: ...``, on stderr
    and exit with status 2, as a command-line error."""
    try:
        init(args)
    except CommandLineError as error:
        _usage_error(name, str(error))
    node = None
    try:
        node = make_node()
        run(node)
    except (KeyboardInterrupt, ExternalShutdownException, *ends):
        pass
    except (ParameterException, NameValidationException) as error:
        _usage_error(name, str(error))
    except fatal as error:
        get_logger(name).fatal(str(error))
        raise SystemExit(1) from None
    finally:
        _Ending(name, node, close).run()


class _Closing:
    """``close(node)`` once, from whichever thread gets there first."""

    def __init__(self, node, close: Callable | None):
        self._node, self._close, self._lock, self._done = node, close, threading.Lock(), False

    def __call__(self):
        with self._lock:
            if not self._done and self._node is not None and self._close is not None:
                self._done = True
                self._close(self._node)


class _Ending:
    """Destroy the node, ``close(node)``, shut ROS down; a signal meanwhile is ignored (a second
    Ctrl-C would otherwise raise KeyboardInterrupt inside ``destroy_node``). A SIGINT whose
    Python handler runs before the ending has ignored signals (at the first Python-level check,
    which can be the ending's own first line; seen in CI), or after rclpy's shutdown put that
    handler back, raises KeyboardInterrupt: that signal is the ending already under way, so
    ``run`` goes on from the step it reached, each step done once. When the middleware has not
    finished within DESTROY_WAIT_S (it has hung in Fast DDS's ``set_listener`` at shutdown), a
    watchdog closes the node (the state store commits what waits) and ends the process with
    status 0 once that is done or CLOSE_WAIT_S have passed."""

    def __init__(self, name: str, node, close: Callable | None):
        self.name, self.node = name, node
        self.closing, self.finished = _Closing(node, close), threading.Event()
        self.done: set = set()

    def run(self) -> None:
        while True:
            try:
                self._steps()
                return
            except KeyboardInterrupt:
                continue

    def _steps(self) -> None:
        _ignore_signals()
        if 'watchdog' not in self.done:
            threading.Thread(target=self._watchdog, name='stars-shutdown-watchdog', daemon=True).start()
            self.done.add('watchdog')
        try:
            if self.node is not None and 'destroyed' not in self.done:
                self.done.add('destroyed')
                self.node.destroy_node()
            self.closing()
            if 'shutdown' not in self.done:
                self.done.add('shutdown')
                rclpy.try_shutdown()
            _ignore_signals()  # rclpy's shutdown puts back the handlers it found: Python's raises KeyboardInterrupt
            _forget_handled_interrupt()
        except KeyboardInterrupt:
            raise  # ``run`` goes on, the watchdog still watching
        except BaseException:
            self.finished.set()
            raise
        self.finished.set()

    def _watchdog(self):
        if self.finished.wait(DESTROY_WAIT_S):
            return
        closer = threading.Thread(target=self.closing, name='stars-close', daemon=True)
        closer.start()
        closer.join(CLOSE_WAIT_S)
        print(f'{self.name}: the middleware did not shut down within {DESTROY_WAIT_S:g} s; '
              + ('closed, ' if not closer.is_alive() else f'close did not finish within {CLOSE_WAIT_S:g} s, ')
              + 'exiting', file=sys.stderr, flush=True)
        os._exit(0)


def _ignore_signals():
    """Ignore SIGINT and SIGTERM from now on. A SIGINT that came while the thread waited in
    rcl (rclpy's handler passes it on to Python's) raises KeyboardInterrupt at the first
    Python-level check, which can be this very call (seen once in CI): that signal is the
    ending already under way, so the handler is set again."""
    for number in (signal.SIGINT, signal.SIGTERM):
        while True:
            try:
                signal.signal(number, signal.SIG_IGN)
                break
            except KeyboardInterrupt:
                continue


def _forget_handled_interrupt():
    """Let the process exit with its own status after a signal's KeyboardInterrupt was handled.
    CPython marks a KeyboardInterrupt that ends code run by ``PyRun_String`` as unhandled even
    when a caller catches it, and at exit then kills its own process with SIGINT (status -2, no
    traceback); rclpy's extension runs Python code that way, so a Ctrl-C landing there ended a
    node that had shut down cleanly with -2 (seen in CI). Each ``PyRun_String`` clears that mark
    before it evaluates, so one of a constant does; signals are ignored by now, so nothing can
    set it again."""
    run = ctypes.pythonapi.PyRun_String
    run.restype, run.argtypes = ctypes.py_object, [ctypes.c_char_p, ctypes.c_int, ctypes.py_object, ctypes.py_object]
    run(b'None', _PY_EVAL_INPUT, {}, {})


def _usage_error(name: str, message: str):
    print(f'{name}: error: {message}', file=sys.stderr, flush=True)
    raise SystemExit(USAGE_ERROR)
