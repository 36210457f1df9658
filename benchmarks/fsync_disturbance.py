"""Does another process's fsync move a node's latency tail on this machine?

    python benchmarks/fsync_disturbance.py [--out results/fsync_disturbance.json]

The ranker journals each feedback rating with an fsync (so accepted feedback survives a
crash). In benchmarks/foldin.py other users' p99 rose when feedback streamed in even with
fold-in off. This isolates the disk: the benchmark's echo node (a trivial callback) is timed
back to back, one request in flight, in blocks that alternate between "quiet" and
"fsync": meanwhile a separate process appends a 3 kB line and fsyncs it ``--fsync-rate``
times a second (a feedback rating's size and a generous feedback rate).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / 'benchmarks'))

import node_latency  # noqa: E402
from offline_training.common import DEFAULT_SOCNAV1, machine  # noqa: E402
from stars_ros.scene_source import read_scenes  # noqa: E402


def fsync_loop(path: str, rate: float):
    with open(path, 'a') as handle:
        while True:
            handle.write('x' * 3000 + '\n')
            handle.flush()
            os.fsync(handle.fileno())
            time.sleep(1.0 / rate)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--data-root', default=str(DEFAULT_SOCNAV1))
    parser.add_argument('--blocks', type=int, default=8, help='blocks per condition, alternating')
    parser.add_argument('--per-block', type=int, default=400)
    parser.add_argument('--fsync-rate', type=float, default=10.0)
    parser.add_argument('--out', default=str(REPO / 'results' / 'fsync_disturbance.json'))
    parser.add_argument('--fsync-into', help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.fsync_into:
        fsync_loop(args.fsync_into, args.fsync_rate)
        return 0
    scenes = read_scenes(Path(args.data_root) / 'raw' / 'b.jsonl')
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', ROS_DOMAIN_ID=str(200 + os.getpid() % 30),
               PYTHONPATH=str(REPO) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    latencies = {'quiet': [], 'fsync': []}
    with tempfile.TemporaryDirectory() as folder:
        echo = node_latency.Served('echo', [sys.executable, str(REPO / 'benchmarks' / 'node_latency.py'), '--echo'],
                                   env, scenes, Path(folder) / 'echo.log')
        try:
            for block in range(args.blocks):
                for condition in (('quiet', 'fsync') if block % 2 == 0 else ('fsync', 'quiet')):
                    writer = None
                    if condition == 'fsync':
                        writer = subprocess.Popen([sys.executable, __file__, '--fsync-rate', str(args.fsync_rate),
                                                   '--fsync-into', str(Path(folder) / 'journal')])
                        time.sleep(0.3)
                    batch = node_latency.requests(scenes, f'{condition}-{block}', args.per_block)
                    latencies[condition] += node_latency.one_at_a_time(echo.client, batch, 0.0)
                    if writer is not None:
                        writer.kill()
                        writer.wait()
        finally:
            echo.stop()
    results = {condition: {'p50': float(np.percentile(v, 50)), 'p99': float(np.percentile(v, 99)),
                           'p99_9': float(np.percentile(v, 99.9)), 'max': float(np.max(v)), 'count': len(v)}
               for condition, v in latencies.items()}
    results['settings'] = {**{k: v for k, v in vars(args).items() if k != 'fsync_into'}, 'machine': machine()}
    for condition in ('quiet', 'fsync'):
        r = results[condition]
        print(f"echo, {condition:5s}: p50 {r['p50']:.2f} ms, p99 {r['p99']:.2f} ms, p99.9 {r['p99_9']:.2f} ms, "
              f"max {r['max']:.2f} ms ({r['count']} requests)")
    Path(args.out).write_text(json.dumps(results, indent=1) + '\n')
    print(f'wrote {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
