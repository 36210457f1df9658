"""Round trip of the ranker's typed service ~/rank_actions, against a trivial echo service.

    python benchmarks/service_latency.py [--data-root ../shared/datasets/socnav1] \
        [--count 1000] [--blocks 10] [--out results/service_latency.json]

Starts two nodes, each in its own process on loopback DDS and in a ROS domain of its own:
the ranker (packaged default checkpoint, recording on, markers published) and an echo node
that serves the same service type under the same name and answers at once with the request's
scene id (no model, no conversion). A client in this process sends real SocNav1 scenes as
typed requests (REP 103, ``stars_ros.typed_messages.scene_message``; user ids alternating),
one call in flight at a time, and times call → response. The calls are made in ``--blocks``
blocks that alternate between the two nodes (echo ranker, ranker echo, ...), as
``node_latency.py`` does, because this VM's speed drifts within minutes. The ratio of the
p50s says what the ranker adds over a service round trip of the same message.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import rclpy  # noqa: E402
from geometry_msgs import msg as geometry  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from stars_ros_msgs import msg as typed  # noqa: E402
from stars_ros_msgs.srv import RankActions  # noqa: E402

from offline_training.common import DEFAULT_SOCNAV1  # noqa: E402
from stars_ros.evaluation.provenance import git_state, machine  # noqa: E402
from stars_ros.data.scene_source import read_scenes  # noqa: E402
from stars_ros.ros.spinning import spin_until_shutdown  # noqa: E402
from stars_ros.typed_messages import scene_message  # noqa: E402

SERVICE = '/ranker/rank_actions'


def echo_main():
    """The echo node: ~/rank_actions answered at once with the request's scene id."""
    rclpy.init()
    node = Node('ranker')

    def echo(request, response):
        response.success = True
        response.ranking.scene_id = request.scene_id
        return response
    node.create_service(RankActions, '~/rank_actions', echo)
    try:
        spin_until_shutdown(node)  # as the ranker spins
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


class Caller:
    """A service client in a domain of its own, timing one call at a time."""

    def __init__(self, domain: int, target: str):
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = Node(f'service_latency_{target}', context=self.context)
        self.client = self.node.create_client(RankActions, SERVICE)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        threading.Thread(target=self.executor.spin, daemon=True).start()

    def call(self, request, timeout: float = 10.0):
        """(seconds from call to response, the response), or (None, None) on a timeout."""
        answered = threading.Event()
        started = time.perf_counter()
        future = self.client.call_async(request)
        future.add_done_callback(lambda _: answered.set())
        if not answered.wait(timeout):
            return None, None
        return time.perf_counter() - started, future.result()

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def typed_requests(scenes, prefix: str, count: int, users=('alice', 'bob')) -> list:
    built = [scene_message(scene, 'base_link', typed, geometry) for scene in scenes]
    return [RankActions.Request(scene_id=f'{prefix}-{k}', user_id=users[k % len(users)], scene=built[k % len(built)])
            for k in range(count)]


class Served:
    """A node's process and the caller that talks to it, warmed up."""

    def __init__(self, name: str, command: list, env: dict, scenes, log: Path):
        self.name = name
        self.process = subprocess.Popen(command, env=env, stdout=log.open('w'), stderr=subprocess.STDOUT)
        self.log = log
        self.caller = Caller(int(env['ROS_DOMAIN_ID']), name)
        while not self.caller.client.wait_for_service(timeout_sec=1.0):
            self.check_running()
        for request in typed_requests(scenes, f'{name}-warmup', 100):
            _, response = self.caller.call(request)
            if response is None or not response.success:
                raise RuntimeError(f'{name} did not answer a warm-up call: {response}')

    def check_running(self):
        """RuntimeError with the end of its log once the node's process has exited."""
        if self.process.poll() is not None:
            raise RuntimeError(f'{self.name} exited with {self.process.returncode}: {self.log.read_text()[-2000:]}')

    def stop(self):
        self.caller.close()
        self.process.terminate()
        try:
            self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()


