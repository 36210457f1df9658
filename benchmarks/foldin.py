"""Fold-in cost per update, and whether it delays other users' rankings in a live node.

    python benchmarks/foldin.py [--checkpoint models/socnav1_gat_stars.pt] \
        [--data-root ../shared/datasets/socnav1] [--out results/foldin_benchmark.json]

1. ROS-free: SocNav1 annotators stream ``--ratings`` ratings each (default 200, the node's
   ``fold_in_max_ratings``); after each one the user is re-solved with ``FoldIn.fit`` from
   all their ratings so far, as the node does it (the rated scene's request text parsed
   again, its h the one its ranking computed). p50 / p99 by number of ratings. ``--people
   trained`` (default) folds each annotator in as the checkpoint's own person (their trained
   row's Gaussian update); ``new`` as a person it was not trained on ('new-' and the name),
   the robot's usual case: the scale mixture, and on a checkpoint with a plain encoder for
   strangers the hand-over (one more encoder pass per rating). ``--repeats`` runs it that many
   times, one after the other, and records each run's figures and their median.
2. Live node (its own process, loopback DDS, recording on): a client ranks scenes for user
   'other', one request in flight at a time, while user 'streamer' (another process, as
   another person's device would be) gets scenes ranked at ``--stream-rate`` per second.
   Condition A: the streamer gives no feedback; B: each of the streamer's rankings is
   followed by a feedback rating, with ``fold_in`` off (the feedback is validated and
   stored with an fsync, as before this feature); C: the same with ``fold_in`` on, so
   the node also folds every rating in. The three take turns in ``--blocks`` rounds of
   blocks (A B C, B C A, C A B, ...) under one streamer process whose feedback is switched
   on and off, so that the machine's drift during the run reaches all three alike.
   Latency of 'other' (send -> the ranking reaches the client's subscription callback) in
   each condition, same run, same node: C − B is what fold-in adds, B − A what recording
   feedback adds. The client subscribes to nothing else. The three conditions run for each of
   ``--gaps`` (seconds between a reply to 'other' and its next request): 0 keeps the node
   busy, so every solve competes with a waiting request; 0.01 is a perception rate, where
   the node idles between requests and waking it is part of each latency.
   The node's own account, from /diagnostics (collected by the streamer): how many rankings
   waited behind fold-in work, the longest such wait, and the longest processing time
   (reception to publication) of those rankings.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import torch
from threadpoolctl import threadpool_limits

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from offline_training.common import DEFAULT_SOCNAV1  # noqa: E402
from stars_ros.evaluation.provenance import git_state, machine  # noqa: E402
from stars_ros import messages  # noqa: E402
from stars_ros.personalisation.foldin import Rating, solve_ridge  # noqa: E402
from stars_ros.personalisation.stack import serving_stack  # noqa: E402
from stars_ros.model.predictor import Predictor  # noqa: E402
from stars_ros.data.scene_source import read_scenes  # noqa: E402

TARGET_P99_MS = 10.0  # the node's latency target (issue 4)


def percentiles(values) -> dict:
    values = np.asarray(values, dtype=float)
    return {'p50': float(np.percentile(values, 50)), 'p99': float(np.percentile(values, 99)),
            'max': float(values.max()), 'count': int(len(values))}


def time_updates(predictor, scenes_by_user: dict, regularisation: float, prefix: str = '') -> dict:
    """ms per update by rating count, as in the node: the newly rated scene's request text is
    parsed again, its h (and for a person served around the plain encoder, that encoder's
    scores) is the one its ranking computed (handed to the fold-in's cache), and
    the user is re-solved from all their ratings so far (``regularisation`` 0: the Gaussian
    posterior, the node's default; > 0: the ridge override). Reference, same run: the solve
    building every rating's regression row again (``design`` and the same solve). ``prefix``
    names each annotator as a person (``prefix`` + name)."""
    times, rebuilt = {}, {}
    messages.validator('scene_request')  # compiled once per process: the node has done it before any feedback
    for name, scenes in scenes_by_user.items():
        user = prefix + name
        foldin = serving_stack(predictor).require_foldin()
        texts = [json.dumps({'scene_id': s['identifier'], 'graph': s}) for s in scenes]
        ratings = []
        for n, (scene, text) in enumerate(zip(scenes, texts), 1):
            scored = predictor.rank_many(user, [messages.parse_scene_request(text)])[0]  # ranking the scene
            # computed its h (and the plain encoder's scores, for a person served around it) before the feedback came
            started = time.perf_counter()
            request = messages.parse_scene_request(text, messages.DEFAULT_MAX_BYTES)
            foldin.remember([request.graphs[0]], scored.h, plain=scored.plain)
            ratings.append(Rating(request.graphs[0], 'navigate', scene['score'] / 100, request.scene_id))
            model = foldin.fit(ratings, user, regularisation)
            times.setdefault(n, []).append((time.perf_counter() - started) * 1e3)
            started = time.perf_counter()
            x, c, z = foldin.design(ratings)
            if predictor.hands_over(user):
                c = c + foldin.hand_over_shift(ratings, x, c)
            theta = (solve_ridge(x, z - c, foldin.prior(user), regularisation) if regularisation else
                     foldin.posterior(x, z - c, np.zeros(len(z), dtype=int), user)[0])
            rebuilt.setdefault(n, []).append((time.perf_counter() - started) * 1e3)
            assert np.allclose(theta, np.append(model.p, model.b), atol=1e-8)
    return {'update_ms': {n: percentiles(v) for n, v in times.items()},
            'update_ms_all': percentiles([x for v in times.values() for x in v]),
            'reference_solve_rebuilding_rows_ms': {n: percentiles(v) for n, v in rebuilt.items()}}


def live(checkpoint: str, scenes: list, args) -> dict:
    from std_msgs.msg import String
    from test_support.loopback import RELIABLE, RosClient, start_node, stop

    domain = 150 + os.getpid() % 50
    client = RosClient(domain, listen=False)  # its only subscription: the rankings it times
    arrived = {}  # scene_id -> (when its ranking reached the client's callback (perf_counter), its processing_ms)

    def on_ranking(msg):
        now = time.perf_counter()
        with client._changed:
            reply = json.loads(msg.data)
            arrived[reply['scene_id']] = (now, reply['processing_ms'])
            client._changed.notify_all()

    client.node.create_subscription(String, '/stars/ranking', on_ranking, RELIABLE)
    with tempfile.TemporaryDirectory() as records:
        process = start_node('stars_ros.ros.ranker', domain, {'checkpoint': checkpoint, 'record_folder': records},
                             Path(records) / 'ranker.log')
        try:
            deadline = time.monotonic() + 120
            while not client.wait(lambda: 'probe' in arrived, 1.0):  # until the endpoints have matched
                if process.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError('the ranker did not answer')
                client.scene({'scene_id': 'probe', 'graph': scenes[0]})
            for k in range(50):  # warm-up
                client.scene({'scene_id': f'warm-{k}', 'user_id': 'other', 'graph': scenes[k % len(scenes)]})
            client.wait(lambda: 'warm-49' in arrived, 30)
            results = {f'gap_{gap:g}': measure_gap(client, domain, arrived, scenes, gap, args) for gap in args.gaps}
            stop(process, 2)
        finally:
            if process.poll() is None:
                process.kill()
            client.close()
    return results


CONDITIONS = {'without_feedback': (False, False), 'feedback_fold_in_off': (True, False),
              'feedback_fold_in_on': (True, True)}  # name: (streamer gives feedback, node's fold_in)


def measure_gap(client, domain: int, arrived, scenes, gap: float, args) -> dict:
    """Conditions A, B and C in ``--blocks`` rounds of blocks (A B C, B C A, ...) under one
    streamer, so that the machine's drift over the run reaches all alike; each condition's
    percentiles pool its blocks."""
    tag = f'{gap:g}'
    names = list(CONDITIONS)
    pooled, processing = {name: [] for name in names}, {name: [] for name in names}
    block_p99 = {name: [] for name in names}
    per_block = max(1, args.requests // args.blocks)
    with Streamer(domain, args, tag) as streamer:
        for round_ in range(args.blocks):
            for name in names[round_ % 3:] + names[:round_ % 3]:
                feedback, fold_in = CONDITIONS[name]
                if not client.set_parameters('/ranker', {'fold_in': fold_in})[0].successful:
                    raise RuntimeError('could not set fold_in')
                streamer.give_feedback(feedback)
                timed = time_other(client, arrived, scenes, f'{name}{round_}-{tag}', per_block, gap)
                latencies = [latency for latency, _ in timed]
                pooled[name] += latencies
                processing[name] += [node_ms for _, node_ms in timed]
                block_p99[name].append(float(np.percentile(latencies, 99)) if latencies else float('nan'))
    results = {name: {**summary(pooled[name], per_block * args.blocks), 'block_p99_ms': block_p99[name],
                      'other_processing_ms': percentiles(processing[name])} for name in names}
    results['streamed'] = streamer.counts
    return results


def summary(latencies: list, sent: int | None = None) -> dict:
    return {'other_latency_ms': percentiles(latencies), 'timeouts': (sent or len(latencies)) - len(latencies)}


def time_other(client, arrived, scenes, tag: str, count: int, gap: float) -> list:
    """(ms from send to the ranking's arrival, the node's processing_ms) for ``count``
    requests of 'other' (timeouts left out)."""
    latencies = []
    for k in range(count):
        scene_id = f'{tag}-other-{k}'
        text = json.dumps({'scene_id': scene_id, 'user_id': 'other', 'graph': scenes[k % len(scenes)]})
        sent = time.perf_counter()
        client.scene(text)
        if client.wait(lambda: scene_id in arrived, 5):
            received, node_ms = arrived[scene_id]
            latencies.append(((received - sent) * 1e3, node_ms))
        if gap:
            time.sleep(gap)
    return latencies


class Streamer:
    """The streaming user's process for a ``with`` block; ``counts`` once it has ended."""

    def __init__(self, domain: int, args, tag: str):
        from test_support.loopback import ros_env
        self.command = [sys.executable, __file__, '--streamer', '--data-root', args.data_root,
                        '--stream-rate', str(args.stream_rate), '--phase', tag]
        self.env = ros_env(domain)
        self.counts = {}

    def give_feedback(self, on: bool):
        """From the streamer's next ranking on, follow each with a rating (or not)."""
        self.process.stdin.write('feedback on\n' if on else 'feedback off\n')
        self.process.stdin.flush()
        time.sleep(0.5)  # ratings already sent reach the node and its store

    def __enter__(self):
        self.process = subprocess.Popen(self.command, env=self.env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                        text=True)
        if self.process.stdout.readline().strip() != 'ready':
            self.process.kill()
            raise RuntimeError(f'the streamer did not start (exit code {self.process.wait()})')
        return self

    def __exit__(self, *exc):
        self.process.send_signal(signal.SIGINT)
        output, _ = self.process.communicate(timeout=30)
        lines = output.strip().splitlines()
        if lines and lines[-1].startswith('{'):
            self.counts = json.loads(lines[-1])
        time.sleep(1.0)  # the node drains what the streamer left
        return False


def streamer_main(args) -> int:
    """The streamer user, a device of its own (own process): a SocNav1 scene ranked
    ``--stream-rate`` times a second, each followed by a feedback rating while the last line
    on its stdin was 'feedback on'. Prints 'ready' after the first ranking, and when
    interrupted a line of JSON: the number of requests, of ratings, of the user models the
    node folded in for it (stars/user_model), and the node's /diagnostics summed over the run."""
    import rclpy
    from rclpy.node import Node
    from rclpy.impl.implementation_singleton import rclpy_implementation
    from diagnostic_msgs.msg import DiagnosticArray
    from std_msgs.msg import String

    from test_support.loopback import RELIABLE
    from stars_ros.ros.spinning import spin_until_shutdown

    scenes = read_scenes(Path(args.data_root) / 'raw' / 'g.jsonl')[:200]
    rclpy.init()
    node = Node('streamer')
    scene_pub = node.create_publisher(String, '/stars/scene', RELIABLE)
    feedback_pub = node.create_publisher(String, '/stars/feedback', 100)
    answered = threading.Condition()
    replies = set()

    def on_ranking(msg):
        scene_id = json.loads(msg.data)['scene_id']
        if scene_id.startswith(f'{args.phase}-stream-'):
            with answered:
                replies.add(scene_id)
                answered.notify_all()

    node.create_subscription(String, '/stars/ranking', on_ranking, RELIABLE)
    models = []
    node.create_subscription(String, '/stars/user_model', lambda msg: models.append(len(msg.data)), RELIABLE)
    periods = []  # the ranker's per-period diagnostic values
    node.create_subscription(DiagnosticArray, '/diagnostics', lambda msg: periods.extend(
        {v.key: v.value for v in s.values} for s in msg.status if s.name.endswith(': ranker')), 100)
    threading.Thread(target=spin_until_shutdown, args=(node,), daemon=True).start()
    feedback = threading.Event()

    def follow_stdin():
        for line in sys.stdin:
            (feedback.set if line.strip() == 'feedback on' else feedback.clear)()

    threading.Thread(target=follow_stdin, daemon=True).start()
    k, rated, ready, deadline = 0, 0, False, time.monotonic() + 60
    try:
        while True:
            scene = scenes[k % len(scenes)]
            scene_id = f'{args.phase}-stream-{k}'
            scene_pub.publish(String(data=json.dumps({'scene_id': scene_id, 'user_id': 'streamer', 'graph': scene})))
            with answered:
                ok = answered.wait_for(lambda: scene_id in replies, 5 if ready else 0.5)
            if not ready:  # until the ranker's endpoints and ours have matched
                if not ok and time.monotonic() > deadline:
                    print('no ranker answered', flush=True)
                    return 1
                if ok:
                    ready = True
                    print('ready', flush=True)
            if ok and feedback.is_set():
                rated += 1
                feedback_pub.publish(String(data=json.dumps({'user_id': 'streamer', 'scene_id': scene_id,
                                                             'action': 'navigate', 'score': scene['score'] / 100})))
            k += 1
            time.sleep(1.0 / args.stream_rate)
    except KeyboardInterrupt:
        pass
    except rclpy_implementation.RCLError:  # rclpy's SIGINT handler shut the context down mid-publish
        if rclpy.ok():
            raise
    finally:
        print(json.dumps({'streamed_requests': k, 'feedback_ratings': rated, 'fold_in_updates': len(models),
                          'node_diagnostics': node_account(periods)}), flush=True)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def node_account(periods: list) -> dict:
    """The ranker's /diagnostics periods summed: rankings, fold-in updates, rankings that waited
    behind fold-in work, and the longest of the waits, of those rankings' processing and of
    any ranking's processing (ms, reception to publication)."""
    def total(key):
        return sum(int(p.get(key, 0)) for p in periods)

    def longest(key):
        return max((float(p[key]) for p in periods if key in p), default=None)
    return {'periods': len(periods), 'rankings': total('period.rankings'),
            'fold_in_updates': total('period.fold_in_updates'),
            'fold_in_update_ms_max': longest('period.fold_in_update_ms.max'),
            'rankings_delayed_by_fold_in': total('period.rankings_delayed_by_fold_in'),
            'fold_in_delay_ms_max': longest('period.fold_in_delay_ms.max'),
            'delayed_processing_ms_max': longest('period.delayed_processing_ms.max'),
            'processing_ms_max': longest('period.processing_ms.max'),
            'fold_in_update_ms_max_by_period': [float(p['period.fold_in_update_ms.max']) for p in periods
                                                if 'period.fold_in_update_ms.max' in p]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--checkpoint', default=str(REPO / 'models' / 'socnav1_gat_stars.pt'))
    parser.add_argument('--data-root', default=str(DEFAULT_SOCNAV1))
    parser.add_argument('--users', type=int, default=10, help='most annotators streaming ratings (part 1)')
    parser.add_argument('--ratings', type=int, default=200,
                        help='ratings each streams (part 1; annotators with fewer are left out)')
    parser.add_argument('--regularisation', type=float, default=0.0,
                        help="fold-in λ; 0 (default, the node's): the Gaussian posterior")
    parser.add_argument('--people', choices=('trained', 'new'), default='trained',
                        help="part 1's annotators as the checkpoint's own people, or as people it was not trained on")
    parser.add_argument('--no-live', action='store_true', help='part 1 only (no node started)')
    parser.add_argument('--repeats', type=int, default=1, help='runs of part 1, one after the other (their median)')
    parser.add_argument('--requests', type=int, default=1500, help="rankings of 'other' per condition")
    parser.add_argument('--blocks', type=int, default=6,
                        help='rounds of blocks (one block of each condition per round) into which they are split')
    parser.add_argument('--gaps', type=float, nargs='+', default=[0.0, 0.01],
                        help="seconds between a reply to 'other' and its next request, one set of conditions each")
    parser.add_argument('--stream-rate', type=float, default=50.0, help="streamer's rankings (+ feedback) per s")
    parser.add_argument('--out', default=str(REPO / 'results' / 'foldin_benchmark.json'))
    parser.add_argument('--streamer', action='store_true', help=argparse.SUPPRESS)
    parser.add_argument('--phase', default='', help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.streamer:
        return streamer_main(args)
    torch.set_num_threads(1)
    threadpool_limits(1, user_api='blas')  # as the node does
    predictor = Predictor.load(args.checkpoint)
    raw = Path(args.data_root) / 'raw'
    annotators = sorted(p.stem for p in raw.glob('*.jsonl'))
    scenes_by_user = {name: scenes[:args.ratings] for name in annotators
                      if len(scenes := read_scenes(raw / f'{name}.jsonl')) >= args.ratings}
    scenes_by_user = dict(list(scenes_by_user.items())[:args.users])
    runs = [time_updates(predictor, scenes_by_user, args.regularisation, 'new-' if args.people == 'new' else '')
            for _ in range(args.repeats)]
    offline = runs[0]
    print(f'{len(scenes_by_user)} annotators stream {args.ratings} ratings each, as {args.people} people')
    if args.repeats > 1:  # the machine drifts between runs: every run's figures, and their median
        offline['runs_update_ms_all'] = [run['update_ms_all'] for run in runs]
        offline['median_update_p50_ms'] = float(np.median([run['update_ms_all']['p50'] for run in runs]))
        print('update p50 / p99 of each run, all updates: '
              + ', '.join(f"{run['update_ms_all']['p50']:.3f} / {run['update_ms_all']['p99']:.3f} ms" for run in runs)
              + f"; median p50 {offline['median_update_p50_ms']:.3f} ms. Per length, the first run:")
    for n in sorted({1, 2, 5, 10, 20, 50, 100, 200, args.ratings} & set(offline['update_ms'])):
        update, reference = offline['update_ms'][n], offline['reference_solve_rebuilding_rows_ms'][n]
        print(f'{n:3d} ratings: update p50 {update["p50"]:.3f} ms p99 {update["p99"]:.3f} ms; reference, the '
              f'solve rebuilding every row: p50 {reference["p50"]:.3f} ms p99 {reference["p99"]:.3f} ms')
    node = {} if args.no_live else live(args.checkpoint, read_scenes(raw / 'b.jsonl')[:300], args)
    for gap in [] if args.no_live else args.gaps:
        figures = node[f'gap_{gap:g}']
        for phase in CONDITIONS:
            latency = figures[phase]['other_latency_ms']
            blocks = figures[phase].get('block_p99_ms')
            node_ms = figures[phase]['other_processing_ms']
            print(f"gap {gap * 1e3:g} ms, other user's ranking latency {phase.replace('_', ' ')}: "
                  f"p50 {latency['p50']:.2f} ms, p99 {latency['p99']:.2f} ms, max {latency['max']:.2f} ms "
                  f"({latency['count']} rankings, {figures[phase]['timeouts']} timeouts); in the node p50 "
                  f"{node_ms['p50']:.2f} ms, p99 {node_ms['p99']:.2f} ms, max {node_ms['max']:.2f} ms"
                  + (f"; p99 per block {' '.join(f'{v:.1f}' for v in blocks)}" if blocks else ''))
        streamed = figures['streamed']
        print(f"  streamer: {streamed.get('streamed_requests')} requests, {streamed.get('feedback_ratings')} of them "
              f"rated, {streamed.get('fold_in_updates')} fold-in updates")
        account = streamed.get('node_diagnostics', {})
        print(f"  node's account: {account.get('rankings')} rankings, {account.get('fold_in_updates')} fold-in updates "
              f"(longest {account.get('fold_in_update_ms_max')} ms); {account.get('rankings_delayed_by_fold_in')} "
              f"rankings waited behind fold-in work, at most {account.get('fold_in_delay_ms_max')} ms, and took at "
              f"most {account.get('delayed_processing_ms_max')} ms from reception to publication (any ranking: "
              f"{account.get('processing_ms_max')} ms)")
    results = {'checkpoint': args.checkpoint, 'fingerprint': predictor.fingerprint, 'settings': vars(args),
               'target_p99_ms': TARGET_P99_MS, 'offline': offline, 'node': node, 'machine': machine(),
               'git': git_state(),
               'load_average': [round(v, 2) for v in os.getloadavg()]}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=1) + '\n')
    print(f'wrote {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
