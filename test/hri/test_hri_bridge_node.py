"""The hri_bridge node for real, on loopback, with the ranker and the scripted world's
publishing half (``hri_world.World``) on the stand-in hri_msgs: who is served, the scene's
positions, stale poses, privacy, goals, implicit outcomes, bad input; and the real TF path
where tf2_ros is importable."""
import json
import math
import signal

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from std_msgs.msg import String

from hri_fixtures import hri_msgs  # noqa: F401 - the fixture
from ros_helpers import LATCHED, RELIABLE, RosClient, domain_id, running_ranker, start_node, stop, stored_feedback
from stars_ros import recording
from stars_ros.data import frames
from stars_ros.hri.people import DISENGAGED, ENGAGED
from stars_ros.hri.scene import placement_offset

pytestmark = pytest.mark.slow  # real nodes, a ranker and a bridge for each test
DOMAIN_OFFSET = 15
PROBE = {'scene_id': 'probe', 'graph': {'humans': [{'id': 1, 'xPos': 0.0, 'yPos': 100.0, 'orientation': 0.0}],
                                        'objects': [], 'links': [],
                                        'room': [[-300, -300], [300, -300], [300, 300], [-300, 300], [-300, -300]]}}
ROBOT_IN_MAP = (4.0, -2.0, math.pi / 2)
POSES = {'alice': (1.0, 0.5, math.pi), 'bob': (2.0, -1.0, 0.5), 'tmp': (1.5, 1.5, -1.0)}


class Loop:
    """Ranker + bridge (subprocesses) and a client that plays the world and listens;
    ``bridge_params`` are added to the bridge's own."""

    def __init__(self, tmp_path, hri_msgs, bridge_params=None):
        self.domain = domain_id(DOMAIN_OFFSET)
        self.record = tmp_path / 'record'
        self.ranker_log_path = tmp_path / 'ranker.log'
        self._ranker = running_ranker(self.domain, {'record_folder': str(self.record)}, self.ranker_log_path, PROBE)
        self.ranker, self.client = self._ranker.__enter__()
        self.bridge = None
        try:
            self._start(tmp_path, bridge_params or {})
        except BaseException:  # a half-made loop leaves no ranker behind to answer later tests on its domain
            self.close()
            raise

    def _start(self, tmp_path, bridge_params):
        from stars_ros.ros.hri_world import World
        node = self.client.node
        self.world = World(node, 'base_link', use_tf=False)
        self.poses = dict(POSES)
        self.ages, self.levels = {}, {}
        node.create_timer(0.1, self._publish_state)
        self.user_ids = self.client.collect_messages('/stars/user_id', String, LATCHED)
        self.served = self.client.collect('/stars/served_person', LATCHED)
        self.scenes = self.client.collect('/stars/scene', RELIABLE)
        self.feedback = self.client.collect('/stars/feedback', RELIABLE)
        self.decisions = self.client.collect('/stars/decision', RELIABLE)
        self.goals = self.client.collect_messages('/stars/goal', PoseStamped, LATCHED)
        self.diagnostics = self.client.collect_messages('/diagnostics', DiagnosticArray, 100)
        self.executed = node.create_publisher(String, '/stars/executed', RELIABLE)
        self.person_feedback = node.create_publisher(String, '/stars/person_feedback', RELIABLE)
        self.bridge = start_node('stars_ros.ros.hri_bridge', self.domain, {
            'pose_source': 'topic', 'goal_frame': 'map', 'rate': 4.0, 'max_age': 1.0, 'abstain_below': 0.0,
            'outcome_window': 1.0, 'diagnostics_period': 0.5, **bridge_params}, tmp_path / 'bridge.log')
        self.bridge_log = tmp_path / 'bridge.log'
        self.world.track(list(POSES))
        for person_id in ('alice', 'bob'):
            self.world.anonymous(person_id, False)
        self.world.anonymous('tmp', True)
        assert self.client.wait(lambda: node.count_subscribers('/humans/persons/tmp/engagement_status') > 0, 60)

    def _publish_state(self):
        """Poses and engagement at 10 Hz, as a person manager publishes them."""
        for person_id, (x, y, yaw) in list(self.poses.items()):
            self.world.pose(person_id, x, y, yaw, age=self.ages.get(person_id, 0.0))
        for person_id, level in list(self.levels.items()):
            self.world.engage(person_id, level)
        self.world.transform('map', 'base_link', *ROBOT_IN_MAP)

    def engage(self, levels: dict):
        self.levels.update(levels)

    def wait_user(self, user_id: str, timeout: float = 30.0) -> bool:
        return self.client.wait(lambda: bool(self.user_ids) and self.user_ids[-1].data == user_id, timeout)

    def status(self):
        """The bridge's latest /diagnostics status values, as a dict."""
        for array in reversed(self.diagnostics):
            for status in array.status:
                if status.name.endswith('hri_bridge'):
                    return {kv.key: kv.value for kv in status.values}
        return {}

    def details(self, kind: str) -> list:
        """Every detail of ``kind`` the bridge's /diagnostics have given (``latest.<kind>``)."""
        return [kv.value for array in self.client.snapshot(self.diagnostics) for status in array.status
                if status.name.endswith('hri_bridge') for kv in status.values if kv.key == f'latest.{kind}']

    def ranker_status(self):
        """The ranker's latest /diagnostics status values, as a dict."""
        for array in reversed(self.client.snapshot(self.client.diagnostics)):
            for status in array.status:
                if status.name.endswith(': ranker'):
                    return {kv.key: kv.value for kv in status.values}
        return {}

    def ranker_log(self) -> str:
        return self.ranker_log_path.read_text()[-3000:]

    def close(self):
        try:
            if self.bridge is not None:
                assert self.bridge.poll() is None, 'the bridge died during the tests'
                assert stop(self.bridge, signal.SIGINT) == 0, self.bridge_log.read_text()[-3000:]
        finally:
            if self.bridge is not None and self.bridge.poll() is None:
                self.bridge.kill()
            self._ranker.__exit__(None, None, None)


