"""Find files the package ships in share/stars_ros (schemas, configs, models).

The same file can live in several places: beside the source tree (a checkout), under a
sourced workspace's ``$AMENT_PREFIX_PATH/share/stars_ros``, under
``<prefix>/share/stars_ros`` (``pip install``) and under a colcon install prefix
(``install/stars_ros/share/stars_ros``, reached by walking up from this module).
"""
import os
import sys
from pathlib import Path

from stars_ros.errors import CheckpointError

PACKAGE = 'stars_ros'
DEFAULT_CHECKPOINT = 'models/socnav1_gat_stars.pt'


def _candidate_roots():
    here = Path(__file__).resolve().parent
    override = os.environ.get('STARS_ROS_SHARE')
    if override:
        yield Path(override)
    yield here.parent  # source checkout: <repo>/msg_schemas
    for prefix in filter(None, os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep)):
        yield Path(prefix) / 'share' / PACKAGE  # a sourced ROS workspace
    yield Path(sys.prefix) / 'share' / PACKAGE
    for parent in here.parents:  # colcon: <prefix>/lib/pythonX.Y/site-packages/stars_ros
        yield parent / 'share' / PACKAGE


def share_path(relative: str) -> Path:
    """Return the installed or checked-out path of ``relative`` (e.g. ``msg_schemas/x.json``)."""
    tried = []
    for root in _candidate_roots():
        path = root / relative
        if path.exists():
            return path
        tried.append(str(path))
    raise FileNotFoundError(f'{relative} not found; looked in: ' + ', '.join(tried))


def resolve_checkpoint(value: str) -> str:
    """A checkpoint parameter or option as a path: the packaged ``DEFAULT_CHECKPOINT`` when
    it is empty."""
    if value:
        return value
    try:
        return str(share_path(DEFAULT_CHECKPOINT))
    except FileNotFoundError as error:
        raise CheckpointError(f'no checkpoint given and the packaged default is missing ({error}); '
                              'pass --ros-args -p checkpoint:=PATH') from None
