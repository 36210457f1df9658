"""Fleet sharing: how long a fold-in takes to reach a peer, and what peers' models cost the
rankings of other users on the robot that receives them.

    python benchmarks/fleet_latency.py [--checkpoint models/socnav1_gat_stars.pt] \
        [--data-root ../shared/datasets/socnav1] [--out results/fleet_latency.json]

Starts two rankers (robot_a, robot_b: fleet_sharing on, each in its namespace, stars/user_model
remapped to /fleet/user_model) on loopback DDS, in a ROS domain reserved as the tests reserve
theirs (no other graph is heard). This process:
  * reach: ``--reach-count`` times, ranks a scene at A for a new user, then sends A feedback
    on it and times feedback → A's model on the fleet topic (A's own fold-in) and → B's model
    of that user on the fleet topic (B took A's ratings in, solved and published);
  * load: times rankings of other users at B (one request at a time, one every
    ``--paced-period`` s) in blocks that alternate between quiet and a stream of new peer
    models at ``--model-rate`` per second (each a new user with ``--ratings-per-model``
    ratings of real scenes, as robot A would send them), so that the VM's drift falls on
    both alike; it also counts the streamed models B solved and published.
The rankers record (MCAP and the state store) unless ``--no-record``.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from offline_training.common import DEFAULT_SOCNAV1  # noqa: E402
from stars_ros.evaluation.provenance import git_state, machine  # noqa: E402
from test_support.loopback import RosClient, domain_id, start_node  # noqa: E402
from stars_ros.model.predictor import Predictor  # noqa: E402
from stars_ros.resources import resolve_checkpoint  # noqa: E402
from stars_ros.data.scene_source import read_scenes  # noqa: E402

FLEET_TOPIC = '/fleet/user_model'
MODELS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


class FleetListener:
    """Timestamps each model on the fleet topic by (origin, user, n_ratings)."""

    def __init__(self, client: RosClient):
        self.seen, self.condition = {}, threading.Condition()
        client.node.create_subscription(String, FLEET_TOPIC, self._on_model, MODELS)
        self.publisher = client.node.create_publisher(String, FLEET_TOPIC, MODELS)

    def _on_model(self, msg):
        now = time.perf_counter()
        model = json.loads(msg.data)
        with self.condition:
            self.seen.setdefault((model.get('origin'), model['user_id'], model['n_ratings']), now)
            self.condition.notify_all()

    def wait(self, key, timeout: float) -> float | None:
        deadline = time.perf_counter() + timeout
        with self.condition:
            while key not in self.seen:
                left = deadline - time.perf_counter()
                if left <= 0:
                    return None
                self.condition.wait(left)
            return self.seen[key]


def summary(values: list) -> dict:
    return {'n': len(values), **({f'p{q}': float(np.percentile(values, q)) for q in (50, 90, 99)} if values else {}),
            'max': float(max(values)) if values else None}


def peer_model(fingerprint: str, scenes: list, user: str, count: int) -> str:
    """A peer's stars/user_model message: a new user rated ``count`` scenes (the model
    fields are placeholders; the receiver solves from the ratings)."""
    stamp = time.time_ns()
    ratings = [{'id': uuid.uuid4().hex, 'stamp': stamp + k, 'origin': '/robot_x/ranker', 'scene': scene,
                'scene_id': scene['identifier'], 'action': 'navigate', 'score': float(k % 2)}
               for k, scene in enumerate(scenes[:count])]
    return json.dumps({'user_id': user, 'p_u': [0.0], 'b_u': 0.0, 'n_ratings': count, 'fingerprint': fingerprint,
                       'regularisation': 1.0, 'origin': '/robot_x/ranker', 'ratings': ratings})


def measure_reach(robot_a: RosClient, listener: FleetListener, scenes: list, count: int) -> dict:
    own, peer = [], []
    for k in range(count):
        user, scene = f'reach-{k}', scenes[k % len(scenes)]
        scene_id = f'reach-{k}'
        robot_a.scene({'scene_id': scene_id, 'user_id': user, 'graph': scene})
        if not robot_a.wait(lambda: robot_a.ranking_for(scene_id) is not None, 10):
            raise TimeoutError('robot_a did not rank')
        sent = time.perf_counter()
        robot_a.feedback({'user_id': user, 'scene_id': scene_id, 'action': 'navigate', 'score': 0.9})
        at_a = listener.wait(('/robot_a/ranker', user, 1), 10)
        at_b = listener.wait(('/robot_b/ranker', user, 1), 10)
        if at_a is None or at_b is None:
            raise TimeoutError(f'the fold-in of {user} did not reach both robots')
        own.append((at_a - sent) * 1e3)
        peer.append((at_b - sent) * 1e3)
    return {'feedback_to_own_model_ms': summary(own), 'feedback_to_peer_model_ms': summary(peer),
            'peer_after_own_ms': summary([b - a for a, b in zip(own, peer)])}


def measure_load(robot_b: RosClient, listener: FleetListener, fingerprint: str, scenes: list, args) -> dict:
    latencies = {'quiet': [], 'models': []}
    streamed = []
    for block in range(2 * args.blocks):
        kind = ('quiet', 'models')[block % 2]
        stop = threading.Event()

        def stream():
            k = 0
            while not stop.wait(1.0 / args.model_rate if k else 0):
                user = f'stream-{block}-{k}'
                listener.publisher.publish(String(data=peer_model(
                    fingerprint, scenes[k % 50:], user, args.ratings_per_model)))
                streamed.append(user)
                k += 1
        streamer = threading.Thread(target=stream, daemon=True)
        if kind == 'models':
            streamer.start()
        for k in range(args.requests_per_block):
            scene_id = f'load-{block}-{k}'
            started = time.perf_counter()
            robot_b.scene({'scene_id': scene_id, 'user_id': ('alice', 'bob')[k % 2], 'graph': scenes[k % len(scenes)]})
            if robot_b.wait(lambda: robot_b.ranking_for(scene_id) is not None, 10):
                latencies[kind].append((time.perf_counter() - started) * 1e3)
            time.sleep(max(0.0, args.paced_period - (time.perf_counter() - started)))  # the pacing itself
        stop.set()
        if streamer.is_alive():
            streamer.join()
    solved = sum(listener.wait(('/robot_b/ranker', user, args.ratings_per_model), 30) is not None
                 for user in streamed)
    return {'ranking_latency_ms': {kind: summary(values) for kind, values in latencies.items()},
            'models_streamed': len(streamed), 'models_solved_and_published_by_b': solved}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--checkpoint', default='', help='both rankers\' checkpoint (default: the packaged model)')
    parser.add_argument('--data-root', default=str(DEFAULT_SOCNAV1))
    parser.add_argument('--reach-count', type=int, default=50)
    parser.add_argument('--blocks', type=int, default=6, help='blocks of each kind (quiet, models), alternating')
    parser.add_argument('--requests-per-block', type=int, default=100)
    parser.add_argument('--paced-period', type=float, default=0.05)
    parser.add_argument('--model-rate', type=float, default=10.0, help='peer models per second while loading')
    parser.add_argument('--ratings-per-model', type=int, default=5)
    parser.add_argument('--no-record', action='store_true',
                        help="rankers with record_folder '': no MCAP recording, no state store")
    parser.add_argument('--out', default=str(REPO / 'results' / 'fleet_latency.json'))
    args = parser.parse_args(argv)
    scenes = read_scenes(Path(args.data_root) / 'raw' / 'b.jsonl')
    checkpoint = resolve_checkpoint(args.checkpoint)
    fingerprint = Predictor.load(checkpoint).fingerprint
    domain = domain_id(0)
    processes, clients = [], []
    with tempfile.TemporaryDirectory() as records:
        try:
            for name in ('robot_a', 'robot_b'):
                folder = "''" if args.no_record else f'{records}/{name}'
                processes.append(start_node('stars_ros.ros.ranker', domain, {
                    'checkpoint': checkpoint, 'record_folder': folder, 'fleet_sharing': True},
                    Path(records) / f'{name}.log', ros_args=['-r', f'__ns:=/{name}',
                                                             '-r', f'stars/user_model:={FLEET_TOPIC}']))
                clients.append(RosClient(domain, namespace=f'/{name}'))
                clients[-1].wait_ready(processes[-1], 120, {'scene_id': f'ready-{name}', 'graph': scenes[0]})
            robot_a, robot_b = clients
            listener = FleetListener(robot_a)
            reach = measure_reach(robot_a, listener, scenes, args.reach_count)
            load = measure_load(robot_b, listener, fingerprint, scenes, args)
        finally:
            for client in clients:
                client.close()
            for process in processes:
                process.terminate()
                process.wait(timeout=30)
    results = {'reach': reach, 'load': load, 'settings': {
        **{k: v for k, v in vars(args).items() if k not in ('out', 'data_root')}, 'checkpoint': checkpoint,
        'scenes': 'SocNav1 b.jsonl', 'machine': machine(), 'git': git_state()}}
    Path(args.out).write_text(json.dumps(results, indent=2))
    for name, values in reach.items():
        print(f"{name}: p50 {values['p50']:.1f} ms, p90 {values['p90']:.1f} ms, max {values['max']:.1f} ms")
    for kind, values in load['ranking_latency_ms'].items():
        print(f"other users' rankings at B, {kind}: p50 {values['p50']:.2f} ms, p99 {values['p99']:.2f} ms "
              f"(n {values['n']})")
    print(f"peer models streamed at {args.model_rate:g}/s: {load['models_streamed']}, solved and published by B: "
          f"{load['models_solved_and_published_by_b']}; written {args.out}")
    return 0


if __name__ == '__main__':
    sys.exit(main())