@pytest.fixture()
def loop(tmp_path, hri_msgs):
    """A loop of its own for each test: people, aliases and stored feedback start as ``POSES`` says."""
    running = Loop(tmp_path, hri_msgs)
    yield running
    running.close()


def test_the_served_user_follows_engagement_and_aliases(loop):
    loop.engage({'alice': ENGAGED, 'bob': DISENGAGED, 'tmp': DISENGAGED})
    assert loop.wait_user('alice')
    loop.engage({'bob': ENGAGED})  # farther than alice, who stays served
    loop.engage({'alice': DISENGAGED})
    assert loop.wait_user('bob')
    loop.engage({'bob': DISENGAGED, 'tmp': ENGAGED})
    assert loop.wait_user('')  # anonymous: no user id, the population prior
    anonymous_scenes = len(loop.scenes)
    assert loop.client.wait(lambda: len(loop.scenes) > anonymous_scenes, 10)
    assert 'user_id' not in loop.scenes[-1]
    loop.world.alias('tmp', 'alice')
    assert loop.wait_user('alice')


def _positions(scene: dict) -> list:
    """(x, y) in metres, REP 103, to the centimetre, of the humans of a scene request's 'stay' candidate."""
    stay = next(c['graph'] for c in scene['candidates'] if c['candidate'] == 'stay')
    return sorted((round(h.x, 2), round(h.y, 2)) for h in frames.from_socnav(stay).humans)


def _wanted(people) -> list:
    return sorted((round(x, 2), round(y, 2)) for pid, (x, y, _) in POSES.items() if pid in people)


def test_scene_positions_match_the_poses_to_a_centimetre(loop):
    count = len(loop.scenes)
    assert loop.client.wait(lambda: len(loop.scenes) > count + 1, 30)
    got, want = _positions(loop.scenes[-1]), _wanted(POSES)  # everyone tracked, the anonymous 'tmp' too
    assert len(got) == len(want)
    for (gx, gy), (wx, wy) in zip(got, want):
        assert abs(gx - wx) <= 0.01 and abs(gy - wy) <= 0.01


def test_a_stale_pose_is_left_out_and_counted(loop):
    loop.ages['bob'] = 5.0
    count = len(loop.scenes)
    assert loop.client.wait(lambda: len(loop.scenes) > count and _positions(loop.scenes[-1]) == _wanted(
        ['alice', 'tmp']), 15)
    assert loop.client.wait(lambda: int(loop.status().get('left_out.stale', 0)) > 0, 10)


