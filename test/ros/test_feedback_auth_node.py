"""Signed feedback over loopback DDS: a ranker process with ``feedback_key_file`` refuses
unsigned feedback (kind auth on stars/errors and /diagnostics) and folds in feedback signed
by ``python -m stars_ros.sign_feedback``, as a client would publish it; its topics and
services are exactly those its SROS2 policy allows; with a key file it cannot read it does
not start. test_feedback_auth.py checks every refusal without ROS."""
import json
import subprocess
import sys
import time
import xml.etree.ElementTree as ET

import pytest
from std_msgs.msg import String

from ros_helpers import REPO, domain_id, running_ranker, start_node
from waiting import wait_for
from stars_ros.data.scene_source import scene_request

pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning:lark.*')
START_TIMEOUT = 90
REACH_TIMEOUT = 30  # a bound on delivery, not a measurement
USER = 'visitor'
SECRET = bytes(range(32))


def _policy_names():
    """(subscribed topics, published topics, services) the policy allows, as fully
    qualified names of a ranker in namespace / (the profile's ns)."""
    profile = ET.parse(REPO / 'config' / 'security' / 'ranker.policy.xml').find('.//profile')

    def names(path):
        return {('/ranker/' + t.text[2:]) if t.text.startswith('~/') else '/' + t.text.lstrip('/')
                for t in profile.findall(path)}
    return (names("topics[@subscribe='ALLOW']/topic"), names("topics[@publish='ALLOW']/topic"),
            names("services[@reply='ALLOW']/service"))


def _graph(client):
    node = client.node
    try:
        return ({t for t, _ in node.get_subscriber_names_and_types_by_node('ranker', '/')},
                {t for t, _ in node.get_publisher_names_and_types_by_node('ranker', '/')},
                {t for t, _ in node.get_service_names_and_types_by_node('ranker', '/')})
    except Exception:  # noqa: BLE001 - rclpy raises NodeNameNonExistentError until discovery has the node
        return None


def test_a_key_file_the_ranker_cannot_use_stops_it(tiny_checkpoint, tmp_path):
    """On a domain of its own: the module's ranker may be serving on domain 13 meanwhile."""
    (tmp_path / 'keys.txt').write_text('tablet:0123\n')
    process = start_node('stars_ros.ros.ranker', domain_id(14), {
        'checkpoint': tiny_checkpoint, 'record_folder': tmp_path / 'records',
        'feedback_key_file': tmp_path / 'keys.txt'}, tmp_path / 'ranker.log')
    try:
        assert process.wait(timeout=START_TIMEOUT) == 1
    finally:
        if process.poll() is None:
            process.kill()
    log = (tmp_path / 'ranker.log').read_text()
    assert 'line 1' in log and 'fewer than 16' in log and not (tmp_path / 'records').exists()


@pytest.fixture(scope='module')
def ranker(tiny_checkpoint, synthetic_scenes, tmp_path_factory):
    """The module's signed-feedback ranker, every option that adds a topic on (fleet sharing,
    consent): the policy test only reads its graph, and the feedback test names a person
    (on the consent list) and scene ids no other test does."""
    folder = tmp_path_factory.mktemp('signed_ranker')
    key_file = folder / 'keys.txt'
    key_file.write_text(f'tablet:{SECRET.hex()}\n')
    key_file.chmod(0o600)
    consent_file = folder / 'consent.txt'
    consent_file.write_text(f'{USER}\n')
    domain = domain_id(13)
    params = {'checkpoint': tiny_checkpoint, 'record_folder': folder / 'records', 'flush_interval': 0.2,
              'diagnostics_period': 0.3, 'fleet_sharing': True, 'feedback_key_file': key_file,
              'store_policy': 'consented', 'consent_file': consent_file}
    probe = {'scene_id': 'probe', 'graph': synthetic_scenes[0]}
    with running_ranker(domain, params, folder / 'ranker.log', probe, START_TIMEOUT) as (process, client):
        yield process, client, key_file, folder


def test_the_ranker_uses_exactly_what_its_sros2_policy_allows(ranker):
    _, client, _, _ = ranker
    expected = _policy_names()
    # the graph fills in as discovery reports the ranker's endpoints
    assert wait_for(lambda: _graph(client) == expected, REACH_TIMEOUT), (_graph(client), expected)


def test_unsigned_feedback_is_refused_and_signed_feedback_from_the_signer_is_folded_in(ranker, synthetic_scenes):
    process, client, key_file, folder = ranker
    scene = synthetic_scenes[1]
    client.scene(scene_request('rated', scene, USER))
    assert client.wait(lambda: client.ranking_for('rated') is not None, REACH_TIMEOUT)
    fields = {'user_id': USER, 'scene_id': 'rated', 'action': 'navigate', 'score': 0.9}
    client.feedback(fields)
    assert client.wait(lambda: any(e['kind'] == 'auth' and e['topic'] == '/stars/feedback' for e in client.errors),
                       REACH_TIMEOUT)

    def diagnosed():
        return any(status.name.endswith(': auth') for array in client.diagnostics for status in array.status)
    assert client.wait(diagnosed, REACH_TIMEOUT)
    signed = subprocess.run([sys.executable, '-m', 'stars_ros.sign_feedback', '--key-file', str(key_file),
                             json.dumps(fields)], capture_output=True, text=True, check=True).stdout.strip()
    client.feedback_pub.publish(String(data=signed))
    deadline = time.monotonic() + REACH_TIMEOUT
    probes = 0
    while time.monotonic() < deadline:  # the fold-in is solved once no scene waits: probe until it is served
        probes += 1
        client.scene(scene_request(f'after-{probes}', scene, USER))
        if client.wait(lambda: client.ranking_for(f'after-{probes}') is not None, REACH_TIMEOUT) and \
                client.ranking_for(f'after-{probes}').get('personalised_from') == 1:
            break
    assert client.ranking_for(f'after-{probes}').get('personalised_from') == 1
    assert sum(e['kind'] == 'auth' for e in client.errors) == 1
    log = (folder / 'ranker.log').read_text()
    assert 'feedback is taken only when signed by a key of' in log and 'not authenticated' not in log
