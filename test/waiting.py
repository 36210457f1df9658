"""Bounded waits for conditions nothing notifies a test of: ``stars_ros.waiting``."""
from stars_ros.waiting import wait_for  # noqa: F401