def test_an_anonymous_persons_feedback_is_not_stored(loop):
    loop.world.track(['alice', 'bob', 'passer'])
    loop.world.anonymous('passer', True)
    loop.poses['passer'] = (2.5, 0.0, 0.0)
    node = loop.client.node  # the bridge follows 'passer' once it has taken the new tracked list
    assert loop.client.wait(lambda: node.count_subscribers('/humans/persons/passer/engagement_status') > 0, 30)
    ranked = len(loop.client.rankings)  # feedback on a scene of the bridge the ranker has ranked
    assert loop.client.wait(lambda: any(r['scene_id'].startswith('hri-') for r in loop.client.rankings[ranked:]), 30)
    scene_id = next(r['scene_id'] for r in loop.client.snapshot(loop.client.rankings)[ranked:]
                    if r['scene_id'].startswith('hri-'))
    message = {'scene_id': scene_id, 'candidate': 'stay', 'score': 0.9}
    loop.person_feedback.publish(String(data=json.dumps({**message, 'person_id': 'passer'})))
    loop.person_feedback.publish(String(data=json.dumps({**message, 'person_id': 'alice', 'score': 0.1})))
    bag = next(loop.record.rglob('*.mcap')).parent
    assert loop.client.wait(lambda: any(f['user_id'] == 'alice' for f in stored_feedback(bag)), 30), (
        loop.status(), loop.ranker_status(), loop.feedback[-3:], loop.client.errors[-3:], loop.ranker_log())
    assert [f['user_id'] for f in stored_feedback(bag)] == ['alice'], stored_feedback(bag)
    assert not any(f['user_id'] == 'passer' for f in loop.feedback)
    assert loop.client.wait(lambda: int(loop.status().get('problems.anonymous_dropped', 0)) >= 1, 30), loop.status()


def _ranked_bridge_scene(loop) -> str:
    """The id of a scene of the bridge that the ranker has ranked (feedback names one)."""
    ranked = len(loop.client.rankings)
    assert loop.client.wait(lambda: any(r['scene_id'].startswith('hri-') for r in loop.client.rankings[ranked:]), 30)
    return next(r['scene_id'] for r in loop.client.snapshot(loop.client.rankings)[ranked:]
                if r['scene_id'].startswith('hri-'))


def test_under_store_policy_consented_only_people_on_the_list_are_relayed(tmp_path, hri_msgs):
    """bob is recognised but not on the consent list: his rating never reaches stars/feedback
    while alice's (on consent_file) does, and the refusal does not name him; stars/served_person
    tells the feedback page his answers are not kept. Once the latched stars/consent lists him,
    his next rating is relayed, and stars/served_person says so."""
    consent_file = tmp_path / 'consent.txt'
    consent_file.write_text('alice\n')
    loop = Loop(tmp_path, hri_msgs, {'store_policy': 'consented', 'consent_file': str(consent_file)})
    try:
        message = {'scene_id': _ranked_bridge_scene(loop), 'candidate': 'stay', 'score': 0.9}
        loop.engage({'bob': ENGAGED})

        def serves_bob(kept):
            return loop.client.wait(lambda: {'person_id': 'bob', 'anonymous': False, 'kept': kept}
                                    in loop.client.snapshot(loop.served), 30)
        assert serves_bob(kept=False), loop.client.snapshot(loop.served)
        loop.person_feedback.publish(String(data=json.dumps({**message, 'person_id': 'bob'})))
        loop.person_feedback.publish(String(data=json.dumps({**message, 'person_id': 'alice'})))
        assert loop.client.wait(lambda: any(f['user_id'] == 'alice' for f in loop.feedback), 30), loop.status()
        assert not any(f['user_id'] == 'bob' for f in loop.feedback)  # published before alice's, in order
        assert loop.client.wait(lambda: loop.details('consent'), 30), loop.status()
        assert not any('bob' in detail for detail in loop.details('consent')), loop.details('consent')
        consent = loop.client.node.create_publisher(String, '/stars/consent', LATCHED)
        consent.publish(String(data=json.dumps({'consented': ['bob']})))
        assert loop.client.wait(lambda: '1 person(s) from stars/consent' in loop.bridge_log.read_text(), 30)
        assert serves_bob(kept=True), loop.client.snapshot(loop.served)
        loop.person_feedback.publish(String(data=json.dumps({**message, 'person_id': 'bob', 'score': 0.2})))
        assert loop.client.wait(lambda: any(f['user_id'] == 'bob' for f in loop.feedback), 30), loop.status()
    finally:
        loop.close()


