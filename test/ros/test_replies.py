"""A service response rmw_fastrtps drops (the caller's reply reader not matched yet) is sent
again until it goes out: with stand-ins for the service and the timers, and for real with
Fast DDS's defaults and a client whose reply reader can never match."""
import subprocess
import sys
import warnings

from ros_helpers import die_with_the_tests, domain_id, ros_env
from stars_ros.ros import replies


class _Timers:
    """A node's create_timer / destroy_timer and get_logger, run by hand."""

    def __init__(self):
        self.waiting, self.destroyed, self.logged = [], [], []

    def create_timer(self, period, callback):
        timer = (period, callback)
        self.waiting.append(timer)
        return timer

    def destroy_timer(self, timer):
        self.destroyed.append(timer)

    def get_logger(self):
        return self

    def warning(self, line):
        self.logged.append(line)

    info = warning

    def fire(self):
        period, callback = self.waiting.pop(0)
        callback()
        return period


DROPPED = 'failed to send response (timeout): client will not receive response'  # rclpy's words


class _Service:
    srv_name = '/ranker/rank_candidates'

    def __init__(self, drops: int):
        self.drops, self.sent = drops, []

    def send_response(self, response, header):
        if self.drops:
            self.drops -= 1
            warnings.warn(DROPPED, RuntimeWarning, stacklevel=2)
            return
        self.sent.append((response, header))


def test_a_dropped_response_is_sent_again_after_each_wait_until_it_goes_out():
    node, service = _Timers(), _Service(drops=3)
    replies.resend_dropped(node, service, resend_after=(0.2, 0.5, 1.0, 2.0))
    service.send_response('answer', 'header')  # as the executor sends it
    assert service.sent == [] and [period for period, _ in node.waiting] == [0.2]
    assert [node.fire(), node.fire(), node.fire()] == [0.2, 0.5, 1.0]
    assert service.sent == [('answer', 'header')] and not node.waiting and len(node.destroyed) == 3
    assert node.logged == [f'{_Service.srv_name}: a response the middleware had dropped was sent again 1.7 s later']


def test_a_client_never_found_is_logged_and_other_warnings_are_issued_as_they_were():
    node, service = _Timers(), _Service(drops=10)
    replies.resend_dropped(node, service, resend_after=(0.1, 0.1))
    service.send_response('answer', 'header')
    node.fire()
    node.fire()
    assert not node.waiting and service.sent == []
    assert node.logged == [f'{_Service.srv_name}: a response could not be sent: the client that called was not '
                           'discovered within 0.2 s']
    plain = _Service(drops=0)
    plain.send_response = lambda response, header: warnings.warn("something else", UserWarning, stacklevel=2)
    replies.resend_dropped(node, plain)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter('always')
        plain.send_response('answer', 'header')
    assert [str(w.message) for w in caught] == ['something else'] and len(node.waiting) == 0


_NEVER_MATCHED = '''
import threading, time
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile
from std_srvs.srv import Trigger
from stars_ros.ros import replies

rclpy.init()
server, caller = Node('server'), Node('caller')
tries = []
service = server.create_service(Trigger, '~/go', lambda request, response: response)
send = service.send_response
service.send_response = lambda response, header: (tries.append(1), send(response, header))
replies.resend_dropped(server, service, resend_after=(0.05, 0.05))
# a reply reader asking for transient local never matches the service's volatile reply writer
client = caller.create_client(Trigger, '/server/go', qos_profile=QoSProfile(
    depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL))
executor = SingleThreadedExecutor()
executor.add_node(server)
executor.add_node(caller)
threading.Thread(target=executor.spin, daemon=True).start()
# service_is_ready never holds for it: call once the server knows its request writer
while not server.get_publishers_info_by_topic('rq/server/goRequest', no_mangle=True):
    time.sleep(0.01)
future = client.call_async(Trigger.Request())
deadline = time.monotonic() + 30
while len(tries) < 3 and time.monotonic() < deadline:
    time.sleep(0.01)
time.sleep(0.5)  # a fourth try would come by now
print('tries', len(tries), 'answered', future.done(), flush=True)
'''


def test_with_fast_dds_defaults_a_response_the_middleware_drops_is_tried_again_then_given_up():
    """The process is the subject: Fast DDS's defaults (not the suite's profile, whose 5 s
    max_blocking_time would make each try that long), the warning rclpy really gives."""
    env = ros_env(domain_id(16))
    for name in ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE'):
        env.pop(name, None)
    child = subprocess.run([sys.executable, '-c', _NEVER_MATCHED], env=env, capture_output=True, text=True,
                           timeout=90, preexec_fn=die_with_the_tests)
    output = child.stdout + child.stderr
    assert child.returncode == 0, output
    assert 'tries 3 answered False' in output, output
    assert 'could not be sent: the client that called was not discovered within 0.1 s' in output, output
    assert 'RuntimeWarning' not in output, output
