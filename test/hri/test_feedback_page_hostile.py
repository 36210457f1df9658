"""The feedback page node (in this process, on loopback) against 500 malformed or hostile
requests: bad JSON, huge bodies, wrong methods, path traversal, wrong content types, wrong
tokens, stale questions, scores off the scale, garbage that is not HTTP, and the flood they
make together. Every one is refused (an HTTP error, never a success or a server error),
stars/errors names the kinds, nothing goes out as feedback, and the page then takes a real
answer. The test plays the ranker: it answers the page's question request itself."""
import http.client
import json
import socket
from concurrent.futures import ThreadPoolExecutor
from urllib.parse import urlsplit

import pytest
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from ros_helpers import RELIABLE, RosClient, domain_id
from waiting import wait_for

pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning:lark.*')
QUESTIONS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
TOKEN = 'hostile-token-0123456789'
REQUESTS = 500
QUESTION = {'user_id': 'alex', 'scene_id': 'h1', 'action': 'navigate', 'expected_variance_reduction': 0.01,
            'score': 0.5, 'score_sd': 0.1, 'candidates': 1, 'targets': 1, 'fingerprint': '0' * 64}
JSON = {'Content-Type': 'application/json', 'X-Page-Token': TOKEN}


@pytest.fixture(scope='module')
def page(tmp_path_factory):
    """The page node serving alex's question 1, a client that hears its topics, and its address."""
    from stars_ros.ros.feedback_page import FeedbackPageNode
    folder = tmp_path_factory.mktemp('hostile')
    (folder / 'token').write_text(TOKEN)
    client = RosClient(domain_id(10))
    feedback = client.collect('/stars/feedback', RELIABLE)
    requests = client.collect('/stars/question_request', QUESTIONS)
    question_pub = client.node.create_publisher(String, '/stars/question', QUESTIONS)
    node = FeedbackPageNode(context=client.context, parameter_overrides=[
        Parameter('port', value=0), Parameter('feedback_via', value='ranker'),
        Parameter('token_file', value=str(folder / 'token'))])
    client.executor.add_node(node)
    try:
        client.user_pub.publish(String(data='alex'))
        assert client.wait(lambda: any(r['user_id'] == 'alex' for r in requests), 30), 'the page asked nothing'
        question_pub.publish(String(data=json.dumps(QUESTION)))
        assert wait_for(lambda: node.page.view()['phase'] == 'question', 10)
        yield client, node, feedback, urlsplit(node.address)
    finally:
        client.executor.remove_node(node)
        node.destroy_node()
        node.close()
        client.close()


def _request(address, method: str, path: str, body: bytes | None = None, headers=None):
    """(status, JSON body or None) of one request on its own connection."""
    connection = http.client.HTTPConnection(address.hostname, address.port, timeout=30)
    try:
        connection.request(method, path, body=body, headers=headers or {})
        response = connection.getresponse()
        text = response.read()
        try:
            return response.status, json.loads(text)
        except ValueError:
            return response.status, None
    finally:
        connection.close()


def _raw(address, data: bytes) -> int:
    """The status line's code of the answer to ``data`` written on a socket as it is."""
    with socket.create_connection((address.hostname, address.port), timeout=30) as raw:
        raw.sendall(data)
        reply = raw.recv(4096)
    return int(reply.split(b' ', 2)[1]) if reply.startswith(b'HTTP/') else 0


