"""How long a client that is already running takes to find a service whose process has just
started, with nothing of stars_ros in either: what bounds the ranker's first answer.

    python benchmarks/discovery_delay.py [--starts 12] [--out results/discovery_delay.json]

Each start: a client node (std_srvs/Trigger) is created in a ROS domain of its own, then a
plain rclpy server process starts there, creates its node (its DDS participant) either at once
or ``--late`` s after its start (the ranker before the lazy import: about 1 s of imports and
model), and then its service; the client polls ``service_is_ready`` every 10 ms. Reported: the
seconds from the server's process start to the service being ready, per start, for each of
the two moments, on Fast DDS's defaults (loopback, ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import rclpy  # noqa: E402
from rclpy.node import Node  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from stars_ros.evaluation.provenance import program_argv, run_record  # noqa: E402
from test_support.loopback import stop  # noqa: E402


def serve(participant_after: float, service_after: float):
    """The server: its node (participant) after ``participant_after`` s, its service after
    ``service_after`` s, both from the process's start (imports included)."""
    started = float(os.environ['DISCOVERY_STARTED'])
    rclpy.init()
    time.sleep(max(0.0, started + participant_after - time.time()))
    node = Node('discovery_server')
    time.sleep(max(0.0, started + service_after - time.time()))
    node.create_service(Trigger, 'ping', lambda request, response: response)
    try:
        rclpy.spin(node)
    except Exception:  # noqa: BLE001 - ended by the client's SIGTERM, however rclpy reports it
        pass


def one_start(domain: int, participant_after: float, service_after: float) -> float:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    node = Node('discovery_client', context=context)
    client = node.create_client(Trigger, 'ping')
    started = time.time()
    process = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), '--serve',
                                str(participant_after), str(service_after)],
                               env=dict(env, DISCOVERY_STARTED=repr(started)),
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        while not client.service_is_ready():
            if process.poll() is not None:
                raise RuntimeError(f'the server exited with {process.returncode}')
            time.sleep(0.01)
        return time.time() - started
    finally:
        stop(process, signal.SIGTERM)
        node.destroy_node()
        rclpy.shutdown(context=context)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--starts', type=int, default=12, help='server starts per moment')
    parser.add_argument('--late', type=float, default=1.0, help='s after its start a late server creates its node')
    parser.add_argument('--service-after', type=float, default=1.1, help='s after its start the service is created')
    parser.add_argument('--out', default=str(REPO / 'results' / 'discovery_delay.json'))
    parser.add_argument('--serve', nargs=2, type=float, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.serve:
        serve(*args.serve)
        return 0
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'  # the clients' contexts, as the servers'
    moments = {'participant_at_once': 0.0, 'participant_late': args.late}
    found = {name: [] for name in moments}
    for start in range(args.starts):
        for offset, (name, participant_after) in enumerate(moments.items()):  # interleaved: drift reaches both
            domain = 120 + 2 * ((os.getpid() + start) % 10) + offset
            found[name].append(one_start(domain, participant_after, args.service_after))
    summary = {}
    for name, seconds in found.items():
        # slow: found after the server's service existed by more than 1 s (one of Fast DDS's
        # periodic announcements, every 3 s by default, instead of discovery at once)
        slow = sum(s > args.service_after + 1.0 for s in seconds)
        summary[name] = {'seconds': [round(s, 3) for s in seconds], 'median_s': float(np.median(seconds)),
                         'slow_starts': int(slow)}
        print(f'{name}: service found after {", ".join(f"{s:.2f}" for s in seconds)} s; '
              f'{slow} of {len(seconds)} more than 1 s after it existed', flush=True)
    results = {**run_record(program_argv('benchmarks/discovery_delay.py', argv)), 'moments': summary,
               'settings': {'starts': args.starts, 'participant_late_s': args.late,
                            'service_after_s': args.service_after, 'middleware': 'Fast DDS defaults'}}
    Path(args.out).write_text(json.dumps(results, indent=2) + '\n')
    print(f'wrote {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
