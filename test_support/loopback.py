"""Real nodes on loopback DDS, for the tests and the benchmarks that run them: a block of
ROS domains reserved per process, a node started as its own process on one of them, and a
client node (``RosClient``) that talks to it.

Each process reserves a block of ROS domains for its lifetime (an exclusive lock on a file
per block), so two runs on one machine never share a domain; each user takes its own domain
of the block, and discovery is limited to this machine.
"""
import ctypes
import fcntl
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String
from std_srvs.srv import Trigger

from stars_ros.waiting import wait_for

PACKAGE_ROOT = Path(__file__).resolve().parents[1]  # the checkout, whose stars_ros a node's process imports
RELIABLE = QoSProfile(depth=5000, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


DOMAINS_PER_BLOCK = 18
FIRST_DOMAIN, BLOCKS = 100, 7  # domains 100..225: clear of the default 0 and of Fast DDS's limit (232)
_reserved = {}


def reserve_block() -> int:
    """The first domain of a block no other process holds; the lock is kept (and released
    by the OS) for this process's lifetime."""
    if 'block' not in _reserved:
        for block in range(BLOCKS):
            handle = open(os.path.join(tempfile.gettempdir(), f'stars_ros_test_domains_{block}.lock'), 'w')
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                handle.close()
                continue
            _reserved.update(block=FIRST_DOMAIN + block * DOMAINS_PER_BLOCK, handle=handle)
            break
        else:
            raise RuntimeError(f'all {BLOCKS} blocks of loopback ROS domains are held by other runs')
    return _reserved['block']


def domain_id(offset: int) -> int:
    """This process's ROS domain number ``offset`` (0..17) of its reserved block."""
    if not 0 <= offset < DOMAINS_PER_BLOCK:
        raise ValueError(f'domain offset {offset} outside 0..{DOMAINS_PER_BLOCK - 1}')
    return reserve_block() + offset


def ros_env(domain: int) -> dict:
    return dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
                PYTHONPATH=str(PACKAGE_ROOT) + os.pathsep + os.environ.get('PYTHONPATH', ''), PYTHONUNBUFFERED='1')


_PR_SET_PDEATHSIG = 1
_prctl = ctypes.CDLL(None, use_errno=True).prctl  # looked up here, not in the forked child


def die_with_the_parent():
    """In a node's process before it starts: killed when the process that started it dies,
    however it dies. A node left behind by a killed run would answer on domains the next run
    reserves."""
    _prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)


def start_node(module: str, domain: int, params: dict, log_path: Path, args=(), ros_args=()) -> subprocess.Popen:
    """``python -m <module> [args] --ros-args -p k:=v ... [ros_args]`` with its output in ``log_path``."""
    command = [sys.executable, '-m', module, *args, '--ros-args']
    for name, value in params.items():
        command += ['-p', f'{name}:={value}']
    command += list(ros_args)
    return subprocess.Popen(command, env=ros_env(domain), stdout=open(log_path, 'w'), stderr=subprocess.STDOUT,
                            preexec_fn=die_with_the_parent)


CLIENT_NAMES = ('stars_test_client',)  # the node name of every RosClient
SETTLE_TIMEOUT = 10.0


