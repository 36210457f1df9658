"""How the package's nodes run: ``rclpy.spin`` until a signal or a ROS shutdown, and the
life of a node executable from ``rclpy.init`` to a clean shutdown, bounded in time.

Signals go through rclpy's own handlers (``rclpy.init``'s default ``SignalHandlerOptions.ALL``):
on SIGINT or SIGTERM they shut the context down, which wakes the executor, and ``rclpy.spin``
ends with ``ExternalShutdownException``, as in ros2/examples. rclpy then calls the Python
handler it found; ``init`` puts in one that notes the signal and raises nothing, so no
``KeyboardInterrupt`` lands in the middle of a callback, of rclpy's C++ code or of the ending."""
from __future__ import annotations

import re
import signal
import sys
import threading
from typing import Callable

import rclpy
from rclpy.exceptions import NameValidationException, ParameterException
from rclpy.executors import ExternalShutdownException
# rclpy exports its error types from its implementation module only (its own modules import them so)
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.logging import LoggingSeverity, get_logger, get_logger_level, set_logger_level
from rclpy.signals import SignalHandlerOptions

from stars_ros.errors import CommandLineError
from stars_ros.waiting import wait_for

USAGE_ERROR = 2  # the exit status of a command line rcl or a parameter declaration refuses
DESTROY_WAIT_S = 3.0  # longest wait for the middleware to destroy a node and shut down before closing anyway
CLOSE_WAIT_S = 12.0  # longest ``close`` then takes (the state store joins its writer for up to 10 s)
SIGNAL_SHUTDOWN_WAIT_S = 1.0  # how long an error out of rclpy.spin may take to turn out to be a signal's shutdown
SIGNALLED = threading.Event()  # set by SIGINT or SIGTERM once ``init`` has run


def _note_signal(number, frame) -> None:
    """The Python handler rclpy's handlers call after shutting ROS down: the signal is noted."""
    SIGNALLED.set()


def _rcl_message(error: Exception) -> str:
    """rcl's message without its source locations (", at /path/arguments.c:415")."""
    text = re.sub(r', at \S+\.c:\d+', '', str(error))
    return text.removeprefix('failed to initialize rcl: ')


def init(args=None) -> None:
    """``rclpy.init(args)`` with rclpy's SIGINT and SIGTERM handlers, which call
    ``_note_signal`` after theirs; a signal that came before them shuts ROS down at once.
    ``--ros-args`` rcl refuses (a params file it cannot open or parse, an override, remap or
    log level it cannot read, an unknown ROS argument) raise ``CommandLineError`` with rcl's
    reason. rcl's own "Failed to parse global arguments" log line is held back: the error
    says more."""
    for number in (signal.SIGINT, signal.SIGTERM):
        signal.signal(number, _note_signal)
    previous = get_logger_level('rcl')
    set_logger_level('rcl', LoggingSeverity.FATAL)
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.ALL)
    except _rclpy.UnknownROSArgsError as error:
        raise CommandLineError(f'unknown ROS arguments: {str(error).strip("[]")}') from None
    except _rclpy.RCLError as error:
        raise CommandLineError(_rcl_message(error)) from None
    finally:
        if get_logger_level('rcl') == LoggingSeverity.FATAL:  # not set by --log-level rcl:=...
            set_logger_level('rcl', previous)
    if SIGNALLED.is_set():
        rclpy.try_shutdown()


def spin_until_shutdown(node) -> None:
    """Spin ``node``; SIGINT, SIGTERM and a ROS shutdown return normally. A shutdown can come
    between rclpy's check of the context and the wait set it then builds (RCLError, seen once
    in CI), or while it converts a message it takes (RuntimeError "Unable to convert call
    argument", seen in a clean-clone run). An error of either kind is a shutdown too when the
    context stops being ok within SIGNAL_SHUTDOWN_WAIT_S; otherwise it is raised."""
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:  # RCLError is one
        if not _shutting_down():
            raise


def _shutting_down() -> bool:
    """Whether ROS's context is, or within SIGNAL_SHUTDOWN_WAIT_S becomes, shut down."""
    return wait_for(lambda: not rclpy.ok(), SIGNAL_SHUTDOWN_WAIT_S, interval=0.01)


def run_node(name: str, make_node: Callable, run: Callable = spin_until_shutdown, fatal: tuple = (),
             args=None, ends: tuple = (), close: Callable | None = None) -> None:
    """``init(args)``, ``run(make_node())``, then destroy the node, ``close(node)`` and shut
    ROS down, however it ended (``end``). A signal, or one of ``ends`` (exceptions the node
    ends with on purpose), is a normal end, and so is an error of rclpy's while a signal shuts
    ROS down (a node still starting when it came); one of ``fatal`` is logged as ``name``'s
    fatal error and exits with status 1. ``--ros-args`` that rcl refuses, and parameter values
    or names the node refuses while it declares them, print one line, ``name: error: ...``, on
    stderr and exit with status 2, as a command-line error."""
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
    except Exception:
        if not (SIGNALLED.is_set() and _shutting_down()):
            raise
    finally:
        end(name, node, close)


def end(name: str, node, close: Callable | None) -> None:
    """Destroy the node, ``close(node)`` (the state store commits what waits, within
    CLOSE_WAIT_S), shut ROS down. The middleware's part runs on a thread of its own: it has
    hung in Fast DDS's ``set_listener`` at shutdown, and when it has not finished within
    DESTROY_WAIT_S the node is closed anyway and the ending returns, saying so; the process
    then exits with the status it has, that thread left behind (a daemon). An error of the
    middleware's part is raised once the ending is done."""
    destroyed, closed, errors = threading.Event(), threading.Event(), []

    def middleware():
        for step in (lambda: node is not None and node.destroy_node(), destroyed.set, closed.wait,
                     rclpy.try_shutdown):
            try:
                step()
            except Exception as error:  # noqa: BLE001 - raised in the ending's own thread
                errors.append(error)
        destroyed.set()

    ending = threading.Thread(target=middleware, name='stars-shutdown', daemon=True)
    ending.start()
    on_time = destroyed.wait(DESTROY_WAIT_S)
    try:
        if node is not None and close is not None:
            close(node)
    finally:
        closed.set()
    if not (on_time and _joined(ending, DESTROY_WAIT_S)):
        print(f'{name}: the middleware did not shut down within {DESTROY_WAIT_S:g} s; closed, exiting',
              file=sys.stderr, flush=True)
    elif errors:
        raise errors[0]


def _joined(thread: threading.Thread, timeout: float) -> bool:
    thread.join(timeout)
    return not thread.is_alive()


def _usage_error(name: str, message: str):
    print(f'{name}: error: {message}', file=sys.stderr, flush=True)
    raise SystemExit(USAGE_ERROR)
