"""Does another process's fsync move a node's latency tail on this machine?

    python benchmarks/fsync_disturbance.py [--out results/fsync_disturbance.json]

The ranker commits each batch of feedback to its state store with an fsync (so accepted
feedback survives a crash); a journal appended and fsync'd per rating came before it. In
benchmarks/foldin.py other users' p99 rose when feedback streamed in even with fold-in off.
This isolates the disk: the benchmark's echo node (a trivial callback) is timed back to back,
one request in flight, in blocks that cycle through ``--conditions`` (the order rotating from
block to block, so the VM's drift reaches all alike). In every condition
but ``quiet`` a separate process writes a 3 kB line (a feedback rating's size)
``--fsync-rate`` times a second (a generous feedback rate), in one of these ways:
  * ``write``: to the OS only, no sync (the control: a process waking up and writing);
  * ``append-fsync``: appended and fsync'd, as a per-rating journal does;
  * ``overwrite-fdatasync``: written in place into a file zero-filled beforehand and
    fdatasync'd: no size change and no block allocation, so no filesystem-journal commit
    (how write-ahead logs avoid one).
Each writer is timed only once it says it is ready: its start-up (imports, the zero fill)
is not part of any block. (Before, a writer got 0.3 s to start, less than its imports take,
and the first version's "fsync" blocks timed mostly that start-up.)
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
from offline_training.common import DEFAULT_SOCNAV1  # noqa: E402
from stars_ros.evaluation.provenance import git_state, machine  # noqa: E402
from stars_ros.data.scene_source import read_scenes  # noqa: E402


LINE = b'x' * 3000 + b'\n'
WRITERS = ('write', 'append-fsync', 'overwrite-fdatasync')


def writer_loop(path: str, rate: float, mode: str):
    """Write ``LINE`` ``rate`` times a second into ``path`` the way ``mode`` says, forever."""
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND * (mode != 'overwrite-fdatasync'))
    if mode == 'overwrite-fdatasync':
        os.write(descriptor, bytes(len(LINE) * 2000))  # zero-filled and on disk before timing starts
        os.fsync(descriptor)
        os.lseek(descriptor, 0, os.SEEK_SET)
    print('ready', flush=True)
    for count in range(1, 1 << 62):
        os.write(descriptor, LINE)
        if mode == 'append-fsync':
            os.fsync(descriptor)
        elif mode == 'overwrite-fdatasync':
            os.fdatasync(descriptor)
            if count % 2000 == 0:
                os.lseek(descriptor, 0, os.SEEK_SET)
        time.sleep(1.0 / rate)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--data-root', default=str(DEFAULT_SOCNAV1))
    parser.add_argument('--blocks', type=int, default=8, help='blocks per condition, alternating')
    parser.add_argument('--per-block', type=int, default=400)
    parser.add_argument('--fsync-rate', type=float, default=10.0, help='writes per second')
    parser.add_argument('--conditions', nargs='+', default=['quiet', *WRITERS], choices=['quiet', *WRITERS])
    parser.add_argument('--out', default=str(REPO / 'results' / 'fsync_disturbance.json'))
    parser.add_argument('--write-into', help=argparse.SUPPRESS)
    parser.add_argument('--mode', choices=WRITERS, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.write_into:
        writer_loop(args.write_into, args.fsync_rate, args.mode)
        return 0
    scenes = read_scenes(Path(args.data_root) / 'raw' / 'b.jsonl')
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', ROS_DOMAIN_ID=str(200 + os.getpid() % 30),
               PYTHONPATH=str(REPO) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    latencies = {condition: [] for condition in args.conditions}
    with tempfile.TemporaryDirectory() as folder:
        echo = node_latency.Served('echo', [sys.executable, str(REPO / 'benchmarks' / 'node_latency.py'), '--echo'],
                                   env, scenes, Path(folder) / 'echo.log')
        try:
            for block in range(args.blocks):
                shift = block % len(args.conditions)
                for condition in args.conditions[shift:] + args.conditions[:shift]:
                    writer = None
                    if condition != 'quiet':
                        writer = subprocess.Popen([sys.executable, __file__, '--fsync-rate', str(args.fsync_rate),
                                                   '--mode', condition, '--write-into',
                                                   str(Path(folder) / f'{condition}-{block}')],
                                                  stdout=subprocess.PIPE, text=True)
                        if writer.stdout.readline().strip() != 'ready':  # its imports and set-up are over
                            raise RuntimeError(f'the {condition} writer did not start')
                        time.sleep(0.5)
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
    results['settings'] = {**{k: v for k, v in vars(args).items() if k not in ('write_into', 'mode')},
                           'machine': machine(), 'git': git_state()}
    for condition in args.conditions:
        r = results[condition]
        print(f"echo, {condition:19s}: p50 {r['p50']:.2f} ms, p99 {r['p99']:.2f} ms, p99.9 {r['p99_9']:.2f} ms, "
              f"max {r['max']:.2f} ms ({r['count']} requests)")
    Path(args.out).write_text(json.dumps(results, indent=1) + '\n')
    print(f'wrote {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
