"""The hri_bridge's goals for real, on loopback, against a stand-in ranker (the test answers
stars/scene with rankings whose scores it sets): one goal per decision change, in a frame
that does not move with the robot, stamped when decided; hysteresis; the refusal of a robot
frame without the opt-in; Nav2's NavigateToPose (a stand-in server); static person frames;
the /diagnostics warnings; the wait for the ranker.

The 60 s of an unchanged scene run on the bridge's ROS clock (``use_sim_time``, /clock from
the test at five times wall speed), not on wall time."""
import json
import math
import signal
import threading

import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from rclpy.time import Time
from rosgraph_msgs.msg import Clock
from std_msgs.msg import String

from hri_fixtures import hri_msgs  # noqa: F401 - the fixture
from nav2_fixtures import navigate_to_pose  # noqa: F401 - the fixture
from ros_helpers import LATCHED, RELIABLE, RosClient, domain_id, start_node, stop
from stars_ros.hri.people import ENGAGED

pytestmark = pytest.mark.slow  # a bridge process per test
DOMAIN_OFFSET = 17
POSES = {'alice': (1.0, 0.5, math.pi), 'bob': (2.0, -1.0, 0.5)}
ROBOT_IN_MAP = (10.0, 5.0, math.pi / 2)
SIM_STEP, SIM_PERIOD = 0.05, 0.01  # /clock: 0.05 s of ROS time every 0.01 s of wall time


class Rig:
    """A bridge (subprocess) and a client that plays the world (static person frames, both
    people engaged) and, with ``ranker``, a stand-in ranker scoring placements by ``scores``
    (the k-th ranking: ``scores(k)``) for scenes of a served user."""

    def __init__(self, tmp_path, params: dict, ranker: bool = True, sim_time: bool = False, static: bool = True):
        from stars_ros.ros.hri_world import World
        self.domain = domain_id(DOMAIN_OFFSET)
        self.client = RosClient(self.domain, listen=False)
        node = self.client.node
        self.world = World(node, 'base_link', use_tf=False)
        self.static, self.ages = static, {}
        self.scores = lambda k: {'back_50cm': 0.9, 'stay': 0.2}
        self.p_best = None
        self.rankings_sent = 0
        self.lock = threading.Lock()
        self.ranking_pub = None
        self.scenes = []
        node.create_subscription(String, '/stars/scene', self._on_scene, RELIABLE)
        if ranker:
            self.start_ranker()
        self.decisions = self.client.collect('/stars/decision', RELIABLE)
        self.executed = self.client.collect('/stars/executed', RELIABLE)
        self.goals = self.client.collect_messages('/stars/goal', PoseStamped, LATCHED)
        self.diagnostics = self.client.collect_messages('/diagnostics', DiagnosticArray, 100)
        self.sim = 1000.0 if sim_time else None
        if sim_time:
            self.clock = node.create_publisher(Clock, '/clock', 10)
            node.create_timer(SIM_PERIOD, self._tick_clock)
        node.create_timer(0.1, self._publish_world)
        self.log = tmp_path / 'bridge.log'
        self.bridge = start_node('stars_ros.ros.hri_bridge', self.domain, {
            'pose_source': 'topic', 'goal_frame': 'map', 'rate': 2.0, 'max_age': 0.5, 'abstain_below': 0.5,
            'diagnostics_period': 0.5, 'use_sim_time': sim_time, **params}, self.log)

    def start_ranker(self):
        self.ranking_pub = self.client.node.create_publisher(String, '/stars/ranking', RELIABLE)

    def _tick_clock(self):
        with self.lock:
            self.sim += SIM_STEP
            now = Time(nanoseconds=int(self.sim * 1e9))
        self.clock.publish(Clock(clock=now.to_msg()))

    def _publish_world(self):
        self.world.track(list(POSES))
        for person_id, (x, y, yaw) in POSES.items():
            self.world.anonymous(person_id, False)
            self.world.engage(person_id, ENGAGED)
            self.world.pose(person_id, x, y, yaw, age=self.ages.get(person_id, 0.0), static=self.static)
        self.world.transform('map', 'base_link', *ROBOT_IN_MAP, static=True)

    def _on_scene(self, msg):
        scene = json.loads(msg.data)
        with self.lock:
            self.scenes.append(scene)
            if self.ranking_pub is None or 'user_id' not in scene:  # decisions for someone served only:
                return  # the first scenes, before engagement arrives, serve nobody, and a goal for alice would follow
            scores = self.scores(self.rankings_sent)
            self.rankings_sent += 1
        labels = sorted((c['candidate'] for c in scene['candidates']), key=lambda c: -scores.get(c, 0.0))
        ranking = {'scene_id': scene['scene_id'], 'user_id': scene.get('user_id'),
                   'ranking': [{'candidate': c, 'score': scores.get(c, 0.0), 'rank': k + 1}
                               for k, c in enumerate(labels)]}
        if self.p_best is not None:
            ranking['p_first_is_best'] = self.p_best
        self.ranking_pub.publish(String(data=json.dumps(ranking)))

    def wait(self, predicate, timeout: float = 60.0) -> bool:
        return self.client.wait(lambda: self.bridge.poll() is not None or predicate(), timeout) and \
            self.bridge.poll() is None

    def more_decisions(self, count: int, timeout: float = 60.0) -> bool:
        start = len(self.decisions)
        return self.wait(lambda: len(self.decisions) >= start + count, timeout)

    def status(self):
        """The bridge's latest /diagnostics status, or None."""
        for array in reversed(self.client.snapshot(self.diagnostics)):
            for status in array.status:
                if status.name.endswith('hri_bridge'):
                    return status
        return None

    def close(self):
        try:
            assert self.bridge.poll() is None, self.log.read_text()[-3000:]
            assert stop(self.bridge, signal.SIGINT) == 0, self.log.read_text()[-3000:]
        finally:
            if self.bridge.poll() is None:
                self.bridge.kill()
            self.client.close()


