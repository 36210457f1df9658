"""The replay node: plays a recorded bag back onto live topics, at recorded or scaled speed.

Re-running a session against a new checkpoint is: start the ranker with that checkpoint,
then replay the old bag's ``/stars/scene`` and ``/stars/user_id``; the new rankings are
recorded by the ranker as usual. Each topic is published with the QoS it was recorded
with (so user ids stay latched) and can be remapped like any topic. It logs what it played
at most every 5 s.

    ros2 run stars_ros replay --ros-args -p bag:=$HOME/.ros/stars_ros/records/stars_2026_01_01-12_00_00 -p rate:=2.0
"""
from __future__ import annotations

import threading
import time

from mcap.exceptions import McapError
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from stars_ros.recording.bag import bag_topics, read_messages
from stars_ros.ros import usage
from stars_ros.ros.spinning import run_node
from stars_ros.ros.unknown_parameters import warn_unknown_overrides

LOG_PERIOD = 5.0  # seconds between two lines saying what was played

PARAMETERS = {  # name: (default, description)
    'bag': ('', 'bag folder or MCAP file to play'),
    'topics': (['/stars/scene', '/stars/user_id'], 'recorded topics to play; [""] plays them all'),
    'rate': (1.0, 'speed factor: 1 recorded speed, 2 twice as fast, 0 as fast as possible'),
    'wait_for_subscribers': (30.0, 'seconds to wait for a subscriber on every played topic'),
}


def _qos(profile: dict) -> QoSProfile:
    return QoSProfile(depth=max(int(profile.get('depth', 10)), 1000),
                      reliability=ReliabilityPolicy.BEST_EFFORT if profile.get('reliability') == 'best_effort'
                      else ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if profile.get('durability') == 'transient_local'
                      else DurabilityPolicy.VOLATILE)


class Replay(Node):
    """Publishes the chosen topics of ``bag`` in recorded order and timing (scaled by ``rate``)."""

    def __init__(self, **kwargs):
        super().__init__('replay', **kwargs)
        value = {name: self.declare_parameter(name, default, ParameterDescriptor(description=text)).value
                 for name, (default, text) in PARAMETERS.items()}
        warn_unknown_overrides(self, 'replay', PARAMETERS)
        self.bag, self.wanted = value['bag'], list(value['topics'])
        self.rate, self.wait = value['rate'], value['wait_for_subscribers']
        if not self.bag:
            raise ValueError('set the bag parameter: -p bag:=PATH')
        if self.rate < 0:
            raise ValueError('rate must be >= 0')
        recorded = bag_topics(self.bag)
        topics = list(recorded) if self.wanted in ([], ['']) else self.wanted
        missing = [t for t in topics if t not in recorded]
        if missing:
            self.get_logger().warning(f'not in the bag, not played: {missing}; it holds {list(recorded)}')
        self._outputs = {t: self.create_publisher(String, t, _qos(recorded[t])) for t in topics if t in recorded}
        self._stopped = threading.Event()  # a signal, or any other end of ROS, stops the playing
        self.context.on_shutdown(self._stopped.set)

    def play(self) -> int:
        """Publish everything, or until ROS shuts down; returns the number of messages played."""
        deadline = time.monotonic() + self.wait
        while time.monotonic() < deadline and not all(p.get_subscription_count() for p in self._outputs.values()):
            if self._stopped.wait(0.1):
                return 0
        played, first, start = 0, None, time.monotonic()
        for topic, text, log_time in read_messages(self.bag, list(self._outputs)):
            if self.rate > 0:
                first = log_time if first is None else first
                delay = start + (log_time - first) / 1e9 / self.rate - time.monotonic()
                if delay > 0 and self._stopped.wait(delay):
                    return played
            if self._stopped.is_set():
                return played
            self._outputs[topic].publish(String(data=text))
            played += 1
            self.get_logger().info(f'played a message on {self._outputs[topic].topic_name} ({played} in all)',
                                   throttle_duration_sec=LOG_PERIOD)
        for publisher in self._outputs.values():
            publisher.wait_for_all_acked(Duration(seconds=5))
        self.get_logger().info(f'replayed {played} messages from {self.bag}')
        return played


def main(args=None):
    if usage.print_help_if_asked('replay', __doc__, PARAMETERS, 'ros2 run stars_ros replay --ros-args '
                                 '-p bag:=$HOME/.ros/stars_ros/records/stars_2026_01_01-12_00_00 -p rate:=2.0', args):
        return
    run_node('replay', Replay, Replay.play, (McapError, OSError, ValueError), args)


if __name__ == '__main__':
    main()
