"""Forgetting a person at scale: how long ``~/forget_person`` takes on a record folder of
1,000 people × 200 ratings with about 100 MB of bags, and what it costs other people's
rankings meanwhile (docs/privacy.md; issue 49's goal: their p99 at most 2× the idle node's).

    python benchmarks/forget_scale.py [--people 1000] [--ratings 200] [--bag-mb 100] \
        [--forgets 3] [--data-root ../shared/datasets/socnav1] [--out results/forget_scale.json]

The record folder is filled in this process: the state store as ``state_scale`` fills it
(every person with a solved model and covariance of the packaged checkpoint and their
ratings of real SocNav1 scenes), and one finished bag of scene requests and feedback that
name them (each request with its whole scene graph), the people taking turns, so every file
names every person, until the bag's files reach ``--bag-mb`` MB (zstd-compressed as the node
writes them). Then a ranker is started on the folder (in a ROS domain the tests' way
reserves) and, ``--forgets`` times: an idle block of ``--requests`` JSON rankings for stored
people who are not forgotten, one every ``--paced-period`` s; then a block that calls
``~/forget_person`` for one person and keeps sending the same paced requests until the
service answers. Each block's latencies (request to ranking), the forget's duration (call to
answer) and what it removed are printed and written to ``--out``.
"""
from __future__ import annotations

import argparse
import json
import random
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / 'benchmarks'))

import state_scale  # noqa: E402  (the store's filling)
from offline_training.common import DEFAULT_SOCNAV1  # noqa: E402
from stars_ros import recording  # noqa: E402
from stars_ros.data.scene_source import read_scenes  # noqa: E402
from stars_ros.evaluation.provenance import program_argv, run_record  # noqa: E402
from stars_ros.model.predictor import Predictor  # noqa: E402
from stars_ros.personalisation.foldin import Rating  # noqa: E402
from stars_ros.personalisation.stack import serving_stack  # noqa: E402
from stars_ros.resources import resolve_checkpoint  # noqa: E402
from stars_ros.state.store import StateStore  # noqa: E402

TOPICS = ('/stars/scene', '/stars/feedback')


def fill_bag(folder: Path, scenes: list, people: int, megabytes: float) -> dict:
    """One finished bag naming every person in turn until its files hold ``megabytes`` MB."""
    graphs = [json.dumps(scene, separators=(',', ':')) for scene in scenes]
    recorder = recording.Recorder(folder, {topic: recording.qos_profile(100) for topic in TOPICS},
                                  name='filled', flush_interval=60.0)
    rng, count, log_time = random.Random(3), 0, 10 ** 9
    while True:
        for _ in range(5000):
            person, scene = f'person-{count % people}', rng.randrange(len(scenes))
            scene_id = f'filled-{count}'
            recorder.write('/stars/scene', f'{{"scene_id":"{scene_id}","user_id":"{person}","graph":{graphs[scene]}}}',
                           log_time)
            recorder.write('/stars/feedback', json.dumps({'user_id': person, 'scene_id': scene_id, 'action': 'navigate',
                                                          'score': round(rng.random(), 4)}), log_time + 1)
            count, log_time = count + 1, log_time + 10 ** 6
        recorder.flush()
        size = sum(path.stat().st_size for path in recorder.path.glob('*.mcap'))
        if size >= megabytes * 1e6:
            break
    recorder.close()
    return {'files': len(list(recorder.path.glob('*.mcap'))), 'bytes': size, 'scene_requests': count,
            'messages': 2 * count}


def fill_store(folder: Path, checkpoint: str, scenes: list, people: int, ratings: int) -> None:
    predictor = Predictor.load(checkpoint)
    foldin = serving_stack(predictor).require_foldin()
    model = foldin.fit([Rating(scenes[0], 'navigate', 0.5)], 'probe')  # what a store holds per person
    state_scale.fill(folder, predictor, model, scenes, people, ratings, random.Random(5),
                     state_scale.encodings(predictor, scenes))
    store = StateStore(folder, 'forget_scale', on_error=print)
    store.close()


def summary(values: list) -> dict:
    return {'n': len(values), **({f'p{q}': float(np.percentile(values, q)) for q in (50, 99)} if values else {}),
            'max': float(max(values)) if values else None}


