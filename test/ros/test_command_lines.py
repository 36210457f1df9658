"""The command lines of docs/interfaces.md ("From the command line") against a real ranker with
the packaged model: each line's YAML argument read into its message's fields as `ros2 service
call` and `ros2 topic pub` read it, the message sent with rclpy (the `ros2` command line does
not install from PyPI). The service call ranks the scene, the typed feedback is folded in, the
JSON scene is ranked on stars/ranking."""
import importlib
import re
import shlex
from pathlib import Path

import pytest
import yaml
from rclpy.qos import QoSProfile, ReliabilityPolicy

from ros_helpers import RosClient, call_service, domain_id, start_node
from waiting import wait_for

pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning:lark.*')
DOC = Path(__file__).resolve().parents[2] / 'docs' / 'interfaces.md'


def command_lines() -> list:
    section = DOC.read_text().split('## From the command line', 1)[1].split('\n## ', 1)[0]
    return [shlex.split(line) for line in section.splitlines() if line.startswith('ros2 ')]


def interface(name: str):
    """The class of 'pkg/msg/Type' or 'pkg/srv/Type'."""
    package, kind, type_name = name.split('/')
    return getattr(importlib.import_module(f'{package}.{kind}'), type_name)


def fill(message, values: dict):
    """``message`` with ``values`` (YAML read) set field by field, nested messages and
    sequences of them included, each value converted to its field's type."""
    fields = message.get_fields_and_field_types()
    for name, value in values.items():
        if name not in fields:
            raise AttributeError(f'{type(message).__name__} has no field {name}')
        current = getattr(message, name)
        if isinstance(value, dict):
            fill(current, value)
        elif isinstance(value, list):
            nested = re.fullmatch(r'sequence<(\w+)/(\w+)>', fields[name])
            element = None if nested is None else interface(f'{nested[1]}/msg/{nested[2]}')
            setattr(message, name, [fill(element(), v) if element else v for v in value])
        else:
            setattr(message, name, type(current)(value))
    return message


@pytest.mark.slow
def test_the_documented_command_lines_work_against_a_ranker(tmp_path):
    service_call, feedback_pub, scene_pub = command_lines()
    assert service_call[:3] == ['ros2', 'service', 'call'] and feedback_pub[:3] == scene_pub[:3] == [
        'ros2', 'topic', 'pub']
    domain = domain_id(2)
    client = RosClient(domain)
    process = start_node('stars_ros.ros.ranker', domain, {'record_folder': tmp_path}, tmp_path / 'ranker.log')
    try:
        name, kind, argument = service_call[3:]
        request = fill(interface(kind).Request(), yaml.safe_load(argument))
        first = call_service(client, interface(kind), name, request, timeout=90)
        assert first.success, first.message
        assert first.ranking.scene_id == 's1' and [e.name for e in first.ranking.entries] == ['navigate']

        topic, kind, argument = feedback_pub[4:]
        assert feedback_pub[3] == '--once'
        publisher = client.node.create_publisher(interface(kind), topic, QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE))
        assert wait_for(lambda: publisher.get_subscription_count() > 0, 30)
        publisher.publish(fill(interface(kind)(), yaml.safe_load(argument)))
        assert wait_for(lambda: call_service(client, interface(service_call[4]), service_call[3], request)
                        .ranking.personalised_from >= 1, 60), 'the typed feedback was not folded in'

        topic, kind, argument = scene_pub[4:]
        assert (topic, kind) == ('/stars/scene', 'std_msgs/msg/String')
        client.scene(fill(interface(kind)(), yaml.safe_load(argument)).data)
        assert client.wait(lambda: client.ranking_for('s2') is not None, 30), client.errors
        assert client.ranking_for('s2')['ranking'][0]['action'] == 'navigate'
    finally:
        process.kill()
        process.wait()
        client.close()
