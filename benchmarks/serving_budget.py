"""The ranker's serving budgets, measured from outside: time to a first answer, and both
request paths' latency against an echo floor, over several runs.

    python benchmarks/serving_budget.py [--runs 5] [--count 400] [--blocks 8] \
        [--data-root ../shared/datasets/socnav1] [--out results/serving_budget.json]

Each run starts a fresh ranker process (packaged model, recording on) in a ROS domain of its
own and an echo node in another:
  * first answer: from just before the ranker's process starts to the first answer of its
    typed service ~/rank_actions, called as soon as the service is discovered; the ranker's
    own log line "serving ..." (the model loaded) splits it into the start (imports, model)
    and the rest (node, discovery, the call);
  * the end: seconds from SIGTERM until each node's process ended (None: still running after
    30 s, then killed);
  * latency: ``--count`` requests per node on each path, one in flight at a time, in
    ``--blocks`` blocks alternating between the ranker and the echo (this VM's speed drifts
    within minutes): the JSON path (std_msgs/String on stars/scene → stars/ranking) and the
    typed service (stars_ros_msgs/srv/RankActions), the same SocNav1 scenes on both.
The echo floor is a plain rclpy node spun by ``rclpy.spin``, of the same message types: it
republishes each JSON request on stars/ranking and answers ~/rank_actions with the request's
scene id, so it carries none of the ranker's machinery. Ratios are ranker / echo of p50 and
p99 in the same run; the summary gives every run and the median of the runs.

*Own work*, after the runs, in this process: the ranker's core (``RankerCore``, packaged model,
recording on) serving the same JSON requests with no middleware, p50 of each step of one
request (parsing and validating; featurising, encoding and scoring with ``score_sd``; the
reply written; the request and reply recorded) and of the whole. Whatever the node around it
does, its JSON p50 cannot be below the echo's plus this work, so ``bound`` = 1 + own work /
echo p50 is the lowest ratio the run allowed. The same for the typed service: the request's
JSON twin made, ranked at once (``RankerCore.rank_now``) and the typed response built; the
recording and markers, which the node does after the reply, are outside it.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / 'benchmarks'))

import rclpy  # noqa: E402
from rclpy.executors import ExternalShutdownException  # noqa: E402
from rclpy.node import Node  # noqa: E402
from std_msgs.msg import String  # noqa: E402
from stars_ros_msgs.srv import RankActions  # noqa: E402

import node_latency  # noqa: E402  (the JSON path's client and requests)
import service_latency  # noqa: E402  (the typed service's caller and requests)
from offline_training.common import DEFAULT_SOCNAV1  # noqa: E402
from stars_ros.evaluation.provenance import program_argv, run_record  # noqa: E402
from test_support.loopback import stop  # noqa: E402
from stars_ros.data.scene_source import read_scenes  # noqa: E402

LOADED = re.compile(r'\[(\d+\.\d+)\] \[ranker\]: serving ')


def echo_main():
    """The echo floor: both paths answered at once, spun by plain rclpy.spin."""
    rclpy.init()
    node = Node('ranker')
    publisher = node.create_publisher(String, 'stars/ranking', node_latency.QOS)
    node.create_subscription(String, 'stars/scene', publisher.publish, node_latency.QOS)

    def answer(request, response):
        response.success = True
        response.ranking.scene_id = request.scene_id
        return response
    node.create_service(RankActions, '~/rank_actions', answer)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):  # SIGINT, SIGTERM: the normal end
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


class Served:
    """A node's process and a client of each path, in the node's own domain."""

    def __init__(self, name: str, command: list, env: dict, log: Path):
        self.name, self.log = name, log
        self.started_wall, started = time.time(), time.perf_counter()
        self.process = subprocess.Popen(command, env=env, stdout=log.open('w'), stderr=subprocess.STDOUT)
        domain = int(env['ROS_DOMAIN_ID'])
        self.caller = service_latency.Caller(domain, name)
        while not self.caller.client.wait_for_service(timeout_sec=1.0):
            self.check_running()
        seconds, response = self.caller.call(service_latency.typed_requests(SCENES, f'{name}-first', 1)[0], 30.0)
        if response is None or not response.success:
            self.check_running()
            raise RuntimeError(f'{name} did not answer its first call: {response}')
        self.first_answer_s = time.perf_counter() - started
        self.client = node_latency.Client(domain, name)
        while not self.client.publisher.get_subscription_count():
            self.check_running()
            time.sleep(0.05)
        for scene_id, text in node_latency.requests(SCENES, f'{name}-warmup', 100):
            self.client.send(text)
            if not self.client.wait_for(scene_id, 5.0):
                self.check_running()
        for request in service_latency.typed_requests(SCENES, f'{name}-warmup', 100):
            self.caller.call(request)

    def loaded_after_s(self) -> float | None:
        """Seconds from the process's start to the ranker's "serving ..." log line."""
        found = LOADED.search(self.log.read_text())
        return None if found is None else float(found.group(1)) - self.started_wall

    def check_running(self):
        if self.process.poll() is not None:
            raise RuntimeError(f'{self.name} exited with {self.process.returncode}: {self.log.read_text()[-2000:]}')

    def stop(self) -> float | None:
        """SIGTERM the node; seconds until its process ended, None if it had not within 30 s
        (it is then killed: one hung end must not lose the run's figures)."""
        self.client.close()
        self.caller.close()
        started = time.perf_counter()
        try:
            stop(self.process, signal.SIGTERM)
        except subprocess.TimeoutExpired:
            return None
        return time.perf_counter() - started


def typed_alternating(served: dict, count: int, blocks: int) -> dict:
    """Round trips (ms) of ``count`` typed calls per node, in alternating blocks."""
    times = {name: [] for name in served}
    names = list(served)
    for block in range(blocks):
        for name in (names if block % 2 == 0 else names[::-1]):
            for request in service_latency.typed_requests(SCENES, f'{name}-typed-{block}', max(1, count // blocks)):
                seconds, response = served[name].caller.call(request)
                if response is not None and response.success:
                    times[name].append(seconds * 1e3)
    return times


def percentiles(values: list) -> dict:
    return {'p50': float(np.percentile(values, 50)), 'p99': float(np.percentile(values, 99)), 'count': len(values)}


def one_run(run: int, count: int, blocks: int) -> dict:
    domain = 150 + 2 * ((os.getpid() + run) % 25)  # the echo's; the ranker's is the next one
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               PYTHONPATH=str(REPO) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    with tempfile.TemporaryDirectory() as records:
        commands = {'echo': [sys.executable, str(Path(__file__).resolve()), '--echo'],
                    'ranker': [sys.executable, '-m', 'stars_ros.ros.ranker', '--ros-args', '-p',
                               f'record_folder:={records}', '-p', f'queue_depth:={node_latency.QUEUE_DEPTH}']}
        served = {}
        try:
            for offset, (name, command) in enumerate(commands.items()):
                served[name] = Served(name, command, dict(env, ROS_DOMAIN_ID=str(domain + offset)),
                                      Path(records) / f'{name}.log')
            json_ms, _ = node_latency.alternating(served, SCENES, 'json', count, blocks, 0.0)
            typed_ms = typed_alternating(served, count, blocks)
            result = {'first_answer_s': served['ranker'].first_answer_s,
                      'model_loaded_after_s': served['ranker'].loaded_after_s(),
                      'json': {name: percentiles(json_ms[name]) for name in served},
                      'typed': {name: percentiles(typed_ms[name]) for name in served}}
        finally:
            ended = {name: node.stop() for name, node in served.items()}
    result['ended_after_sigterm_s'] = ended  # None: still running 30 s after SIGTERM, killed
    for path in ('json', 'typed'):
        result[path]['ratio'] = {q: result[path]['ranker'][q] / result[path]['echo'][q] for q in ('p50', 'p99')}
    return result


def own_work(count: int) -> dict:
    """p50 (ms) of each step of the ranker's core serving one JSON request in this process,
    and of ``accept_scene`` + ``work`` together (``whole``), as the node's scene callback runs them."""
    from threadpoolctl import threadpool_limits

    from stars_ros import messages, typed_messages
    from stars_ros_msgs import msg as typed
    from stars_ros.node.batching import Pending, rank_batch
    from stars_ros.node.core import RankerCore
    from stars_ros.node.parameters import PARAMETERS, TOPICS

    quiet = logging.getLogger('serving_budget.own_work')  # the core's log lines go nowhere
    quiet.addHandler(logging.NullHandler())
    quiet.propagate = False
    threadpool_limits(1, user_api='blas')  # as the node does
    steps = {name: [] for name in ('parse_validate', 'score', 'reply', 'record', 'whole',
                                   'typed_convert', 'typed_rank', 'typed_reply', 'typed_whole')}
    with tempfile.TemporaryDirectory() as records:
        params = {name: spec[0] for name, spec in PARAMETERS.items()}
        params['record_folder'] = records
        core = RankerCore(params, {topic: '/' + topic for topic in TOPICS}, '/ranker', lambda topic, text: None,
                          quiet, time.time_ns)
        try:
            for k, (_, text) in enumerate(node_latency.requests(SCENES, 'own', count + 100)):
                warm = k >= 100
                started = time.perf_counter()
                core.accept_scene(text, time.time_ns())
                while core.work():
                    pass
                whole = time.perf_counter()
                request = messages.parse_scene_request(text, params['max_message_bytes'])
                parsed = time.perf_counter()
                scored = rank_batch(core.predictor, [Pending(request, request.user_id, 0)], params['top_k'],
                                    core.personalisation.uncertainty, (params['explain'],
                                                                       params['explain_entities']))[0]
                ranked = time.perf_counter()
                reply = messages.dumps(messages.ranking_payload(
                    request, request.user_id, False, scored.ranked, core.predictor.fingerprint, 0.0, scored.action,
                    0, scored.p_first_is_best))
                replied = time.perf_counter()
                core.record('stars/scene', text)
                core.record('stars/ranking', reply)
                recorded = time.perf_counter()
                if warm:
                    for name, (begin, end) in {'whole': (started, whole), 'parse_validate': (whole, parsed),
                                               'score': (parsed, ranked), 'reply': (ranked, replied),
                                               'record': (replied, recorded)}.items():
                        steps[name].append((end - begin) * 1e3)
            for k, request in enumerate(service_latency.typed_requests(SCENES, 'own-typed', count + 100)):
                started = time.perf_counter()
                twin = typed_messages.rank_actions_twin(request, params['frame_id'])
                converted = time.perf_counter()
                payload, _ = core.rank_now(twin, time.time_ns(), time.time_ns(), '/ranker/rank_actions')
                ranked = time.perf_counter()
                RankActions.Response(success=True, ranking=typed_messages.ranking_message(payload, typed))
                replied = time.perf_counter()
                while core.work():  # the recording and markers, after the reply as the node does
                    pass
                if k >= 100:
                    for name, (begin, end) in {'typed_whole': (started, replied), 'typed_convert': (started, converted),
                                               'typed_rank': (converted, ranked),
                                               'typed_reply': (ranked, replied)}.items():
                        steps[name].append((end - begin) * 1e3)
        finally:
            core.close()
    return {f'{name}_ms_p50': float(np.median(values)) for name, values in steps.items()}


def main(argv=None) -> int:
    global SCENES
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--runs', type=int, default=5)
    parser.add_argument('--count', type=int, default=400, help='requests per node and path in a run')
    parser.add_argument('--blocks', type=int, default=8)
    parser.add_argument('--data-root', default=str(DEFAULT_SOCNAV1))
    parser.add_argument('--out', default=str(REPO / 'results' / 'serving_budget.json'))
    parser.add_argument('--echo', action='store_true', help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.echo:
        echo_main()
        return 0
    SCENES = read_scenes(Path(args.data_root) / 'raw' / 'b.jsonl')
    runs = []
    for run in range(args.runs):
        result = one_run(run, args.count, args.blocks)
        runs.append(result)
        print(f"run {run + 1}: first answer {result['first_answer_s']:.2f} s (model loaded after "
              f"{result['model_loaded_after_s']:.2f} s); JSON p50 {result['json']['ranker']['p50']:.2f} / "
              f"{result['json']['echo']['p50']:.2f} ms = {result['json']['ratio']['p50']:.2f}, p99 ratio "
              f"{result['json']['ratio']['p99']:.2f}; typed p50 {result['typed']['ranker']['p50']:.2f} / "
              f"{result['typed']['echo']['p50']:.2f} ms = {result['typed']['ratio']['p50']:.2f}, p99 ratio "
              f"{result['typed']['ratio']['p99']:.2f}", flush=True)
    median = {'first_answer_s': float(np.median([r['first_answer_s'] for r in runs])),
              'model_loaded_after_s': float(np.median([r['model_loaded_after_s'] for r in runs])),
              **{f'{path}_{q}_ratio': float(np.median([r[path]['ratio'][q] for r in runs]))
                 for path in ('json', 'typed') for q in ('p50', 'p99')}}
    print('median of runs: ' + ', '.join(f'{k} {v:.2f}' for k, v in median.items()))
    work = own_work(args.count)
    for result in runs:
        result['json']['bound'] = 1 + work['whole_ms_p50'] / result['json']['echo']['p50']
        result['typed']['bound'] = 1 + work['typed_whole_ms_p50'] / result['typed']['echo']['p50']
    print('own work in process (p50 ms): ' + ', '.join(f'{k} {v:.3f}' for k, v in work.items())
          + '; lowest p50 ratio each run allowed, JSON: ' + ', '.join(f"{r['json']['bound']:.2f}" for r in runs)
          + '; typed: ' + ', '.join(f"{r['typed']['bound']:.2f}" for r in runs), flush=True)
    results = {**run_record(program_argv('benchmarks/serving_budget.py', argv)), 'runs': runs, 'median_of_runs': median,
               'own_work': work,
               'settings': {'runs': args.runs, 'count': args.count, 'blocks': args.blocks,
                            'checkpoint': 'packaged default', 'scenes': 'SocNav1 b.jsonl'}}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=2) + '\n')
    print(f'wrote {args.out}')
    return 0


SCENES: list = []

if __name__ == '__main__':
    sys.exit(main())