@pytest.fixture()
def rig(tmp_path, hri_msgs, request):
    """A rig of its own for each test; ``@pytest.mark.parametrize('rig', [kwargs], indirect=True)`` sets it up."""
    made = Rig(tmp_path, **getattr(request, 'param', {'params': {}}))
    yield made
    made.close()


def _xy(goal: PoseStamped) -> tuple:
    return goal.pose.position.x, goal.pose.position.y


@pytest.mark.parametrize('rig', [{'params': {}, 'sim_time': True}], indirect=True)
def test_an_unchanged_scene_for_60_s_gives_exactly_one_goal(rig):
    assert rig.wait(lambda: bool(rig.goals)), rig.log.read_text()[-3000:]
    with rig.lock:
        first_at = rig.sim
    assert rig.wait(lambda: rig.sim >= first_at + 60.0 and len(rig.decisions) >= 100, 120), len(rig.decisions)
    goals = rig.client.snapshot(rig.goals)
    assert len(goals) == 1, [_xy(g) for g in goals]
    (goal,) = goals
    assert goal.header.frame_id == 'map'
    assert _xy(goal) == (pytest.approx(10.0), pytest.approx(4.5))  # 0.5 m behind the robot at (10, 5, 90 degrees)
    stamp = Time.from_msg(goal.header.stamp).nanoseconds / 1e9
    assert first_at - 2.0 <= stamp <= first_at  # stamped on the bridge's clock when decided, not re-stamped


def test_a_changed_best_placement_gives_one_new_goal(rig):
    assert rig.wait(lambda: bool(rig.goals))
    rig.scores = lambda k: {'back_50cm': 0.2, 'stay': 0.9}
    assert rig.wait(lambda: len(rig.goals) >= 2)
    assert rig.more_decisions(6)
    goals = rig.client.snapshot(rig.goals)
    assert len(goals) == 2
    assert _xy(goals[1]) == (pytest.approx(10.0), pytest.approx(5.0))  # 'stay': where the robot is


def test_near_equal_placements_do_not_alternate(rig):
    rig.scores = lambda k: {'back_50cm': 0.61, 'stay': 0.60} if k % 2 else {'back_50cm': 0.60, 'stay': 0.61}
    assert rig.wait(lambda: bool(rig.goals))
    assert rig.more_decisions(10)
    assert len(rig.client.snapshot(rig.goals)) == 1
    assert {d['candidate'] for d in rig.decisions} == {'back_50cm', 'stay'}  # the rankings did alternate


def test_a_goal_frame_that_moves_with_the_robot_is_refused_at_start(tmp_path, hri_msgs):
    log = tmp_path / 'bridge.log'
    bridge = start_node('stars_ros.ros.hri_bridge', domain_id(DOMAIN_OFFSET),
                        {'pose_source': 'topic', 'goal_frame': 'base_link'}, log)
    try:
        assert bridge.wait(timeout=60) == 1
    finally:
        if bridge.poll() is None:
            bridge.kill()
    assert "goal_frame 'base_link' moves with the robot" in log.read_text() and 'goal_in_robot_frame' in \
        log.read_text()