def test_the_best_placement_is_a_pose_stamped_goal_in_the_navigation_frame(loop):
    assert loop.client.wait(lambda: bool(loop.goals) and bool(loop.decisions), 30)
    decision = next(d for d in reversed(loop.decisions) if 'goal' in d)
    goal = next(g for g in reversed(loop.goals) if abs(g.pose.position.x - decision['goal']['x']) < 1e-9)
    assert goal.header.frame_id == 'map'
    dx, dy = placement_offset(decision['candidate'])
    rx, ry, ryaw = ROBOT_IN_MAP
    assert goal.pose.position.x == pytest.approx(rx + math.cos(ryaw) * dx - math.sin(ryaw) * dy)
    assert goal.pose.position.y == pytest.approx(ry + math.sin(ryaw) * dx + math.cos(ryaw) * dy)
    assert {'score', 'score_sd', 'p_first_is_best', 'abstain'} <= set(decision)


def _same_place(a: PoseStamped, b: PoseStamped, metres: float = 0.25, radians: float = 0.35) -> bool:
    """Within the bridge's default goal_position_tolerance and goal_yaw_tolerance."""
    def yaw(goal):
        q = goal.pose.orientation
        return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
    turn = abs(math.atan2(math.sin(yaw(a) - yaw(b)), math.cos(yaw(a) - yaw(b))))
    return math.hypot(a.pose.position.x - b.pose.position.x, a.pose.position.y - b.pose.position.y) <= metres \
        and turn <= radians


def test_as_the_served_person_leaves_their_goal_is_cancelled_and_not_sent_again_for_nobody(loop):
    loop.engage({'alice': ENGAGED, 'bob': DISENGAGED, 'tmp': DISENGAGED})
    assert loop.wait_user('alice')
    decided = len(loop.decisions)
    assert loop.client.wait(lambda: len(loop.decisions) > decided + 6, 30), loop.status()
    cancelled, sent = int(loop.status().get('goals_cancelled', 0)), len(loop.goals)
    followed = loop.goals[-1]  # alice's
    loop.engage({'alice': DISENGAGED})
    assert loop.wait_user('')
    assert loop.client.wait(lambda: int(loop.status().get('goals_cancelled', 0)) > cancelled, 30), loop.status()
    decided = len(loop.decisions)
    assert loop.client.wait(lambda: len(loop.decisions) > decided + 8, 30), loop.status()
    assert not [goal for goal in loop.client.snapshot(loop.goals)[sent:] if _same_place(goal, followed)]


def test_implicit_outcomes_move_the_next_ranking_and_are_in_the_bag(loop):
    loop.engage({'alice': ENGAGED})
    assert loop.wait_user('alice')
    before = len(loop.client.rankings)
    assert loop.client.wait(lambda: any(r['user_id'] == 'alice' for r in loop.client.rankings[before:]), 15)
    first = next(r for r in loop.client.rankings[before:] if r['user_id'] == 'alice')
    known = first.get('personalised_from', 0)  # alice's relayed rating, earlier
    for entry in first['ranking'][:3]:
        loop.executed.publish(String(data=json.dumps({'scene_id': first['scene_id'],
                                                      'candidate': entry['candidate']})))
    assert loop.client.wait(lambda: sum(bool(f.get('implicit')) for f in loop.feedback) >= 3, 15)
    assert loop.client.wait(lambda: any(r.get('personalised_from', 0) >= known + 3 and r['user_id'] == 'alice'
                                        for r in loop.client.rankings), 30)
    later = next(r for r in reversed(loop.client.rankings) if r.get('personalised_from', 0) >= known + 3)
    scores = {e['candidate']: e['score'] for e in first['ranking']}
    assert any(abs(e['score'] - scores[e['candidate']]) > 1e-6 for e in later['ranking'])
    bag = next(loop.record.rglob('*.mcap')).parent
    assert loop.client.wait(lambda: sum(bool(f.get('implicit')) for f in stored_feedback(bag)) >= 3, 30)
    assert all(f['user_id'] == 'alice' and f['score'] == 1.0 for f in stored_feedback(bag) if f.get('implicit'))

    def implicit_in_the_bag():  # the log of record, as the recorder has flushed it so far (the file is open)
        found = [json.loads(text) for path in recording.bag_files(bag)
                 for topic, text, _ in recording.salvage_messages(path)[0] if topic == '/stars/feedback']
        return [f for f in found if f.get('implicit')]
    assert loop.client.wait(lambda: len(implicit_in_the_bag()) >= 3, 30)
    assert sorted(map(json.dumps, implicit_in_the_bag())) == sorted(
        json.dumps(f) for f in stored_feedback(bag) if f.get('implicit'))


