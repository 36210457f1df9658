"""The scene_publisher node: feeds test scenes to the ranker at a set rate, for one user.

Scenes come from a JSONL file (SocNav1 lines as they are) or are generated at random;
with ``placements`` > 0 each message asks to rank that many alternative robot placements
of the scene instead of the model's actions. Publishes ``stars/scene`` and logs what it
published at most every 5 s. A relative ``source`` is taken from the folder the node starts in.

    ros2 run stars_ros scene_publisher --ros-args -p source:=$STARS_SOCNAV1_ROOT/raw/a.jsonl -p user_id:=a -p rate:=5.0
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from stars_ros.errors import DataError
from stars_ros.data.scene_source import PLACEMENTS, random_scene, read_scenes, scene_request
from stars_ros.ros import usage
from stars_ros.ros.spinning import run_node
from stars_ros.ros.unknown_parameters import warn_unknown_overrides

LOG_PERIOD = 5.0  # seconds between two lines saying what was published

PARAMETERS = {  # name: (default, description)
    'source': ('', 'JSONL file of scenes (relative: to the folder the node starts in); empty: random scenes'),
    'user_id': ('', 'user id put in every request; empty: none'),
    'rate': (2.0, 'requests per second'),
    'count': (0, 'requests to publish before exiting; 0: no end'),
    'placements': (0, f'0: rank the actions; 1..{len(PLACEMENTS)}: rank that many robot placements'),
    'scene_id_prefix': ('scene-', 'scene ids are this prefix + a counter (unless keep_identifiers)'),
    'keep_identifiers': (False, "publish each scene under its own identifier (a SocNav1 line's; random scenes: "
                         'scene_id_prefix + counter), so feedback can name a scene found in the source file'),
    'seed': (0, 'seed of the random scenes and of the file order'),
    'wait_for_subscribers': (30.0, 'seconds to wait for a subscriber first'),
}


class ScenePublisher(Node):
    """Publishes one scene request per timer tick; stops after ``count`` when it is set."""

    def __init__(self, **kwargs):
        super().__init__('scene_publisher', **kwargs)
        value = {name: self.declare_parameter(name, default, ParameterDescriptor(description=text)).value
                 for name, (default, text) in PARAMETERS.items()}
        warn_unknown_overrides(self, 'scene_publisher', PARAMETERS)
        self.source, self.user_id, rate = value['source'], value['user_id'], value['rate']
        self.count, self.placements, self.prefix = value['count'], value['placements'], value['scene_id_prefix']
        self.keep_identifiers = value['keep_identifiers']
        seed, wait = value['seed'], value['wait_for_subscribers']
        if not rate > 0 or self.count < 0 or not 0 <= self.placements <= len(PLACEMENTS):
            raise ValueError(f'need rate > 0, count >= 0 and placements in 0..{len(PLACEMENTS)}')
        self.rng = np.random.default_rng(seed)
        if self.source:
            self.source = str(Path(self.source).expanduser().absolute())
            if not Path(self.source).is_file():
                raise DataError(f'source {self.source}: no such file')
        self.scenes = read_scenes(self.source) if self.source else None
        self.sent = 0
        self.publisher = self.create_publisher(String, 'stars/scene',
                                               QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
        deadline = time.monotonic() + wait
        while self.publisher.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.1)
        self.timer = self.create_timer(1.0 / rate, self._tick)

    def _next_scene(self) -> dict:
        if self.scenes is None:
            return random_scene(self.rng)
        return self.scenes[self.sent % len(self.scenes)]

    def _tick(self):
        if self.count and self.sent >= self.count:
            self.timer.cancel()
            self.publisher.wait_for_all_acked(Duration(seconds=5))
            self.get_logger().info(f'published {self.sent} scene requests')
            raise SystemExit(0)
        scene = self._next_scene()
        scene_id = f'{self.prefix}{self.sent}'
        if self.keep_identifiers and 'identifier' in scene:
            scene_id = str(scene['identifier'])
        payload = scene_request(scene_id, scene, self.user_id or None, self.placements)
        self.publisher.publish(String(data=json.dumps(payload)))
        self.sent += 1
        self.get_logger().info(f"published {scene_id}{f' for user {self.user_id}' if self.user_id else ''} on "
                               f'{self.publisher.topic_name} ({self.sent} in all)', throttle_duration_sec=LOG_PERIOD)


def main(args=None):
    if usage.print_help_if_asked('scene_publisher', __doc__, PARAMETERS, 'ros2 run stars_ros scene_publisher '
                                 '--ros-args -p source:=$STARS_SOCNAV1_ROOT/raw/a.jsonl -p user_id:=a -p rate:=5.0 '
                                 '-p count:=10', args):
        return
    run_node('scene_publisher', ScenePublisher, fatal=(DataError, OSError, ValueError), args=args,
             ends=(SystemExit,))  # _tick's end once count requests are out


if __name__ == '__main__':
    main()