def measure(folder: Path, checkpoint: str, scenes: list, people: int, args) -> dict:
    from test_support.loopback import RosClient, domain_id, start_node, stop
    from stars_ros_msgs.srv import ForgetPerson
    import signal
    domain = domain_id(0)
    client = RosClient(domain)
    process = start_node('stars_ros.ros.ranker', domain, {'checkpoint': checkpoint, 'record_folder': folder,
                                                          'fold_in_max_users': people},
                         folder.parent / 'ranker.log')
    forget = client.node.create_client(ForgetPerson, '/ranker/forget_person')
    blocks, rng, sent = [], random.Random(11), 0
    try:
        started = time.perf_counter()
        client.wait_ready(process, 600, {'scene_id': 'ready', 'graph': scenes[0]})
        first_answer = time.perf_counter() - started
        if not forget.wait_for_service(timeout_sec=60):
            raise TimeoutError('~/forget_person not available')

        def paced(until) -> list:
            nonlocal sent
            latencies = []
            while not until(len(latencies)):
                scene_id, request_started = f'paced-{sent}', time.perf_counter()
                user = f'person-{rng.randrange(args.forgets, people)}'  # never one who is forgotten
                client.scene({'scene_id': scene_id, 'user_id': user, 'graph': scenes[sent % len(scenes)]})
                sent += 1
                if not client.wait(lambda: client.ranking_for(scene_id) is not None, 60):
                    raise TimeoutError(f'{scene_id} was not ranked')
                latencies.append((time.perf_counter() - request_started) * 1e3)
                time.sleep(max(0.0, args.paced_period - (time.perf_counter() - request_started)))  # the pacing
            return latencies

        for k in range(args.forgets):
            idle = paced(lambda n: n >= args.requests)
            called = time.perf_counter()
            future = forget.call_async(ForgetPerson.Request(user_id=f'person-{k}'))
            during = paced(lambda n: future.done())
            took = time.perf_counter() - called
            response = future.result()
            block = {'person': f'person-{k}', 'forget_s': took, 'success': response.success,
                     'message': response.message,
                     'removed': dict(zip(response.removed_places, map(int, response.removed_counts))),
                     'idle_ranking_ms': summary(idle), 'during_forget_ranking_ms': summary(during)}
            block['p99_ratio'] = block['during_forget_ranking_ms']['p99'] / block['idle_ranking_ms']['p99']
            print(json.dumps({key: block[key] for key in ('person', 'forget_s', 'success', 'p99_ratio')}), flush=True)
            print(f"  idle {block['idle_ranking_ms']}\n  during {block['during_forget_ranking_ms']}", flush=True)
            blocks.append(block)
    finally:
        stop(process, signal.SIGINT, 120)
        client.close()
    return {'start_to_first_answer_s': first_answer, 'blocks': blocks}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--checkpoint', default='models/socnav1_gat_stars.pt')
    parser.add_argument('--data-root', default=str(DEFAULT_SOCNAV1))
    parser.add_argument('--people', type=int, default=1000)
    parser.add_argument('--ratings', type=int, default=200)
    parser.add_argument('--bag-mb', type=float, default=100.0)
    parser.add_argument('--forgets', type=int, default=3)
    parser.add_argument('--requests', type=int, default=400, help='paced requests of an idle block')
    parser.add_argument('--paced-period', type=float, default=0.02)
    parser.add_argument('--out', default='results/forget_scale.json')
    args = parser.parse_args(argv)
    checkpoint = str(resolve_checkpoint(args.checkpoint))
    scenes = [s for name in 'abcdefgh' for s in read_scenes(Path(args.data_root) / 'raw' / f'{name}.jsonl')]
    with tempfile.TemporaryDirectory(prefix='forget_scale_') as temporary:
        folder = Path(temporary) / 'records'
        folder.mkdir()
        started = time.perf_counter()
        fill_store(folder, checkpoint, scenes, args.people, args.ratings)
        bag = fill_bag(folder, scenes, args.people, args.bag_mb)
        print(f'filled in {time.perf_counter() - started:.0f} s: {bag}', flush=True)
        store_bytes = sum(p.stat().st_size for p in folder.glob('state.db*'))
        measured = measure(folder, checkpoint, scenes, args.people, args)
        shutil.rmtree(folder)
    ratios = [block['p99_ratio'] for block in measured['blocks']]
    result = {**run_record(program_argv('benchmarks/forget_scale.py', argv)),
              'record_folder': {'people': args.people, 'ratings_each': args.ratings, 'state_store_bytes': store_bytes,
                                'bag': bag},
              'paced_period_s': args.paced_period, **measured,
              'goal': {'other_people_p99_at_most_2x_idle': all(r <= 2.0 for r in ratios), 'p99_ratios': ratios}}
    Path(args.out).write_text(json.dumps(result, indent=2) + '\n')
    print(json.dumps(result['goal']))
    return 0


if __name__ == '__main__':
    sys.exit(main())