def test_bad_input_is_diagnosed_and_the_bridge_keeps_running(loop):
    loop.world.track(['alice', 'bob', 'never'])  # 'never': a frame that never arrives
    loop.world.engage('ghost', ENGAGED)  # not tracked
    loop.world.pose('nan', math.nan, 0.0, 0.0)
    loop.world.group('g', ['alice', 'stranger'])
    loop.executed.publish(String(data='{not json'))

    def diagnosed():
        loop.world.engage('ghost', ENGAGED)  # again, once the bridge's scan has found the topic
        status = loop.status()
        return all(int(status.get(key, 0)) > 0 for key in (
            'problems.untracked', 'problems.non_finite_pose', 'left_out.no_pose', 'problems.unknown_id',
            'problems.bad_executed'))
    assert loop.client.wait(diagnosed, 30), loop.status()
    count = len(loop.scenes)
    assert loop.client.wait(lambda: len(loop.scenes) > count, 10)  # still serving
    assert loop.bridge.poll() is None


@pytest.mark.socnav1
def test_the_scripted_world_drives_the_bridge(hri_msgs, socnav1_root, tmp_path):
    """hri_world's script (people from a real SocNav1 scene) through the bridge: p1 is served,
    then p2, and the scene holds the scene's people."""
    domain = domain_id(16)  # after test_state_node's, in turn (as domain 7 is shared)
    client = RosClient(domain, listen=False)
    users = client.collect_messages('/stars/user_id', String, LATCHED)
    scenes = client.collect('/stars/scene', RELIABLE)
    processes = [start_node('stars_ros.ros.hri_world', domain, {'source': socnav1_root / 'raw' / 'a.jsonl',
                                                                  'period': 8.0, 'pose_source': 'topic'},
                            tmp_path / 'world.log'),
                 start_node('stars_ros.ros.hri_bridge', domain, {'pose_source': 'topic', 'wait_for_ranker': False},
                            tmp_path / 'bridge.log')]
    try:
        def served_and_seen():  # both people served, and a scene that holds at least three of the scene's people
            humans = [len(s['candidates'][0]['graph']['humans']) for s in client.snapshot(scenes)]
            return {'p1', 'p2'} <= {u.data for u in client.snapshot(users)} and max(humans, default=0) >= 3
        assert client.wait(served_and_seen, 90), ([u.data for u in users], len(scenes),
                                                  (tmp_path / 'bridge.log').read_text()[-2000:])
        assert all(s.get('user_id', 'p').startswith('p') for s in scenes)
        for process, log in zip(processes, ('world.log', 'bridge.log')):
            assert process.poll() is None and stop(process, signal.SIGINT) == 0, (tmp_path / log).read_text()[-2000:]
    finally:
        for process in processes:
            if process.poll() is None:
                process.kill()
        client.close()


def test_the_real_tf_path(hri_msgs, tmp_path):
    """The same scene through real TF frames person_<id> (pose_source:=tf), where tf2_ros is."""
    pytest.importorskip('tf2_ros', reason='tf2_ros is not importable (it comes with a ROS install, ros-jazzy-tf2-ros; '
                        'no registry here serves it): the TF path runs where it is')
    from stars_ros.ros.hri_world import World
    domain = domain_id(16)  # after test_state_node's, in turn (as domain 7 is shared)
    client = RosClient(domain, listen=False)
    scenes = client.collect('/stars/scene', RELIABLE)
    world = World(client.node, 'base_link', use_tf=True)
    bridge = start_node('stars_ros.ros.hri_bridge', domain,
                        {'pose_source': 'tf', 'max_age': 1.0, 'wait_for_ranker': False},
                        tmp_path / 'bridge.log')
    try:
        world.track(['alice'])
        world.anonymous('alice', False)
        client.node.create_timer(0.1, lambda: (world.pose('alice', *POSES['alice']), world.engage('alice', ENGAGED)))
        assert client.wait(lambda: any(s.get('user_id') == 'alice' for s in scenes), 60)
        stay = next(c['graph'] for c in scenes[-1]['candidates'] if c['candidate'] == 'stay')
        (human,) = frames.from_socnav(stay).humans
        assert abs(human.x - POSES['alice'][0]) <= 0.01 and abs(human.y - POSES['alice'][1]) <= 0.01
        assert bridge.poll() is None and stop(bridge, signal.SIGINT) == 0
    finally:
        if bridge.poll() is None:
            bridge.kill()
        client.close()
