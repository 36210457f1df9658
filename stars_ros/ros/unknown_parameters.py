"""The warning every node gives for a parameter override it does not declare: rclpy drops
such an override without a word, so ``-p goal_fram:=map`` would silently leave the default."""
from __future__ import annotations

import difflib

from rclpy.parameter import Parameter


def unknown_overrides(node) -> list:
    """Names of the parameter overrides given to ``node`` (``-p``, params files) that it
    has not declared."""
    with node.handle:
        overrides = node.handle.get_parameters(Parameter)
    return sorted(name for name in overrides if not node.has_parameter(name))


def warn_unknown_overrides(node, executable: str, known) -> list:
    """Log a warning for each override ``node`` has not declared, with the nearest of
    ``known`` (its parameter names) when one is close; the names warned about."""
    names = unknown_overrides(node)
    for name in names:
        near = difflib.get_close_matches(name, list(known), n=1)
        node.get_logger().warning(f"parameter '{name}' is not one of the {executable}'s: ignored"
                                  + (f" (did you mean '{near[0]}'?)" if near else '')
                                  + f'; `ros2 run stars_ros {executable} --help` lists them')
    return names
