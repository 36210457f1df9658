"""How the package's nodes run: ``rclpy.spin`` until a signal or a ROS shutdown, and the
life of a node executable from ``rclpy.init`` to a clean shutdown."""
from __future__ import annotations

from typing import Callable

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.logging import get_logger


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


def run_node(name: str, make_node: Callable, run: Callable = spin_until_shutdown, fatal: tuple = (),
             args=None, ends: tuple = (), close: Callable | None = None) -> None:
    """``rclpy.init(args)``, ``run(make_node())``, then destroy the node, ``close(node)`` and
    shut ROS down, however it ended. A signal, or one of ``ends`` (exceptions the node ends
    with on purpose), is a normal end; one of ``fatal`` is logged as ``name``'s fatal error
    and exits with status 1."""
    rclpy.init(args=args)
    node = None
    try:
        node = make_node()
        run(node)
    except (KeyboardInterrupt, ExternalShutdownException, *ends):
        pass
    except fatal as error:
        get_logger(name).fatal(str(error))
        raise SystemExit(1) from None
    finally:
        if node is not None:
            node.destroy_node()
            if close is not None:
                close(node)
        rclpy.try_shutdown()
