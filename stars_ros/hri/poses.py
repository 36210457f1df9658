"""Where people are: the seam between the bridge and TF, without ROS.

The bridge asks a pose source for ``lookup(target_frame, source_frame)``: the latest pose of
``source_frame`` in ``target_frame`` (REP 103 metres, yaw in radians) with its stamp, or None
when there is none. In production ``stars_ros.ros.hri_bridge`` wraps a tf2 buffer; where
tf2_ros is absent (and in tests) a ``TransformTable`` holds transforms given to it directly,
one hop each (``parent`` -> ``child``), as geometry_msgs/TransformStamped carries them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

TIMELESS = 2 ** 62  # the stamp of a frame in itself: never stale


@dataclass(frozen=True)
class Pose:
    """A planar pose: ``x``, ``y`` metres, ``yaw`` radians, ``stamp`` ns (when it was true)."""

    x: float
    y: float
    yaw: float
    stamp: int


class PoseSource(Protocol):
    def lookup(self, target_frame: str, source_frame: str) -> Pose | None:
        """The latest pose of ``source_frame`` in ``target_frame``, None if unknown."""


def compose(a: Pose, b: Pose) -> Pose:
    """Pose ``b`` (given in a's frame) in the frame ``a`` is given in; stamp the older one's."""
    c, s = math.cos(a.yaw), math.sin(a.yaw)
    return Pose(a.x + c * b.x - s * b.y, a.y + s * b.x + c * b.y, math.atan2(math.sin(a.yaw + b.yaw),
                math.cos(a.yaw + b.yaw)), min(a.stamp, b.stamp))


class TransformTable:
    """Transforms handed over one by one (the bridge's ``pose_source:=topic`` and the tests):
    the latest of each (parent, child), looked up directly, or inverted."""

    def __init__(self):
        self._latest: dict[tuple, Pose] = {}

    def put(self, parent: str, child: str, pose: Pose) -> None:
        """Keep ``child``'s pose in ``parent``; ValueError for a non-finite one."""
        if not all(math.isfinite(v) for v in (pose.x, pose.y, pose.yaw)):
            raise ValueError(f"transform {parent} -> {child} is not finite ({pose.x}, {pose.y}, yaw {pose.yaw})")
        if not parent or not child or parent == child:
            raise ValueError(f"transform needs two different frames, got '{parent}' -> '{child}'")
        self._latest[(parent, child)] = pose

    def lookup(self, target_frame: str, source_frame: str) -> Pose | None:
        if target_frame == source_frame:
            return Pose(0.0, 0.0, 0.0, TIMELESS)
        direct = self._latest.get((target_frame, source_frame))
        if direct is not None:
            return direct
        inverse = self._latest.get((source_frame, target_frame))
        if inverse is None:
            return None
        c, s = math.cos(inverse.yaw), math.sin(inverse.yaw)
        return Pose(-(c * inverse.x + s * inverse.y), s * inverse.x - c * inverse.y, -inverse.yaw, inverse.stamp)