class RosClient:
    """A client node on its own context: publishes requests, collects replies."""

    def __init__(self, domain: int, listen: bool = True, namespace: str = ''):
        """``listen=False``: no subscriptions of its own (a benchmark adds just the ones it
        times, so that collecting everything does not load the measuring process);
        ``namespace``: talk to the ranker in that namespace (``/robot1``)."""
        os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = Node('stars_test_client', namespace=namespace or None, context=self.context)
        self.scene_pub = self.node.create_publisher(String, f'{namespace}/stars/scene', RELIABLE)
        self.feedback_pub = self.node.create_publisher(String, f'{namespace}/stars/feedback', RELIABLE)
        self.user_pub = self.node.create_publisher(String, f'{namespace}/stars/user_id', LATCHED)
        self.namespace = namespace
        self.rankings, self.errors, self.diagnostics = [], [], []
        self._changed = threading.Condition()
        if listen:
            self.node.create_subscription(String, f'{namespace}/stars/ranking', self._keep(self.rankings, json.loads),
                                          RELIABLE)
            self.node.create_subscription(String, f'{namespace}/stars/errors', self._keep(self.errors, json.loads),
                                          RELIABLE)
            self.node.create_subscription(DiagnosticArray, '/diagnostics', self._keep(self.diagnostics, None), 100)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._spinner = threading.Thread(target=self.executor.spin, daemon=True)
        self._spinner.start()

    def snapshot(self, store: list) -> list:
        """A copy of ``store`` (one of this client's lists) taken while no callback adds to it."""
        with self._changed:
            return list(store)

    def forget(self):
        """Empty ``rankings``, ``errors`` and ``diagnostics``: a test on a node it shares with
        other tests hears only what comes after (call once their answers are in)."""
        with self._changed:
            for store in (self.rankings, self.errors, self.diagnostics):
                store.clear()

    def collect(self, topic: str, qos) -> list:
        """A list that gathers the JSON of every std_msgs/String on ``topic`` (``wait`` sees it grow)."""
        store = []
        self.node.create_subscription(String, topic, self._keep(store, json.loads), qos)
        return store

    def collect_messages(self, topic: str, msg_type, qos) -> list:
        """A list that gathers every ``msg_type`` message on ``topic`` as it is (``wait`` sees it grow)."""
        store = []
        self.node.create_subscription(msg_type, topic, self._keep(store, None), qos)
        return store

    def _keep(self, store, convert):
        def callback(msg):
            with self._changed:
                store.append(convert(msg.data) if convert else msg)
                self._changed.notify_all()
        return callback

    def wait(self, predicate, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        with self._changed:
            while not predicate():
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._changed.wait(min(left, 0.2))
        return True

    def scene(self, payload):
        self.scene_pub.publish(String(data=payload if isinstance(payload, str) else json.dumps(payload)))

    def feedback(self, payload: dict):
        self.feedback_pub.publish(String(data=json.dumps(payload)))

    def ranking_for(self, scene_id: str):
        with self._changed:
            return next((r for r in self.rankings if r['scene_id'] == scene_id), None)

    def wait_ready(self, process, timeout: float, probe: dict):
        """Wait until ``process`` answers ``probe`` (a valid request) end to end."""
        deadline = time.monotonic() + timeout

        def discovered_or_exited():
            return process.poll() is not None or bool(
                self.scene_pub.get_subscription_count()
                and self.node.count_publishers(f'{self.namespace}/stars/ranking'))
        while wait_for(discovered_or_exited, deadline - time.monotonic()):
            if process.poll() is not None:
                raise RuntimeError(f'node exited with {process.returncode}')
            self.scene(probe)
            if self.wait(lambda: self.ranking_for(probe['scene_id']) is not None, 2.0):
                return
        raise TimeoutError('node did not answer in time')

    def call(self, service: str, timeout: float = 30.0):
        client = self.node.create_client(Trigger, service)
        if not client.wait_for_service(timeout_sec=timeout):
            raise TimeoutError(f'{service} not available')
        future = client.call_async(Trigger.Request())
        if not self.wait(future.done, timeout):
            raise TimeoutError(f'{service} did not answer')
        return future.result()

    def set_parameters(self, node_name: str, values: dict, timeout: float = 10.0):
        client = AsyncParameterClient(self.node, node_name)
        if not client.wait_for_services(timeout_sec=timeout):
            raise TimeoutError(f'parameters of {node_name} not available')
        future = client.set_parameters([Parameter(k, value=v) for k, v in values.items()])
        if not self.wait(future.done, timeout):
            raise TimeoutError('set_parameters did not answer')
        return future.result().results

    def close(self):
        """Destroy the client once the nodes it talked to have left its graph (at most
        ``SETTLE_TIMEOUT``): Fast DDS 2.14 can deadlock when a participant is destroyed while
        it still takes in a leaving participant's endpoints (seen once: the whole run hung,
        the destroying thread holding the GIL)."""
        self.executor.shutdown()
        wait_for(lambda: set(self.node.get_node_names()) <= set(CLIENT_NAMES), SETTLE_TIMEOUT)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def stop(process: subprocess.Popen, signal_number, timeout: float = 30.0) -> int:
    process.send_signal(signal_number)
    try:
        return process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
        raise
