"""From a ROS4HRI fact to a ranking: the hri_bridge in front of the ranker, against the ranker
alone, in the same run.

    python benchmarks/hri_latency.py [--people 20] [--count 200] [--out results/hri_latency.json]

Needs hri_msgs (a ROS install's, or the tests' stand-in built into .venv:
``bash scripts/build_interfaces.sh test/interfaces/hri_msgs``). Starts the ranker (packaged
checkpoint, recording on) and the bridge (``pose_source:=topic``, six placements, ``rate``
so low that only changes send scenes), each in its own process on loopback DDS in a domain of
their own. A client in this process plays a ROS4HRI world of ``--people`` tracked, recognised
people (poses at 10 Hz; the bridge's ``max_age`` ``--max-age``) and times, one request in
flight at a time:

* **bridge**: an engagement message that changes who is served (person k engages, k − 1
  disengages) → the ranking for person k of the scene the bridge sends on that change (the
  bridge looks at its facts every 50 ms, which is part of what this measures);
* **ranker alone**: the same scene request the bridge sent, published by the client straight
  to stars/scene → its ranking.

The two alternate in ``--blocks`` blocks (this VM's speed drifts within minutes). p50 / p99 /
max in ms.
"""
from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from stars_ros.evaluation.provenance import program_argv, run_record  # noqa: E402
from stars_ros.hri.people import DISENGAGED, ENGAGED  # noqa: E402
from test_support.loopback import RELIABLE, RosClient, domain_id, start_node, stop  # noqa: E402


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--people', type=int, default=20)
    parser.add_argument('--count', type=int, default=200, help='timed requests per path (default: %(default)s)')
    parser.add_argument('--blocks', type=int, default=10)
    parser.add_argument('--max-age', type=float, default=3.0,
                        help="the bridge's max_age: generous, so that a loaded machine's late poses do not drop "
                             'people from the timed scenes (default: %(default)s s)')
    parser.add_argument('--out', type=Path, default=REPO / 'results' / 'hri_latency.json')
    return parser.parse_args(argv)


def summary(values: list) -> dict:
    v = np.asarray(values) * 1e3
    return {'n': len(v), 'p50_ms': float(np.percentile(v, 50)), 'p99_ms': float(np.percentile(v, 99)),
            'max_ms': float(v.max())}


def main(argv=None) -> int:
    args = parse_args(argv)
    from stars_ros.ros.hri_world import World
    work = Path(tempfile.mkdtemp(prefix='hri-latency-'))
    domain = domain_id(0)
    client = RosClient(domain)
    world = World(client.node, 'base_link', use_tf=False)
    ids = [f'p{k}' for k in range(args.people)]
    poses = {pid: (1.0 + 0.4 * k * math.cos(k), 0.4 * k * math.sin(k), 0.1 * k) for k, pid in enumerate(ids)}
    levels = {pid: DISENGAGED for pid in ids}
    scenes = client.collect('/stars/scene', RELIABLE)

    ticks = [0]

    def publish_world():
        """Poses at 10 Hz, engagement again at 1 Hz (changes go out at once, below)."""
        ticks[0] += 1
        for pid, pose in poses.items():
            world.pose(pid, *pose)
            if ticks[0] % 10 == 0:
                world.engage(pid, levels[pid])
    client.node.create_timer(0.1, publish_world)
    ranker = start_node('stars_ros.ros.ranker', domain, {'record_folder': str(work / 'records')}, work / 'ranker.log')
    bridge = start_node('stars_ros.ros.hri_bridge', domain, {'pose_source': 'topic', 'rate': 0.001,
                                                                   'max_age': args.max_age},
                        work / 'bridge.log')
    timings = {'bridge': [], 'ranker alone': []}
    try:
        client.wait_ready(ranker, 120, {'scene_id': 'probe', 'graph': {
            'humans': [{'id': 1, 'xPos': 0.0, 'yPos': 100.0, 'orientation': 0.0}], 'objects': [], 'links': [],
            'room': [[-300, -300], [300, -300], [300, 300], [-300, 300], [-300, -300]]}})
        world.track(ids)
        for pid in ids:
            world.anonymous(pid, False)
        def tracking_all():  # the bridge's /diagnostics say it has the tracked list
            return any(kv.key == 'tracked' and kv.value == str(args.people) for array in client.diagnostics
                       for status in array.status if status.name.endswith('hri_bridge') for kv in status.values)
        if not client.wait(tracking_all, 120):
            raise TimeoutError('the bridge did not take the tracked list')
        served = 0

        def through_bridge():
            nonlocal served
            previous, served = ids[served % len(ids)], (served + 1) % len(ids)
            target, count = ids[served], len(client.rankings)
            started = time.perf_counter()
            levels[target], levels[previous] = ENGAGED, DISENGAGED
            world.engage(target, ENGAGED)
            world.engage(previous, DISENGAGED)
            if not client.wait(lambda: any(r['user_id'] == target for r in client.rankings[count:]), 30):
                raise TimeoutError(f'no ranking for {target}')
            return time.perf_counter() - started

        def ranker_alone(k):
            request = dict(next(s for s in reversed(scenes) if s.get('user_id')), scene_id=f'direct-{k}')
            started = time.perf_counter()
            client.scene(request)
            if not client.wait(lambda: client.ranking_for(request['scene_id']) is not None, 30):
                raise TimeoutError('no ranking')
            return time.perf_counter() - started

        for _ in range(5):  # warm-up: discovery, first solves
            through_bridge()
            ranker_alone(-1)
        per_block = max(1, args.count // args.blocks)
        for block in range(args.blocks):
            order = ('bridge', 'ranker alone') if block % 2 == 0 else ('ranker alone', 'bridge')
            for path in order:
                for k in range(per_block):
                    timings[path].append(through_bridge() if path == 'bridge' else ranker_alone(block * per_block + k))
        humans = [len(s['candidates'][0]['graph']['humans']) for s in scenes if s.get('user_id')]
    finally:
        for process in (bridge, ranker):
            if process.poll() is None:
                stop(process, signal.SIGINT)
        client.close()
    result = {**run_record(program_argv('benchmarks/hri_latency.py', argv)),
              'people_tracked': args.people, 'placements': 6, 'max_age_s': args.max_age,
              'humans_per_bridge_scene': {'min': min(humans), 'max': max(humans), 'median': float(np.median(humans))},
              **{path: summary(values) for path, values in timings.items()}}
    result['bridge_minus_ranker_p50_ms'] = result['bridge']['p50_ms'] - result['ranker alone']['p50_ms']
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + '\n')
    print(json.dumps({k: v for k, v in result.items() if k != 'machine'}, indent=1))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
