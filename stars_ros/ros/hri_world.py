"""The hri_world node: a scripted ROS4HRI (REP 155) world to try the bridge in, no robot needed.

People stand where the humans of a real SocNav1 scene stand (``source``: a SocNav1 JSONL
file; empty: a generated scene), converted to REP 103 by ``data.frames``; they are tracked
as p1, p2, ... (latched /humans/persons/tracked), recognised (anonymous false), and their
poses go out as TF frames person_<id> in ``base_frame`` where tf2_ros exists, else on
hri/transforms (the bridge's ``pose_source:=topic``); the robot stands at the origin of
``map`` (a static map -> base_frame transform), so the bridge's goals have a frame. A script of ``period`` seconds
loops:

    0 s   p1 engages; p2 and p3 form a group; p1 and p2 gaze at each other
    1/4   an anonymous passer-by ('passer') walks across, engaged; an anonymous 'face_new' engages
    1/2   'face_new' is recognised as p1's alias (an alias merge); p1 disengages, p2 engages
    3/4   the passer-by leaves; p2 disengages

    ros2 run stars_ros hri_world --ros-args -p source:=$STARS_SOCNAV1_ROOT/raw/a.jsonl

``World`` is the publishing half, also used by the tests to drive the same topics.
"""
from __future__ import annotations

import math

import numpy as np
from geometry_msgs.msg import TransformStamped
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Bool, Float32, String

from stars_ros.data import frames
from stars_ros.data.scene_source import random_scene, read_scenes
from stars_ros.hri.people import DISENGAGED, DISENGAGING, ENGAGED
from stars_ros.ros import usage
from stars_ros.ros.spinning import run_node
from stars_ros.ros.unknown_parameters import warn_unknown_overrides
from stars_ros.rotations import quaternion_of_yaw

try:
    from hri_msgs.msg import EngagementLevel, Gaze, Group, IdsList
except ImportError as missing:
    HRI_MSGS_ERROR = f'hri_world needs hri_msgs (ros-jazzy-hri-msgs, ROS4HRI): {missing}'
else:
    HRI_MSGS_ERROR = None

RELIABLE = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)

PARAMETERS = {  # name: (default, description)
    'source': ('', 'SocNav1 JSONL file whose first scene with people places them; empty: a generated scene'),
    'base_frame': ('base_link', 'frame the poses are given in'),
    'period': (40.0, 's the script takes before it starts again'),
    'pose_source': ('auto', 'tf, topic (hri/transforms) or auto: tf where tf2_ros is importable'),
    'seed': (0, 'seed of the generated scene'),
}


class World:
    """Publishes ROS4HRI facts from ``node``: tracked ids (latched), per-person topics
    (anonymous and alias latched), groups, gazes and poses (TF or hri/transforms)."""

    def __init__(self, node: Node, base_frame: str = 'base_link', use_tf: bool = False):
        if HRI_MSGS_ERROR:
            raise ImportError(HRI_MSGS_ERROR)
        self.node, self.base_frame = node, base_frame
        self.tracked = node.create_publisher(IdsList, '/humans/persons/tracked', LATCHED)
        self.groups = node.create_publisher(Group, '/humans/interactions/groups', RELIABLE)
        self.gazes = node.create_publisher(Gaze, '/humans/interactions/gazing', RELIABLE)
        self._people = {}
        if use_tf:
            import tf2_ros  # only where a ROS install provides it
            self._broadcaster = tf2_ros.TransformBroadcaster(node)
            self._send_transform = self._broadcaster.sendTransform
        else:
            topic = node.create_publisher(TransformStamped, 'hri/transforms', RELIABLE)
            self._send_transform = topic.publish

    def _publishers(self, person_id: str) -> dict:
        if person_id not in self._people:
            base, create = f'/humans/persons/{person_id}/', self.node.create_publisher
            self._people[person_id] = {
                'engagement_status': create(EngagementLevel, base + 'engagement_status', RELIABLE),
                'anonymous': create(Bool, base + 'anonymous', LATCHED),
                'alias': create(String, base + 'alias', LATCHED),
                'location_confidence': create(Float32, base + 'location_confidence', RELIABLE)}
        return self._people[person_id]

    def stamp(self, age: float = 0.0):
        return (self.node.get_clock().now() - Duration(nanoseconds=int(age * 1e9))).to_msg()

    def track(self, ids) -> None:
        msg = IdsList(ids=list(ids))
        msg.header.stamp = self.stamp()
        self.tracked.publish(msg)

    def engage(self, person_id: str, level: int) -> None:
        msg = EngagementLevel(level=level)
        msg.header.stamp = self.stamp()
        self._publishers(person_id)['engagement_status'].publish(msg)

    def anonymous(self, person_id: str, anonymous: bool) -> None:
        self._publishers(person_id)['anonymous'].publish(Bool(data=anonymous))

    def alias(self, person_id: str, target: str) -> None:
        self._publishers(person_id)['alias'].publish(String(data=target))

    def confidence(self, person_id: str, value: float) -> None:
        self._publishers(person_id)['location_confidence'].publish(Float32(data=value))

    def group(self, group_id: str, members) -> None:
        msg = Group(group_id=group_id, members=list(members))
        msg.header.stamp = self.stamp()
        self.groups.publish(msg)

    def gaze(self, sender: str, receiver: str) -> None:
        msg = Gaze(sender=sender, receiver=receiver)
        msg.header.stamp = self.stamp()
        self.gazes.publish(msg)

    def pose(self, person_id: str, x: float, y: float, yaw: float, age: float = 0.0, parent: str = '',
             static: bool = False) -> None:
        """person_<id>'s pose in ``parent`` (default base_frame), stamped ``age`` s ago."""
        self.transform(parent or self.base_frame, f'person_{person_id}', x, y, yaw, age, static)

    def transform(self, parent: str, child: str, x: float, y: float, yaw: float, age: float = 0.0,
                  static: bool = False) -> None:
        """``child``'s pose in ``parent``; ``static``: stamped 0, as tf2 gives a static transform."""
        msg = TransformStamped()
        msg.header.frame_id, msg.child_frame_id = parent, child
        if not static:
            msg.header.stamp = self.stamp(age)
        msg.transform.translation.x, msg.transform.translation.y = float(x), float(y)
        r = msg.transform.rotation
        r.x, r.y, r.z, r.w = quaternion_of_yaw(yaw)
        self._send_transform(msg)


