"""``--help`` of the node executables, answered before rclpy starts: asking for it creates
no node, joins no ROS graph and writes nothing (rcl's log files included).

ROS-free. The parameters are printed from the node's own table, so the help cannot drift
from what the node declares.
"""
from __future__ import annotations

import sys
from typing import Mapping, Sequence


def asked_for_help(argv: Sequence[str]) -> bool:
    """``-h`` or ``--help`` among the executable's own arguments; what follows
    ``--ros-args`` belongs to ROS (``-p name:=--help`` is a value, not a request)."""
    argv = list(argv)
    own = argv[:argv.index('--ros-args')] if '--ros-args' in argv else argv
    return '-h' in own or '--help' in own


def shown_value(default) -> str:
    """A default as it is written after ``-p name:=`` (the value is read as YAML)."""
    if isinstance(default, bool):
        return str(default).lower()
    if isinstance(default, str):
        return f"'{default}'"
    if isinstance(default, (list, tuple)):
        return '[' + ', '.join(shown_value(item) for item in default) + ']'
    return str(default)


def help_text(executable: str, doc: str, parameters: Mapping[str, tuple], example: str) -> str:
    """What ``executable`` does (the first two paragraphs of its module ``doc``), its
    parameters with defaults (``parameters``: name -> (default, description, ...)) and how
    to set them."""
    about = '\n\n'.join(doc.strip().split('\n\n')[:2]).replace('``', '')
    lines = [f'usage: ros2 run stars_ros {executable} [--ros-args (-p NAME:=VALUE | --params-file FILE | -r A:=B)...]',
             f'       python -m stars_ros.ros.{executable} [--ros-args ...]', '', about, '',
             'parameters (set with --ros-args -p NAME:=VALUE, values read as YAML: -p "name:=\'\'" is an',
             'empty string; or --params-file FILE; remap topics with -r stars/scene:=/other):']
    for name, (default, description, *_) in parameters.items():
        lines += [f'  {name} (default {shown_value(default)})', f'      {description}']
    lines += ['', f'example: {example}']
    return '\n'.join(lines)


def print_help_if_asked(executable: str, doc: str, parameters: Mapping[str, tuple], example: str,
                        argv: Sequence[str] | None = None) -> bool:
    """Print ``help_text`` and return True when ``argv`` (default ``sys.argv``) asks for it;
    the caller then returns before ``rclpy.init``."""
    if not asked_for_help(sys.argv if argv is None else argv):
        return False
    print(help_text(executable, doc, parameters, example))
    return True
