"""Yaw and quaternion, the one conversion between them (REP 103: yaw is the rotation about z,
the heading on the floor). ROS-free: every module that reads or writes a quaternion uses it."""
from __future__ import annotations

import math


def yaw_of_quaternion(x: float, y: float, z: float, w: float) -> float:
    """The rotation about z (radians) of quaternion (x, y, z, w); it need not be unit length."""
    return math.atan2(2.0 * (w * z + x * y), w * w + x * x - y * y - z * z)


def quaternion_of_yaw(yaw: float) -> tuple:
    """(x, y, z, w) of a rotation by ``yaw`` radians about z."""
    return 0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0)