def hostile(k: int):
    """The k-th hostile request: (method, path, body, headers), or bytes to write raw."""
    token = f'?token={TOKEN}'
    cases = [
        ('POST', '/answer', b'{"question": 1, "score": 0.5', JSON),  # bad JSON
        ('POST', '/answer', b'\xff\xfe not utf-8', JSON),
        ('POST', '/answer', b'[' * 1000 + b']' * 1000, JSON),  # deep nesting
        ('POST', '/answer', b'["question", 1]', JSON),
        ('POST', '/answer', b'{"question": 1, "score": NaN}', JSON),
        ('POST', '/answer', b'{"question": 1, "score": 1' + b'0' * 400 + b'}', JSON),  # off every scale
        ('POST', '/answer', b'{"question": 1, "score": -0.5}', JSON),
        ('POST', '/answer', b'{"question": 1, "score": true}', JSON),
        ('POST', '/answer', b'{"question": 99, "score": 0.5}', JSON),  # stale
        ('POST', '/answer', b'{"question": 1, "score": 0.5, "user_id": "mallory"}', JSON),
        ('POST', '/skip', b'{"question": "1"}', JSON),
        ('POST', '/answer', b'{"question": 1, "score": 0.5}' + b' ' * (2048 + 64 * k), JSON),  # huge bodies
        ('POST', '/answer', b'x' * (1 << 20), JSON),
        ('PUT', '/answer', b'{"question": 1, "score": 0.5}', JSON),  # wrong methods
        ('DELETE', '/answer', None, JSON),
        ('GET', '/answer' + token, None, None),
        ('PATCH', '/' + token, b'{}', JSON),
        ('POST', '/events' + token, b'{}', JSON),
        ('GET', '/static/../../package.xml', None, None),  # path traversal
        ('GET', '/static/..%2F..%2Fsetup.py', None, None),
        ('GET', '/static/%2e%2e/%2e%2e/etc/passwd', None, None),
        ('GET', '/scene/..%2F..%2Fetc%2Fpasswd.png' + token, None, None),
        ('GET', '/../../../etc/passwd' + token, None, None),
        ('GET', '/static/page.js%00.png', None, None),
        ('POST', '/answer', b'{"question": 1, "score": 0.5}',  # wrong content types
         {'Content-Type': 'text/plain', 'X-Page-Token': TOKEN}),
        ('POST', '/answer', b'question=1&score=0.5',
         {'Content-Type': 'application/x-www-form-urlencoded', 'X-Page-Token': TOKEN}),
        ('POST', '/answer', b'--b\r\n\r\n--b--', {'Content-Type': 'multipart/form-data; boundary=b',
                                                   'X-Page-Token': TOKEN}),
        ('POST', '/answer', b'{"question": 1, "score": 0.5}', {'Content-Type': 'application/json'}),  # tokens
        ('POST', '/answer', b'{"question": 1, "score": 0.5}', {**JSON, 'X-Page-Token': 'guess'}),
        ('GET', '/', None, None),
        ('GET', '/events?token=' + 'A' * 4000, None, None),
        b'GARBAGE\r\n\r\n',  # not HTTP
        b'GET / HTTP/1.1\r\nHost: x\r\nContent-Length: -1\r\n\r\n',
        b'POST /answer HTTP/1.1\r\nHost: x\r\n' + b'X-Long: ' + b'a' * 20000 + b'\r\n\r\n',
    ]
    return cases[k % len(cases)]


def test_500_hostile_requests_are_refused_and_the_page_serves_on(page):
    client, node, feedback, address = page
    first_ones = [hostile(k) for k in (8, 6)]  # stale and off the scale while the flood bucket is full

    def send(case):
        return ('raw', _raw(address, case)) if isinstance(case, bytes) else (case, _request(address, *case))
    results = [send(case) for case in first_ones]
    with ThreadPoolExecutor(8) as pool:
        results += list(pool.map(send, [hostile(k) for k in range(REQUESTS - len(first_ones))]))
    assert len(results) == REQUESTS
    for case, outcome in results:
        status = outcome if case == 'raw' else outcome[0]
        assert 400 <= status < 500, (case, outcome)
    statuses = {outcome[0] for case, outcome in results if case != 'raw'}
    assert {400, 403, 404, 405, 409, 413, 415, 422, 429} <= statuses, statuses

    kinds = {'bad_request', 'schema', 'stale', 'out_of_scale', 'oversized', 'method', 'not_found', 'content_type',
             'token', 'flood'}
    assert client.wait(lambda: kinds <= {e['kind'] for e in client.errors}, 10), {e['kind'] for e in client.errors}
    assert all(set(e) == {'kind', 'message', 'topic', 'scene_id', 'level'} and e['topic'].startswith('http ')
               for e in client.snapshot(client.errors))

    def answered():  # once the flood has drained, a real answer is taken
        return _request(address, 'POST', '/answer', b'{"question": 1, "score": 0.75}', JSON)[0] == 200
    assert wait_for(answered, 30, interval=0.1), 'the page took no answer after the hostile requests'
    assert client.wait(lambda: len(feedback) >= 1, 10)
    assert client.snapshot(feedback)[0] == {'user_id': 'alex', 'scene_id': 'h1', 'score': 0.75,
                                            'action': 'navigate'}, 'something before the real answer went out'
    assert node.page.view()['phase'] == 'thanks'
