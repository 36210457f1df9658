"""Fleet sharing over loopback DDS: three ranker processes, each in its own namespace, with
stars/user_model remapped to one fleet topic. Feedback for a new user given only to robot A
makes robot B rank for that user exactly as A does; feedback given to A and B at the same
moment ends in the same model on both; a robot started after the feedback gets the models;
a model of another checkpoint is ignored with a warning."""
import json

import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from ros_helpers import RosClient, domain_id, start_node
from stars_ros.model.predictor import Predictor
from stars_ros.resources import DEFAULT_CHECKPOINT, share_path
from stars_ros.data.scene_source import read_scenes

pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning:lark.*')
FLEET_TOPIC = '/fleet/user_model'
START_TIMEOUT = 90
REACH_TIMEOUT = 30  # a fold-in must reach a peer within this (a bound, not a measurement)
MODELS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


@pytest.fixture(scope='module')
def scenes(synthetic_root):
    return read_scenes(synthetic_root / 'raw' / 'h.jsonl')[:12]


def _robot(name, domain, checkpoint, tmp_path):
    return start_node('stars_ros.ros.ranker', domain, {
        'checkpoint': checkpoint, 'record_folder': tmp_path / name, 'flush_interval': 0.2, 'fleet_sharing': True},
        tmp_path / f'{name}.log', ros_args=['-r', f'__ns:=/{name}', '-r', f'stars/user_model:={FLEET_TOPIC}'])


class Robot:
    """A ranker process and a client in its namespace."""

    probes = 0

    def __init__(self, name, domain, checkpoint, tmp_path, scene):
        self.name, self.process = name, _robot(name, domain, checkpoint, tmp_path)
        self.client = RosClient(domain, namespace=f'/{name}')
        self.client.wait_ready(self.process, START_TIMEOUT, {'scene_id': f'ready-{name}', 'graph': scene})

    def rank(self, scene, user, scene_id=None):
        """This robot's ranking of ``scene`` for ``user``."""
        Robot.probes += 1
        scene_id = scene_id or f'{self.name}-probe-{Robot.probes}'
        self.client.scene({'scene_id': scene_id, 'user_id': user, 'graph': scene})
        assert self.client.wait(lambda: self.client.ranking_for(scene_id) is not None, 20), f'{self.name}: no ranking'
        return self.client.ranking_for(scene_id)

    def rate(self, scene, user, score):
        self.rank(scene, user, scene['identifier'])
        self.client.feedback({'user_id': user, 'scene_id': scene['identifier'], 'action': 'navigate', 'score': score})

    def personalised(self, shared, scene, user, n_ratings):
        """This robot's ranking of ``scene`` for ``user`` once it has published a model of
        them solved from ``n_ratings`` ratings (None if none comes within REACH_TIMEOUT):
        the model is served before it is published."""
        origin = f'/{self.name}/ranker'
        if not shared.wait(lambda: any(m['origin'] == origin and m['user_id'] == user and m['n_ratings'] == n_ratings
                                       for m in shared.models), REACH_TIMEOUT):
            return None
        reply = self.rank(scene, user)
        assert reply['personalised_from'] == n_ratings
        return reply

    def stop(self):
        if self.process.poll() is None:
            self.process.terminate()
            self.process.wait(timeout=30)


class FleetTopic:
    """The fleet topic as a listener that joined first sees it, and a publisher on it."""

    def __init__(self, domain):
        self.client = RosClient(domain, listen=False)
        self.models = self.client.collect(FLEET_TOPIC, MODELS)
        self.publisher = self.client.node.create_publisher(String, FLEET_TOPIC, MODELS)

    def wait(self, predicate, timeout: float) -> bool:
        return self.client.wait(predicate, timeout)

    def close(self):
        self.client.close()


def _same(first, second):
    assert [(e['action'], e['score']) for e in first['ranking']] == \
        [(e['action'], e['score']) for e in second['ranking']]


@pytest.mark.slow
def test_a_fleet_of_three_rankers_shares_what_it_learns(tiny_checkpoint, scenes, tmp_path):
    domain = domain_id(11)
    robots = []
    fleet = FleetTopic(domain)
    try:
        robots += [Robot(name, domain, tiny_checkpoint, tmp_path, scenes[11]) for name in ('robot_a', 'robot_b')]
        robot_a, robot_b = robots
        probe = scenes[10]

        # feedback for a new user only at A changes B's ranking for them to exactly A's
        stranger_at_b = robot_b.rank(probe, 'walker')
        for scene, score in zip(scenes[:3], (1.0, 0.9, 0.1)):
            robot_a.rate(scene, 'walker', score)
        at_a = robot_a.personalised(fleet, probe, 'walker', 3)
        at_b = robot_b.personalised(fleet, probe, 'walker', 3)
        assert at_a is not None and at_b is not None, 'the fold-in did not reach robot B in time'
        assert [e['score'] for e in at_b['ranking']] != [e['score'] for e in stranger_at_b['ranking']]
        _same(at_a, at_b)

        # feedback at A and B at the same moment: both end with the same model
        robot_a.rank(scenes[3], 'runner', scenes[3]['identifier'])
        robot_b.rank(scenes[4], 'runner', scenes[4]['identifier'])
        robot_a.client.feedback({'user_id': 'runner', 'scene_id': scenes[3]['identifier'], 'action': 'navigate',
                                 'score': 0.95})
        robot_b.client.feedback({'user_id': 'runner', 'scene_id': scenes[4]['identifier'], 'action': 'navigate',
                                 'score': 0.05})
        at_a, at_b = robot_a.personalised(fleet, probe, 'runner', 2), robot_b.personalised(fleet, probe, 'runner', 2)
        assert at_a is not None and at_b is not None, 'A and B did not converge in time'
        _same(at_a, at_b)
        final = {m['origin']: (m['p_u'], m['b_u']) for m in fleet.models
                 if m['user_id'] == 'runner' and m['n_ratings'] == 2}
        assert final['/robot_a/ranker'] == final['/robot_b/ranker']  # the same model, to the last digit sent

        # a robot started after the feedback receives the models
        robots.append(Robot('robot_c', domain, tiny_checkpoint, tmp_path, scenes[11]))
        robot_c = robots[-1]
        late = robot_c.personalised(fleet, probe, 'walker', 3)
        assert late is not None, 'the late robot did not get the models'
        _same(late, robot_a.rank(probe, 'walker'))
        assert robot_c.personalised(fleet, probe, 'runner', 2) is not None

        # a model solved against another checkpoint is ignored, with a warning
        other = dict(next(m for m in fleet.models if m['user_id'] == 'walker'), user_id='jogger',
                     fingerprint=Predictor.load(share_path(DEFAULT_CHECKPOINT)).fingerprint)
        fleet.publisher.publish(String(data=json.dumps(other)))
        assert robot_b.client.wait(lambda: any(e['kind'] == 'fleet' for e in robot_b.client.errors), 20)
        assert 'personalised_from' not in robot_b.rank(probe, 'jogger')
    finally:  # every robot gone before any client is destroyed (RosClient.close)
        for robot in robots:
            robot.stop()
        for robot in robots:
            robot.client.close()
        fleet.close()