def tf2_available() -> bool:
    try:
        import tf2_ros  # noqa: F401
    except ImportError:
        return False
    return True


def scene_people(source: str, seed: int) -> list:
    """(x, y, yaw) in REP 103 metres of the humans of the first scene with at least three
    (``source``), else of a generated one."""
    scenes = read_scenes(source) if source else []
    scene = next((s for s in scenes if len(s.get('humans') or []) >= 3), None)
    rng = np.random.default_rng(seed)
    while scene is None:
        candidate = random_scene(rng)
        scene = candidate if len(candidate['humans']) >= 3 else None
    return [(h.x, h.y, h.yaw) for h in frames.from_socnav(scene).humans]


class ScriptedWorld(Node):
    """Plays the module docstring's script at 10 Hz."""

    def __init__(self, **kwargs):
        super().__init__('hri_world', **kwargs)
        v = {name: self.declare_parameter(name, default, ParameterDescriptor(description=text)).value
             for name, (default, text) in PARAMETERS.items()}
        warn_unknown_overrides(self, 'hri_world', PARAMETERS)
        if not v['period'] > 0 or v['pose_source'] not in ('auto', 'tf', 'topic'):
            raise ValueError("need period > 0 and pose_source in auto, tf, topic")
        use_tf = v['pose_source'] == 'tf' or (v['pose_source'] == 'auto' and tf2_available())
        self.world = World(self, v['base_frame'], use_tf)
        self.people = {f'p{k + 1}': pose for k, pose in enumerate(scene_people(v['source'], v['seed']))}
        self.period, self.started = v['period'], self.get_clock().now().nanoseconds
        self.phase = None
        for person_id in [*self.people, 'face_new']:
            self.world.anonymous(person_id, person_id == 'face_new')
        self.world.anonymous('passer', True)
        self.create_timer(0.1, self._tick)
        self.get_logger().info(f"{len(self.people)} people from {v['source'] or 'a generated scene'}; poses via "
                               f"{'TF' if use_tf else 'hri/transforms'}")

    def _tick(self):
        t = ((self.get_clock().now().nanoseconds - self.started) / 1e9) % self.period / self.period
        phase = int(t * 4)
        passer = 1 <= phase <= 2
        ids = [*self.people, *(['passer', 'face_new'] if passer else [])]
        if phase != self.phase:
            self.phase = phase
            self.world.track(ids)
            self.world.alias('face_new', 'p1' if phase == 2 else '')
        levels = {'p1': ENGAGED if phase in (0, 1) else DISENGAGING, 'p2': ENGAGED if phase == 2 else DISENGAGED,
                  'passer': ENGAGED, 'face_new': ENGAGED}
        for person_id in ids:
            self.world.engage(person_id, levels.get(person_id, DISENGAGED))
            self.world.confidence(person_id, 1.0)
        for person_id, (x, y, yaw) in self.people.items():
            self.world.pose(person_id, x, y, yaw)
        if passer:
            self.world.pose('passer', 3.0 - 6.0 * (t - 0.25) / 0.5, 2.0, -math.pi / 2)
            self.world.pose('face_new', *self.people['p1'])
        self.world.transform('map', self.world.base_frame, 0.0, 0.0, 0.0, static=True)  # the robot stands still
        if {'p2', 'p3'} <= set(self.people):
            self.world.group('g1', ['p2', 'p3'])
        self.world.gaze('p1', 'p2')
        self.world.gaze('p2', 'p1')


def main(args=None):
    if usage.print_help_if_asked('hri_world', __doc__, PARAMETERS, 'ros2 run stars_ros hri_world --ros-args '
                                 '-p source:=$STARS_SOCNAV1_ROOT/raw/a.jsonl', args):
        return
    run_node('hri_world', ScriptedWorld, fatal=(ImportError, ValueError, OSError), args=args)


if __name__ == '__main__':
    main()
