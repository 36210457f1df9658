"""Launch arguments as node parameters: a value read as the parameter's own type and checked
against its range, or refused with a clear error, as ``ros2 run ... -p`` refuses it.

Without this, ``ros2 launch stars_ros ranker.launch.py top_k:=abc`` hands the node the
string 'abc' after the packaged params file's 0, and ROS drops the later value of another
type without a word. ROS-free, so it is tested without launch.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Mapping

from stars_ros.errors import LaunchArgumentError

TRUE, FALSE = ('true', 'yes', 'on'), ('false', 'no', 'off')  # YAML 1.1 booleans, as rcl reads -p values


def parameter_value(name: str, text: str, parameters: Mapping[str, tuple]):
    """``text`` as a value of parameter ``name`` (``parameters``: name -> (default, description,
    read_only, range), the node's table): bool, int, float or str like its default, in range."""
    default, _, _, limits = parameters[name]
    word = text.strip().lower()
    if isinstance(default, bool):
        if word not in TRUE + FALSE:
            raise LaunchArgumentError(f"{name}:={text} is not a boolean (true or false)")
        return word in TRUE
    if isinstance(default, int):
        try:
            value = int(text.strip())
        except ValueError:
            raise LaunchArgumentError(f'{name}:={text} is not an integer') from None
    elif isinstance(default, float):
        try:
            value = float(text.strip())
        except ValueError:
            raise LaunchArgumentError(f'{name}:={text} is not a number') from None
        if not math.isfinite(value):
            raise LaunchArgumentError(f'{name}:={text} is not a finite number')
    else:
        return text
    if limits and not limits[0] <= value <= limits[1]:
        raise LaunchArgumentError(f'{name}:={text} is outside its range [{limits[0]}, {limits[1]}]')
    return value


def existing_file(name: str, text: str) -> str:
    """``text``, the path launch argument ``name`` names, refused when no file is there: a
    node started on a missing file would fail while the launch runs on without it."""
    if not Path(text).expanduser().is_file():
        raise LaunchArgumentError(f'{name}:={text}: no such file')
    return text
