"""Launch arguments as node parameters: a value read as the parameter's own type and checked
against its range, or refused with a clear error, as ``ros2 run ... -p`` refuses it; and a
misspelt argument named, as a node names a misspelt parameter.

Without this, ``ros2 launch stars_ros ranker.launch.py top_k:=abc`` hands the node the
string 'abc' after the packaged params file's 0, and ROS drops the later value of another
type without a word; ``top_kk:=3`` would be set as a launch configuration nobody reads.
ROS-free, so it is tested without launch.
"""
from __future__ import annotations

import difflib
import math
from pathlib import Path
from typing import Iterable, Mapping, Sequence

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


def unknown_arguments(argv: Sequence[str], declared: Iterable[str], launch_file: str) -> list:
    """A warning for each ``name:=value`` of ``argv`` (what ``ros2 launch`` was given after
    the file: launch's ``context.argv``) whose name ``launch_file`` does not declare, with the
    closest declared name when one is close, as ``unknown_parameters`` words it for a node.
    Launch sets every given argument as a configuration, read or not, and checks none
    (ros2/launch#313: an argument may be meant for a file included further down); this
    package's launch files include none, so an undeclared name is a mistake, or, where another
    launch file includes one of them, that file's own argument: a warning, not a refusal."""
    declared = list(declared)
    warnings = []
    for name in dict.fromkeys(argument.split(':=', 1)[0] for argument in argv if ':=' in argument):
        if name in declared:
            continue
        near = difflib.get_close_matches(name, declared, n=1)
        warnings.append(f"launch argument '{name}' is not one of {launch_file}'s: ignored"
                        + (f" (did you mean '{near[0]}'?)" if near else '')
                        + f'; `ros2 launch stars_ros {launch_file} --show-args` lists them')
    return warnings
