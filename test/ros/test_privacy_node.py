"""The fleet forget over loopback DDS: two ranker processes sharing a fleet's user models
and forgets, with feedback keys. Robot B learns a person from robot A; ~/forget_person on A
makes B forget them too (told on the fleet's stars/forget_person, without the id), and a
model of that person published later is refused by B."""
import json

import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from ros_helpers import RosClient, call_service, domain_id, start_node
from waiting import wait_for
from stars_ros import feedback_auth
from stars_ros.data.scene_source import read_scenes
from stars_ros_msgs.srv import ForgetPerson

pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning:lark.*')
MODELS, FORGETS = '/fleet/user_model', '/fleet/forget_person'
LATCHED = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
SECRET = bytes(range(32))
START_TIMEOUT, REACH_TIMEOUT = 90, 30  # bounds, not measurements


def _robot(name, domain, checkpoint, tmp_path, key_file, scene):
    process = start_node('stars_ros.ros.ranker', domain, {
        'checkpoint': checkpoint, 'record_folder': tmp_path / name, 'flush_interval': 0.2, 'fleet_sharing': True,
        'feedback_key_file': key_file}, tmp_path / f'{name}.log',
        ros_args=['-r', f'__ns:=/{name}', '-r', f'stars/user_model:={MODELS}', '-r', f'stars/forget_person:={FORGETS}'])
    client = RosClient(domain, namespace=f'/{name}')
    client.wait_ready(process, START_TIMEOUT, {'scene_id': f'ready-{name}', 'graph': scene})
    return process, client


@pytest.mark.slow
def test_a_forget_on_one_robot_reaches_its_peer(tiny_checkpoint, synthetic_root, tmp_path):
    scenes = read_scenes(synthetic_root / 'raw' / 'h.jsonl')[:4]
    key_file = tmp_path / 'keys.txt'
    key_file.write_text(f'fleet:{SECRET.hex()}\n')
    key_file.chmod(0o600)
    domain = domain_id(17)
    fleet = RosClient(domain, listen=False)
    models, forgets = fleet.collect(MODELS, LATCHED), fleet.collect(FORGETS, LATCHED)
    publisher = fleet.node.create_publisher(String, MODELS, LATCHED)
    robots = []
    try:
        robots.append(_robot('robot_a', domain, tiny_checkpoint, tmp_path, key_file, scenes[3]))
        robots.append(_robot('robot_b', domain, tiny_checkpoint, tmp_path, key_file, scenes[3]))
        (_, at_a), (_, at_b) = robots
        for n, scene in enumerate(scenes[:2]):
            at_a.scene({'scene_id': f'rated-{n}', 'user_id': 'walker', 'graph': scene})
            assert at_a.wait(lambda: at_a.ranking_for(f'rated-{n}') is not None, 20)
            stamp = at_a.node.get_clock().now().nanoseconds
            at_a.feedback(feedback_auth.sign({'user_id': 'walker', 'scene_id': f'rated-{n}', 'action': 'navigate',
                                              'score': 0.9 - 0.6 * n}, 'fleet', SECRET, stamp))
        assert fleet.wait(lambda: any(m['origin'] == '/robot_b/ranker' and m['user_id'] == 'walker'
                                      and m['n_ratings'] == 2 for m in models), REACH_TIMEOUT), 'B did not learn'
        shared = next(m for m in models if m['user_id'] == 'walker')

        response = call_service(at_a, ForgetPerson, '/robot_a/ranker/forget_person',
                                ForgetPerson.Request(user_id='walker'))
        assert response.success, response.message
        assert fleet.wait(lambda: forgets, REACH_TIMEOUT), 'no forget on the fleet topic'
        assert 'walker' not in json.dumps(forgets[0]) and forgets[0]['auth']['key_id'] == 'fleet'

        probes = iter(range(1000))

        def b_forgot():
            scene_id = f'probe-{next(probes)}'
            at_b.scene({'scene_id': scene_id, 'user_id': 'walker', 'graph': scenes[3]})
            assert at_b.wait(lambda: at_b.ranking_for(scene_id) is not None, 20), 'B does not rank'
            return 'personalised_from' not in at_b.ranking_for(scene_id)
        assert wait_for(b_forgot, REACH_TIMEOUT, interval=0.2), 'B still serves the forgotten person'

        publisher.publish(String(data=json.dumps(shared)))  # a late model of them: refused
        assert at_b.wait(lambda: any(e['kind'] == 'forgotten' for e in at_b.errors), REACH_TIMEOUT)
        assert not any('walker' in e['message'] for e in at_b.errors if e['kind'] == 'forgotten')
    finally:
        for process, _ in robots:
            process.terminate()
            process.wait(timeout=30)
        for _, client in robots:
            client.close()
        fleet.close()