@pytest.mark.parametrize('rig', [{'params': {'goal_frame': 'base_link', 'goal_in_robot_frame': True}}],
                         indirect=True)
def test_a_goal_in_the_robots_frame_with_the_opt_in(rig):
    assert rig.wait(lambda: bool(rig.goals))
    assert rig.goals[0].header.frame_id == 'base_link'
    assert _xy(rig.goals[0]) == (pytest.approx(-0.5), pytest.approx(0.0))


@pytest.mark.parametrize('rig', [{'params': {'max_age': 0.2}}], indirect=True)
def test_static_person_frames_are_in_the_scene_and_a_goal_is_sent(rig):
    """Person frames stamped 0 (static, as tf2 gives /tf_static) stay in the scene long past max_age."""
    assert rig.wait(lambda: bool(rig.goals) and len(rig.scenes) >= 4)
    for scene in rig.scenes[-3:]:
        stay = next(c['graph'] for c in scene['candidates'] if c['candidate'] == 'stay')
        assert len(stay['humans']) == 2
    assert rig.wait(lambda: rig.status() is not None and rig.status().values)
    values = {kv.key: kv.value for kv in rig.status().values}
    assert values['in_scene'] == '2' and 'left_out.stale' not in values


@pytest.mark.parametrize('rig', [{'params': {}, 'static': False}], indirect=True)
def test_diagnostics_warn_when_everyone_is_left_out(rig):
    rig.ages.update(alice=5.0, bob=5.0)  # dynamic frames older than max_age: stale

    def warned():
        status = rig.status()
        return status is not None and status.level == DiagnosticStatus.WARN and \
            '2 people tracked, none in the scene (left out: stale 2)' in status.message
    assert rig.wait(warned), rig.status()


@pytest.mark.parametrize('rig', [{'params': {}, 'ranker': False}], indirect=True)
def test_the_bridge_waits_for_the_ranker_and_says_so(rig):
    def waiting():
        status = rig.status()
        return status is not None and 'waiting for the ranker' in status.message and \
            {kv.key: kv.value for kv in status.values}.get('ranker') == 'waiting'
    assert rig.wait(waiting)
    assert rig.wait(lambda: len(rig.diagnostics) >= 4)  # two more periods: still no scene
    assert rig.scenes == []
    rig.start_ranker()
    assert rig.wait(lambda: bool(rig.scenes) and bool(rig.goals))
    assert rig.wait(lambda: 'waiting' not in rig.status().message)


@pytest.mark.parametrize('rig', [{'params': {'navigate_to_pose': 'navigate_to_pose'}}], indirect=True)
def test_navigate_to_pose_goal_cancel_on_abstain_and_result_as_executed(rig, navigate_to_pose):
    from rclpy.action import ActionServer, CancelResponse
    from rclpy.task import Future
    received, cancelled, finish = [], [], {}

    async def execute(handle):
        done = finish.setdefault(id(handle), Future())
        received.append(handle.request.pose)
        outcome = await done
        if outcome == 'cancel':
            handle.canceled()
        else:
            handle.succeed()
        return navigate_to_pose.Result()

    def cancel(handle):
        cancelled.append(handle.request.pose)
        finish.setdefault(id(handle), Future()).set_result('cancel')
        return CancelResponse.ACCEPT

    rig.p_best = 0.1  # abstain until the server is up
    server = ActionServer(rig.client.node, navigate_to_pose, 'navigate_to_pose', execute, cancel_callback=cancel)
    try:
        rig.p_best = 0.9
        assert rig.wait(lambda: bool(received)), rig.log.read_text()[-3000:]
        assert received[0].header.frame_id == 'map' and _xy(received[0]) == (pytest.approx(10.0), pytest.approx(4.5))
        rig.p_best = 0.1  # abstain: the goal followed is cancelled
        assert rig.wait(lambda: bool(cancelled)), rig.log.read_text()[-3000:]
        rig.p_best = 0.9  # the abstain ends: a goal again, which succeeds
        assert rig.wait(lambda: len(received) >= 2)
        (pending,) = [f for f in finish.values() if not f.done()]
        pending.set_result('succeed')
        assert rig.wait(lambda: bool(rig.executed)), rig.log.read_text()[-3000:]
        executed = rig.executed[0]
        assert executed['candidate'] == 'back_50cm' and executed['person_id'] in POSES
        assert executed['scene_id'].startswith('hri-')
    finally:
        server.destroy()
