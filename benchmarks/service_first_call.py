"""Fresh client processes, each calling the ranker's ~/rank_candidates the moment the service
appears to it: how many get their answer, on the middleware's defaults.

    python benchmarks/service_first_call.py [--clients 200] [--parallel 4] \
        [--out results/service_first_call.json]

One ranker (the package's defaults: the packaged checkpoint, Fast DDS's default profile,
FASTRTPS_DEFAULT_PROFILES_FILE and FASTDDS_DEFAULT_PROFILES_FILE unset, unlike the test
suite's) in a ROS domain of this process's own (``loopback.domain_id``, as the tests reserve
theirs, discovery on this machine only). Then ``--clients`` processes, ``--parallel`` at a
time: each creates its node and a RankCandidates client, polls ``service_is_ready`` every
millisecond and calls at once with a request the ranker refuses (no candidates: its answer is
a refusal, the cheapest one), waiting up to ``--answer-timeout`` s. rmw_fastrtps drops a
response whose client's reply reader the service has not matched within its writer's
``max_blocking_time`` (rclpy warns "failed to send response (timeout)"): such a client waits
for ever; the ranker sends such a response again (``stars_ros.ros.replies``) and logs it. Reported:
answers, calls left unanswered, how long the answers took, and the ranker's log lines on
dropped responses (sent again, given up, or rclpy's own warning).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from stars_ros.evaluation.provenance import git_state, machine  # noqa: E402
from test_support.loopback import domain_id, ros_env, stop  # noqa: E402

SERVICE = '/ranker/rank_candidates'
PROFILE_VARIABLES = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')


def client_main(timeout: float) -> int:
    """One fresh client: the service found, one call, one JSON line on stdout."""
    import rclpy
    from rclpy.node import Node
    from stars_ros_msgs.srv import RankCandidates

    started = time.monotonic()
    rclpy.init()
    node = Node(f'first_call_{os.getpid()}')
    client = node.create_client(RankCandidates, SERVICE)
    while not client.service_is_ready():
        time.sleep(0.001)
    found = time.monotonic()
    future = client.call_async(RankCandidates.Request(scene_id=f'first-{os.getpid()}'))
    rclpy.spin_until_future_complete(node, future, timeout_sec=timeout)
    answered = time.monotonic()
    result = {'answered': future.done(), 'found_s': found - started,
              'answer_s': answered - found if future.done() else None}
    print(json.dumps(result), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def one_client(env: dict, timeout: float) -> dict:
    command = [sys.executable, str(Path(__file__).resolve()), '--client', '--answer-timeout', str(timeout)]
    done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=timeout + 120)
    lines = [line for line in done.stdout.splitlines() if line.startswith('{')]
    if done.returncode != 0 or not lines:
        return {'answered': False, 'failed': f'exit {done.returncode}: {done.stderr[-500:]}'}
    return {**json.loads(lines[-1]), 'warnings': done.stderr.count('RuntimeWarning')}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--clients', type=int, default=200)
    parser.add_argument('--parallel', type=int, default=4)
    parser.add_argument('--answer-timeout', type=float, default=10.0, help='s a client waits for its answer')
    parser.add_argument('--out', default=str(REPO / 'results' / 'service_first_call.json'))
    parser.add_argument('--client', action='store_true', help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.client:
        return client_main(args.answer_timeout)
    env = ros_env(domain_id(0))
    for name in PROFILE_VARIABLES:
        env.pop(name, None)
    with tempfile.TemporaryDirectory() as records:
        log = Path(records) / 'ranker.log'
        ranker = subprocess.Popen([sys.executable, '-m', 'stars_ros.ros.ranker', '--ros-args', '-p',
                                   f'record_folder:={records}'], env=env, stdout=log.open('w'),
                                  stderr=subprocess.STDOUT)
        try:
            first = one_client(env, 120.0)  # waits for the ranker to come up, then calls
            if not first['answered']:
                raise RuntimeError(f'the ranker did not answer a first client: {first}\n'
                                   + log.read_text()[-2000:])
            started = time.monotonic()
            with ThreadPoolExecutor(args.parallel) as pool:
                results = list(pool.map(lambda _: one_client(env, args.answer_timeout), range(args.clients)))
            took = time.monotonic() - started
        finally:
            stopped = stop(ranker, signal.SIGINT) if ranker.poll() is None else ranker.returncode
        text = log.read_text()
        dropped = {'sent_again': text.count('had dropped was sent again'),  # stars_ros.ros.replies
                   'given_up': text.count('a response could not be sent'),
                   'dropped_unnoticed': text.count('failed to send response')}  # rclpy's own warning
    answers = [r['answer_s'] for r in results if r['answered']]
    summary = {'clients': args.clients, 'answered': len(answers), 'unanswered': args.clients - len(answers),
               'failed_processes': sum('failed' in r for r in results),
               'responses_the_middleware_dropped': dropped,
               'answer_s': {'p50': float(np.median(answers)), 'p99': float(np.percentile(answers, 99)),
                            'max': float(np.max(answers))} if answers else None,
               'found_s_p50': float(np.median([r['found_s'] for r in results if 'found_s' in r])),
               'wall_s': took, 'ranker_exit': stopped,
               'settings': {'parallel': args.parallel, 'answer_timeout_s': args.answer_timeout,
                            'service': SERVICE, 'profile': 'Fast DDS defaults (no profiles file)',
                            'machine': machine(), 'git': git_state()}}
    print(f"{summary['answered']} of {args.clients} fresh clients answered, "
          f"{summary['unanswered']} unanswered "
          f"({args.parallel} clients at a time, {took:.0f} s); responses the middleware dropped: {dropped}")
    if answers:
        print(f"answer after the call: p50 {summary['answer_s']['p50'] * 1e3:.1f} ms, "
              f"p99 {summary['answer_s']['p99'] * 1e3:.1f} ms, max {summary['answer_s']['max'] * 1e3:.1f} ms")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(summary, indent=2) + '\n')
    print(f'wrote {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
