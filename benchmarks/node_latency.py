"""End-to-end latency and sustained throughput of the ranker node, against an echo floor.

    python benchmarks/node_latency.py [--checkpoint models/socnav1_gat_stars.pt] \
        [--data-root ../shared/datasets/socnav1] [--out results/node_latency.json]

Starts two nodes, each in its own process on loopback DDS and in a ROS domain of its own:
the ranker (packaged default checkpoint, recording on) and an echo node with the same QoS
that republishes each scene request unchanged on stars/ranking (a trivial callback, replies
at least as large as the ranker's). A client in this process sends real SocNav1 scenes (one
request per scene, user id included) and times scene → ranking:
  * latency: one request in flight at a time, each sent as soon as the previous one is
    answered; p50 / p99 / max over ``--latency-count``;
  * paced latency: the same, but one request every ``--paced-period`` seconds (100 Hz by
    default, a perception rate): between two requests every thread of both processes goes
    idle, and on this VM waking them is part of what a robot's request costs;
  Both latencies are measured in ``--blocks`` blocks that alternate between the two nodes
  (echo ranker, ranker echo, ...): this VM's speed drifts by tens of percent within minutes,
  and measured one after the other the two nodes met different stretches of it;
  * throughput: for each of ``--rates`` (per second; 0: as fast as the client can), a burst
    of ``--burst`` requests; the sustained rate = replies per second between the first and
    the last reply, the number lost (no reply within 10 s of the last send) and the latency
    under that load. The default rates are the target (300/s) and 1.5 times it.
The ratios ranker / echo say what the model adds over the middleware floor. Before the
nodes start, ``in_process`` times the steps of one request on one thread in this process
(parse and validate, featurise, encode, score, build the reply; the whole request with and
without score_sd and p_first_is_best, which the node computes for every ranking, and with
every entry's ``why``, ``"explain": true``: docs/explanations.md; and the stars/markers of an
explained ranking, built and encoded as a MarkerArray, which the node does after the reply
for a subscriber or the bag: ``--no-markers`` turns their recording off), with the
encoder in its serving form (GAT: compiled; the others: dense numpy) and, as a reference
measured in the same run, in its PyG sparse form.
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
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from offline_training.common import DEFAULT_SOCNAV1  # noqa: E402
from stars_ros.evaluation.provenance import git_state, machine  # noqa: E402
from stars_ros.data.scene_source import read_scenes  # noqa: E402
from stars_ros.ros.spinning import spin_until_shutdown  # noqa: E402

QUEUE_DEPTH = 1000
QOS = QoSProfile(depth=QUEUE_DEPTH, reliability=ReliabilityPolicy.RELIABLE)


def echo_main():
    """The echo node: stars/scene → stars/ranking unchanged, same QoS as the ranker."""
    rclpy.init()
    node = Node('echo')
    publisher = node.create_publisher(String, 'stars/ranking', QOS)
    node.create_subscription(String, 'stars/scene', publisher.publish, QOS)
    try:
        spin_until_shutdown(node)  # as the ranker spins
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


class Client:
    """Publishes requests and timestamps the replies, matched by scene_id."""

    def __init__(self, domain: int, target: str):
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = Node(f'latency_client_{target}', context=self.context)
        self.publisher = self.node.create_publisher(String, 'stars/scene', QOS)
        self.node.create_subscription(String, 'stars/ranking', self._on_reply, QOS)
        self.received = {}
        self.processing_ms = []
        self.condition = threading.Condition()
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        threading.Thread(target=self.executor.spin, daemon=True).start()

    def _on_reply(self, msg):
        now = time.perf_counter()
        reply = json.loads(msg.data)
        with self.condition:
            self.received[reply['scene_id']] = now
            if 'processing_ms' in reply:
                self.processing_ms.append(reply['processing_ms'])
            self.condition.notify_all()

    def send(self, text: str) -> float:
        sent = time.perf_counter()
        self.publisher.publish(String(data=text))
        return sent

    def wait_for(self, scene_id: str, timeout: float) -> bool:
        deadline = time.perf_counter() + timeout
        with self.condition:
            while scene_id not in self.received:
                left = deadline - time.perf_counter()
                if left <= 0:
                    return False
                self.condition.wait(left)
        return True

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def requests(scenes, prefix: str, count: int, users=('alice', 'bob')) -> list:
    return [(f'{prefix}-{k}', json.dumps({'scene_id': f'{prefix}-{k}', 'user_id': users[k % len(users)],
                                          'graph': scenes[k % len(scenes)]})) for k in range(count)]


class Served:
    """A node's process and the client that talks to it (in the node's own domain)."""

    def __init__(self, name: str, command: list, env: dict, scenes, log: Path):
        self.name, self.log = name, log
        self.process = subprocess.Popen(command, env=env, stdout=log.open('w'), stderr=subprocess.STDOUT)
        self.client = Client(int(env['ROS_DOMAIN_ID']), name)
        for scene_id, text in requests(scenes, f'{name}-warm', 10 ** 6):  # until the node answers
            if self.process.poll() is not None:
                raise RuntimeError(f'{name} exited with {self.process.returncode}: {log.read_text()[-2000:]}')
            if self.client.publisher.get_subscription_count():
                self.client.send(text)
                if self.client.wait_for(scene_id, 2.0):
                    break
            else:
                time.sleep(0.2)
        for scene_id, text in requests(scenes, f'{name}-warmup', 100):
            self.client.send(text)
            self.client.wait_for(scene_id, 5.0)
        self.client.processing_ms.clear()

    def stop(self):
        self.client.close()
        self.process.terminate()
        try:
            self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:  # seen once, the echo node: rclpy's destroy_node spun
            self.process.kill()            # in Node.destroy_when_not_in_use after SIGTERM
            self.process.wait()
            print(f'{self.name} did not end within 30 s of SIGTERM: killed', file=sys.stderr)


def alternating(served: dict, scenes, kind: str, count: int, blocks: int, period: float) -> tuple:
    """Latencies (ms) per node of ``count`` requests each, one at a time, sent in ``blocks``
    blocks per node that alternate between the nodes (A B, B A, ...); and each block's median."""
    latencies = {name: [] for name in served}
    medians = {name: [] for name in served}
    names = list(served)
    per_block = max(1, count // blocks)
    for block in range(blocks):
        for name in (names if block % 2 == 0 else names[::-1]):
            batch = requests(scenes, f'{name}-{kind}-{block}', per_block)
            measured = one_at_a_time(served[name].client, batch, period)
            latencies[name] += measured
            medians[name].append(float(np.median(measured)) if measured else float('nan'))
    return latencies, medians


def one_at_a_time(client, burst: list, period: float) -> list:
    """Latencies (ms) of ``burst`` sent one at a time, each ``period`` s after the previous
    was sent (0: as soon as it is answered)."""
    latencies = []
    for scene_id, text in burst:
        sent = client.send(text)
        if client.wait_for(scene_id, 5.0):
            latencies.append((client.received[scene_id] - sent) * 1e3)
        if period:
            time.sleep(max(0.0, sent + period - time.perf_counter()))
    return latencies


def summary(latencies: list, sent: int) -> dict:
    return {'p50': float(np.percentile(latencies, 50)), 'p99': float(np.percentile(latencies, 99)),
            'max': float(np.max(latencies)), 'count': len(latencies), 'timeouts': sent - len(latencies)}


def run_burst(client, burst: list, rate: float) -> dict:
    """Publish ``burst`` at ``rate`` per second (0: flat out). Sustained rate = replies per
    second between the first and the last reply: a node that keeps up answers at the offered
    rate, one that falls behind answers at its capacity while its queue grows."""
    sent_at, period = [], 1.0 / rate if rate else 0.0
    start = time.perf_counter()
    for k, (_, text) in enumerate(burst):
        if period:
            delay = start + k * period - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        sent_at.append(client.send(text))
    client.wait_for(burst[-1][0], 10.0)
    deadline = time.perf_counter() + 10.0
    while time.perf_counter() < deadline:
        with client.condition:
            if all(scene_id in client.received for scene_id, _ in burst):
                break
        time.sleep(0.05)
    with client.condition:
        replies = sorted(client.received[s] for s, _ in burst if s in client.received)
        latency = [(client.received[s] - t) * 1e3 for (s, _), t in zip(burst, sent_at) if s in client.received]
    return {'sent': len(burst), 'received': len(replies), 'lost': len(burst) - len(replies),
            'offered_per_s': (len(burst) - 1) / (sent_at[-1] - sent_at[0]),
            'sustained_per_s': (len(replies) - 1) / (replies[-1] - replies[0]) if len(replies) > 1 else 0.0,
            'latency_ms_p50': float(np.percentile(latency, 50)), 'latency_ms_p99': float(np.percentile(latency, 99))}


def _timed(call):
    """(result of call(), milliseconds it took)."""
    started = time.perf_counter()
    result = call()
    return result, (time.perf_counter() - started) * 1e3


def in_process(checkpoint: str, scenes: list, count: int = 500) -> dict:
    """Median ms of each step of one request on one torch thread and one BLAS thread, as the
    node serves (see the module docstring)."""
    import torch

    from stars_ros import messages
    from stars_ros.model.checkpoint import load_checkpoint
    from stars_ros.model.predictor import Predictor
    from stars_ros.resources import resolve_checkpoint
    from stars_ros.data.scene_graph import featurise
    from stars_ros.data.scene_store import GraphStore
    from stars_ros.node.batching import Pending, rank_batch
    from stars_ros.node.markers import encode_marker_array, ranking_markers
    from stars_ros.personalisation.stack import serving_stack

    from threadpoolctl import threadpool_limits

    torch.set_num_threads(1)
    threadpool_limits(1, user_api='blas')  # as the node does; OpenBLAS threads on busy cores slow explained requests
    predictor = Predictor.load(resolve_checkpoint(checkpoint))
    model = load_checkpoint(resolve_checkpoint(checkpoint))[0].require_model()  # the torch form, timed beside
    uncertainty = serving_stack(predictor).uncertainty  # as the node serves: score_sd and p_first_is_best
    steps = {}

    def request_total(text, spread=uncertainty, explanations=(False, 5)):
        request = messages.parse_scene_request(text, messages.DEFAULT_MAX_BYTES)
        scored = rank_batch(predictor, [Pending(request, 'alice', 0)], 0, spread, explanations)[0]
        return messages.dumps(messages.ranking_payload(request, 'alice', False, scored.ranked,
                                                       predictor.fingerprint, 1.0, scored.action, 0,
                                                       scored.p_first_is_best))

    serving_encoder = model.encoder.serving_form()
    for k, (_, text) in enumerate(requests(scenes, 'in-process', count)):
        _, total = _timed(lambda: request_total(text))
        _, without_spread = _timed(lambda: request_total(text, None))
        _, explained = _timed(lambda: request_total(text, explanations=(True, 5)))
        parsed = messages.parse_scene_request(text, messages.DEFAULT_MAX_BYTES)
        ranked = rank_batch(predictor, [Pending(parsed, 'alice', 0)], 0, uncertainty, (True, 5))[0].ranked
        _, markers = _timed(lambda: encode_marker_array(ranking_markers(parsed, ranked), 'base_link', 0))
        request, parse = _timed(lambda: messages.parse_scene_request(text, messages.DEFAULT_MAX_BYTES))
        graph, featurising = _timed(lambda: featurise(request.graphs[0], validate=False))
        sparse = GraphStore([graph]).batch(torch.arange(1))
        _, encode_serving = _timed(lambda: serving_encoder([graph]))
        with torch.inference_mode():
            _, encode_sparse = _timed(lambda: model.encode(sparse))
        _, score = _timed(lambda: predictor.score('alice', [request.graphs[0]], validate=False))
        if k >= 50:  # the first are warm-up
            for name, ms in (('request_total', total), ('request_total_without_score_sd', without_spread),
                             ('request_total_explained', explained),
                             ('markers_explained', markers),
                             ('parse_validate', parse), ('featurise', featurising),
                             ('encode_serving', encode_serving),
                             ('encode_sparse_reference', encode_sparse),
                             ('featurise_encode_score', score)):
                steps.setdefault(name, []).append(ms)
    return {f'{name}_ms_p50': float(np.median(values)) for name, values in steps.items()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--checkpoint', default='', help='ranker checkpoint (default: the packaged model)')
    parser.add_argument('--data-root', default=str(DEFAULT_SOCNAV1))
    parser.add_argument('--latency-count', type=int, default=1000)
    parser.add_argument('--paced-count', type=int, default=500)
    parser.add_argument('--paced-period', type=float, default=0.01)
    parser.add_argument('--blocks', type=int, default=10,
                        help='blocks per node into which each latency measurement is split, alternating')
    parser.add_argument('--burst', type=int, default=3000)
    parser.add_argument('--rates', type=float, nargs='+', default=[300.0, 450.0],
                        help='offered loads of the bursts, one burst each (0: flat out)')
    parser.add_argument('--out', default=str(REPO / 'results' / 'node_latency.json'))
    parser.add_argument('--explain', action='store_true',
                        help="the ranker explains every ranking (-p explain:=true: each entry's why)")
    parser.add_argument('--no-markers', action='store_true',
                        help='the ranker does not record stars/markers (-p record_markers:=false; nobody subscribes)')
    parser.add_argument('--echo', action='store_true', help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.echo:
        echo_main()
        return 0
    scenes = read_scenes(Path(args.data_root) / 'raw' / 'b.jsonl')
    steps = in_process(args.checkpoint, scenes)
    print('in process, one thread (p50 ms): ' + ', '.join(f'{k[:-7]} {v:.3f}' for k, v in steps.items()))
    domain = 150 + 2 * (os.getpid() % 25)  # the echo node's; the ranker's is the next one
    base_env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
                    PYTHONPATH=str(REPO) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    with tempfile.TemporaryDirectory() as records:
        ranker = [sys.executable, '-m', 'stars_ros.ros.ranker', '--ros-args', '-p', f'record_folder:={records}',
                  '-p', f'queue_depth:={QUEUE_DEPTH}']
        if args.checkpoint:
            ranker += ['-p', f'checkpoint:={args.checkpoint}']
        if args.explain:
            ranker += ['-p', 'explain:=true']
        if args.no_markers:
            ranker += ['-p', 'record_markers:=false']
        echo = [sys.executable, str(Path(__file__).resolve()), '--echo']
        served = {}
        try:
            for offset, (name, command) in enumerate((('echo', echo), ('ranker', ranker))):
                env = dict(base_env, ROS_DOMAIN_ID=str(domain + offset))
                served[name] = Served(name, command, env, scenes, Path(records) / f'{name}.log')
            latency, latency_blocks = alternating(served, scenes, 'lat', args.latency_count, args.blocks, 0.0)
            processing = list(served['ranker'].client.processing_ms)
            paced, paced_blocks = alternating(served, scenes, 'paced', args.paced_count, args.blocks,
                                              args.paced_period)
            results = {name: {
                'latency_ms': summary(latency[name], args.latency_count // args.blocks * args.blocks),
                'latency_block_p50_ms': latency_blocks[name],
                'paced_latency_ms': summary(paced[name], args.paced_count // args.blocks * args.blocks),
                'paced_latency_block_p50_ms': paced_blocks[name],
                'bursts': [run_burst(served[name].client, requests(scenes, f'{name}-burst-{rate:g}', args.burst), rate)
                           for rate in args.rates]} for name in served}
            results['ranker']['node_processing_ms_p50'] = float(np.percentile(processing, 50)) if processing else None
        finally:
            for node in served.values():
                node.stop()
    results['in_process'] = steps
    results['ratio'] = {
        'latency_p50': results['ranker']['latency_ms']['p50'] / results['echo']['latency_ms']['p50'],
        'latency_p99': results['ranker']['latency_ms']['p99'] / results['echo']['latency_ms']['p99'],
        'paced_latency_p50': results['ranker']['paced_latency_ms']['p50'] / results['echo']['paced_latency_ms']['p50'],
        'paced_latency_p99': results['ranker']['paced_latency_ms']['p99'] / results['echo']['paced_latency_ms']['p99']}
    results['settings'] = {'latency_count': args.latency_count, 'paced_count': args.paced_count, 'blocks': args.blocks,
                           'paced_period': args.paced_period, 'burst': args.burst, 'rates': args.rates,
                           'explain': args.explain, 'record_markers': not args.no_markers,
                           'checkpoint': args.checkpoint or 'packaged default', 'scenes': 'SocNav1 b.jsonl',
                           'machine': machine(), 'git': git_state()}
    for name in ('echo', 'ranker'):
        lat = results[name]['latency_ms']
        paced = results[name]['paced_latency_ms']
        print(f"{name:6s} latency p50 {lat['p50']:.2f} ms  p99 {lat['p99']:.2f} ms  max {lat['max']:.2f} ms; "
              f"paced p50 {paced['p50']:.2f} ms  p99 {paced['p99']:.2f} ms  max {paced['max']:.2f} ms")
        for burst in results[name]['bursts']:
            print(f"       burst {burst['sent']} at {burst['offered_per_s']:.0f}/s: sustained "
                  f"{burst['sustained_per_s']:.0f}/s, lost {burst['lost']}, p50 {burst['latency_ms_p50']:.2f} ms, "
                  f"p99 {burst['latency_ms_p99']:.2f} ms")
    ratio = results['ratio']
    ratio['latency_p50_per_block'] = [r / e for r, e in zip(results['ranker']['latency_block_p50_ms'],
                                                            results['echo']['latency_block_p50_ms'])]
    print(f"ratio ranker/echo: p50 {ratio['latency_p50']:.2f}, p99 {ratio['latency_p99']:.2f}; "
          f"paced p50 {ratio['paced_latency_p50']:.2f}, p99 {ratio['paced_latency_p99']:.2f}; p50 per block "
          + ' '.join(f'{r:.2f}' for r in ratio['latency_p50_per_block']))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=2) + '\n')
    print(f'wrote {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