def alternating(served: dict, scenes, count: int, blocks: int) -> tuple:
    """Round trips (ms) per node of ``count`` calls each, in ``blocks`` alternating blocks,
    the calls that got no answer in 10 s, each block's median, and the ranker's own account
    of each call's work (the ranking's ``processing_time``, ms)."""
    times = {name: [] for name in served}
    processing = []
    medians = {name: [] for name in served}
    timeouts = {name: 0 for name in served}
    names = list(served)
    for block in range(blocks):
        for name in (names if block % 2 == 0 else names[::-1]):
            measured = []
            for request in typed_requests(scenes, f'{name}-{block}', max(1, count // blocks)):
                seconds, response = served[name].caller.call(request)
                if response is None or not response.success:
                    served[name].check_running()
                    timeouts[name] += 1
                else:
                    measured.append(seconds * 1e3)
                    if name == 'ranker':
                        processing.append(response.ranking.processing_time * 1e3)
            times[name] += measured
            medians[name].append(float(np.median(measured)) if measured else float('nan'))
    return times, timeouts, medians, processing


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--data-root', default=str(DEFAULT_SOCNAV1))
    parser.add_argument('--count', type=int, default=1000, help='calls per node')
    parser.add_argument('--blocks', type=int, default=10)
    parser.add_argument('--out', default=str(REPO / 'results' / 'service_latency.json'))
    parser.add_argument('--echo', action='store_true', help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.echo:
        echo_main()
        return 0
    scenes = read_scenes(Path(args.data_root) / 'raw' / 'b.jsonl')
    domain = 150 + 2 * (os.getpid() % 25)  # the echo node's; the ranker's is the next one
    base_env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
                    PYTHONPATH=str(REPO) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    with tempfile.TemporaryDirectory() as records:
        commands = {'echo': [sys.executable, str(Path(__file__).resolve()), '--echo'],
                    'ranker': [sys.executable, '-m', 'stars_ros.ros.ranker', '--ros-args', '-p',
                               f'record_folder:={records}']}
        served = {}
        try:
            for offset, (name, command) in enumerate(commands.items()):
                env = dict(base_env, ROS_DOMAIN_ID=str(domain + offset))
                served[name] = Served(name, command, env, scenes, Path(records) / f'{name}.log')
            times, timeouts, medians, processing = alternating(served, scenes, args.count, args.blocks)
        finally:
            for node in served.values():
                node.stop()
    results = {name: {'round_trip_ms': {'p50': float(np.percentile(times[name], 50)),
                                        'p99': float(np.percentile(times[name], 99)),
                                        'max': float(np.max(times[name])), 'count': len(times[name]),
                                        'timeouts': timeouts[name]},
                      'block_p50_ms': medians[name]} for name in served}
    results['ranker']['processing_ms'] = {'p50': float(np.percentile(processing, 50)),
                                          'p99': float(np.percentile(processing, 99))}
    results['ratio'] = {'p50': results['ranker']['round_trip_ms']['p50'] / results['echo']['round_trip_ms']['p50'],
                        'p99': results['ranker']['round_trip_ms']['p99'] / results['echo']['round_trip_ms']['p99'],
                        'p50_per_block': [r / e for r, e in zip(medians['ranker'], medians['echo'])]}
    results['settings'] = {'count': args.count, 'blocks': args.blocks, 'checkpoint': 'packaged default',
                           'scenes': 'SocNav1 b.jsonl', 'service': SERVICE, 'machine': machine(), 'git': git_state()}
    for name in served:
        trip = results[name]['round_trip_ms']
        print(f"{name:6s} round trip p50 {trip['p50']:.2f} ms  p99 {trip['p99']:.2f} ms  max {trip['max']:.2f} ms  "
              f"({trip['count']} calls, {trip['timeouts']} unanswered)")
    print(f"ranker's own processing_time (from the service callback's start to the reply built) p50 "
          f"{results['ranker']['processing_ms']['p50']:.2f} ms")
    ratio = results['ratio']
    print(f"ratio ranker/echo: p50 {ratio['p50']:.2f}, p99 {ratio['p99']:.2f}; p50 per block "
          + ' '.join(f'{r:.2f}' for r in ratio['p50_per_block']))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=2) + '\n')
    print(f'wrote {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
