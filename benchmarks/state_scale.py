"""The ranker's state store at scale: what one update writes and costs, how long a restart
takes, and what feedback for stored people costs other users' rankings, for stores of
50 × 5, 1,000 × 20 and 1,000 × 200 people × ratings of real SocNav1 scenes (``--sizes``: also 10,000 × 200),
and how long importing a state file of an earlier version takes.

    python benchmarks/state_scale.py [--checkpoint models/socnav1_gat_stars.pt] \
        [--data-root ../shared/datasets/socnav1] [--out results/state_scale.json]

For each size a store is filled (``StateStore.write_person``: every person with a solved
model and covariance of the served checkpoint, their ratings of scenes drawn from the data,
and the served checkpoint's h of those scenes, as the node stores them with the ratings)
and then, in this process:
  * update: ``--updates`` times, one stored person's next rating arrives (the oldest leaves
    when they hold their maximum) with their new model, queued with its feedback as the node
    queues it (``write_person``) and waited for until committed, one at a time: the time to
    commit (p50/p99), the executor's share (building the update and queueing it), and the
    bytes this process handed to the kernel per update (/proc/self/io wchar: WAL frames and
    the checkpoints that copy them into the database);
  * restart in process: open the store, load it and restore it into a Personalisation as
    the node does (``restore``).
Then, unless ``--no-node``, a ranker is started on a copy of each store as filled and on an
empty folder (each in a ROS domain the tests' way reserves): the time from starting the process
to its first answer, and other users' ranking latency (one request every
``--paced-period`` s) in blocks that alternate between quiet and a stream of feedback at
``--feedback-rate``/s for stored people on scenes the node ranked, ``--blocks`` of each,
with what the node's /diagnostics said of its fold-in work meanwhile (turns, the longest).
"""
from __future__ import annotations

import argparse
import json
import random
import shlex
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from offline_training.common import DEFAULT_SOCNAV1  # noqa: E402
from stars_ros.evaluation.provenance import git_state, machine, program_argv  # noqa: E402
from stars_ros.data.scene_source import read_scenes  # noqa: E402
from stars_ros.model.predictor import Predictor  # noqa: E402
from stars_ros.personalisation.foldin import Rating  # noqa: E402
from stars_ros.personalisation.stack import serving_stack  # noqa: E402
from stars_ros.personalisation.online import Personalisation  # noqa: E402
from stars_ros.state import migration  # noqa: E402
from stars_ros.state import PersonUpdate, StateStore  # noqa: E402
from stars_ros.resources import resolve_checkpoint  # noqa: E402

SIZES = ((50, 5), (1000, 20), (1000, 200))
ORIGIN = '/ranker'


def summary(values: list) -> dict:
    return {'n': len(values), **({f'p{q}': float(np.percentile(values, q)) for q in (50, 99)} if values else {}),
            'max': float(max(values)) if values else None}


def written_bytes() -> int:
    return int(dict(line.split(': ') for line in Path('/proc/self/io').read_text().splitlines())['wchar'])


def encodings(predictor, scenes: list) -> dict:
    """id(scene) -> h_i of every scene, as the node hands them to the store with the ratings."""
    h = np.concatenate([predictor.encode(scenes[start:start + 256]) for start in range(0, len(scenes), 256)])
    return {id(scene): row for scene, row in zip(scenes, h.astype(np.float64))}


def fill(folder: Path, predictor, model, scenes: list, people: int, ratings: int, rng, encoded: dict) -> list:
    """A store of ``people`` × ``ratings``, with the h of their scenes; returns the updates it holds."""
    updates = []
    for k in range(people):
        held = [Rating(scenes[rng.randrange(len(scenes))], 'navigate', rng.random(), None, f'p{k}-r{j}', j, ORIGIN)
                for j in range(ratings)]
        updates.append(PersonUpdate(f'person-{k}', model, predictor.fingerprint, held, 0, [], True, encoded))
    store = StateStore(folder, 'state_scale', on_error=print)  # each person through the store's one write
    store.set_fingerprint(predictor.fingerprint)
    for update in updates:
        store.write_person(update)
    if store.close():
        raise OSError(f'the state store in {folder} was not filled')
    return [update._replace(encoded=None) for update in updates]


def measure_updates(folder: Path, predictor, model, scenes: list, updates: list, count: int, max_ratings: int,
                    rng) -> dict:
    store = StateStore(folder, 'state_scale', on_error=print)
    store.load(predictor.fingerprint)
    current = {u.user_id: u for u in updates}
    latency, executor, written = [], [], []
    done = threading.Event()
    for k in range(count):
        started = time.perf_counter()
        person = current[f'person-{rng.randrange(len(updates))}']
        rating = Rating(scenes[rng.randrange(len(scenes))], 'navigate', rng.random(), None, f'new-{k}',
                        10 ** 6 + k, ORIGIN)
        held = (person.ratings + [rating])[-max_ratings:]
        update = person._replace(ratings=held, dropped=person.dropped + len(person.ratings) + 1 - len(held),
                                 solved=False)
        current[person.user_id] = update
        done.clear()
        before = written_bytes()
        entry = {'topic': '/stars/feedback', 'log_time': k, 'data': json.dumps(
            {'user_id': person.user_id, 'scene_id': f's{k}', 'action': 'navigate', 'score': rating.score})}
        store.when_committed(store.write_person(update, [(entry, 'bench')]), done.set)
        executor.append((time.perf_counter() - started) * 1e3)
        if not done.wait(30):
            raise TimeoutError('an update was never committed')
        latency.append((time.perf_counter() - started) * 1e3)
        written.append(written_bytes() - before)
    store.close()
    return {'commit_ms': summary(latency), 'executor_ms': summary(executor),
            'bytes_written_per_update': {'mean': float(np.mean(written)), 'p50': float(np.median(written)),
                                         'max': int(max(written))}}


def measure_restart(folder: Path, checkpoint: str, max_ratings: int, people: int) -> dict:
    predictor = Predictor.load(checkpoint)
    started = time.perf_counter()
    store = StateStore(folder, 'state_scale', on_error=print)
    opened = time.perf_counter()
    personalisation = Personalisation(predictor, max_ratings, max(people, 1000), lambda kind, text: print(text),
                                      store=store)
    personalisation.restore()
    restored = time.perf_counter()
    store.close()
    return {'open_s': opened - started, 'open_load_restore_s': restored - started,
            'people_served': len(predictor.user_models), 'waiting_to_be_solved': len(personalisation.pending)}


def write_legacy_file(folder: Path, fingerprint: str, updates: list) -> int:
    """``user_models.json`` as an earlier version kept ``updates`` (``migration``); its bytes."""
    users = {u.user_id: {**u.model.to_json(), 'ratings_dropped': u.dropped, 'ratings': [r.to_json() for r in u.ratings],
                         'peer_ratings': []} for u in updates}
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / migration.STATE_FILE
    path.write_text(json.dumps({'format': migration.FORMAT, 'version': 1, 'fingerprint': fingerprint, 'users': users}))
    return path.stat().st_size


def measure_migration(folder: Path, checkpoint: str, max_ratings: int, people: int) -> dict:
    """Open a store on a folder holding only a legacy state file (it is imported) and
    restore it, as the node's start does."""
    progress = []
    started = time.perf_counter()
    store = StateStore(folder, 'state_scale', on_error=print,
                       on_progress=lambda text: progress.append((round(time.perf_counter() - started, 3), text)))
    opened = time.perf_counter()
    predictor = Predictor.load(checkpoint)
    personalisation = Personalisation(predictor, max_ratings, max(people, 1000), lambda kind, text: print(text),
                                      store=store)
    personalisation.restore()
    restored = time.perf_counter()
    store.close()
    return {'import_s': opened - started, 'import_load_restore_s': restored - started, 'imported': store.imported,
            'people_served': len(predictor.user_models), 'progress': progress}


def fold_in_work(diagnostics: list) -> dict:
    """What the node's /diagnostics said of its fold-in over ``diagnostics``: its turns of
    work (a solve, or a step of building a restored person's rows), the longest, and the
    rankings that waited behind them."""
    values = [{v.key: v.value for v in status.values} for array in diagnostics for status in array.status
              if status.name.endswith(': ranker')]
    longest = [float(v['period.fold_in_update_ms.max']) for v in values if 'period.fold_in_update_ms.max' in v]
    return {'fold_in_turns': sum(int(v.get('period.fold_in_updates', 0)) for v in values),
            'longest_turn_ms': max(longest) if longest else None,
            'rankings_delayed_by_fold_in': sum(int(v.get('period.rankings_delayed_by_fold_in', 0)) for v in values)}


def measure_node(folder: Path, checkpoint: str, scenes: list, people: int, domain: int, args) -> dict:
    from test_support.loopback import RosClient, start_node
    client = RosClient(domain)
    started = time.perf_counter()
    process = start_node('stars_ros.ros.ranker', domain, {'checkpoint': checkpoint, 'record_folder': folder,
                                                          'fold_in_max_users': max(people, 1000)},
                         folder.parent / f'{folder.name}.log')
    try:
        client.wait_ready(process, 300, {'scene_id': 'ready', 'graph': scenes[0]})
        first_answer = time.perf_counter() - started
        rated = [f'rated-{k}' for k in range(50)]
        for k, scene_id in enumerate(rated):  # feedback names scenes the node ranked
            client.scene({'scene_id': scene_id, 'graph': scenes[k]})
        if not client.wait(lambda: all(client.ranking_for(s) for s in rated), 60):
            raise TimeoutError('the scenes to rate were not ranked')
        rng = random.Random(7)
        latencies = {'quiet': [], 'feedback': []}
        diagnostics = {'quiet': [], 'feedback': []}
        sent = 0
        for block in range(2 * args.blocks):
            kind = ('quiet', 'feedback')[block % 2]
            stop = threading.Event()

            def stream():
                nonlocal sent
                while not stop.wait(1.0 / args.feedback_rate):
                    client.feedback({'user_id': f'person-{rng.randrange(people)}', 'scene_id': rng.choice(rated),
                                     'action': 'navigate', 'score': rng.random()})
                    sent += 1
            streamer = threading.Thread(target=stream, daemon=True)
            seen = len(client.diagnostics)
            if kind == 'feedback':
                streamer.start()
            for k in range(args.requests_per_block):
                scene_id = f'load-{block}-{k}'
                request_started = time.perf_counter()
                client.scene({'scene_id': scene_id, 'user_id': 'other', 'graph': scenes[50 + k % 100]})
                if client.wait(lambda: client.ranking_for(scene_id) is not None, 30):
                    latencies[kind].append((time.perf_counter() - request_started) * 1e3)
                time.sleep(max(0.0, args.paced_period - (time.perf_counter() - request_started)))  # the pacing
            stop.set()
            if streamer.is_alive():
                streamer.join()
            diagnostics[kind] += client.diagnostics[seen:]
    finally:  # the node first: a participant leaving while the node destroys its own can hang Fast DDS
        process.terminate()
        process.wait(timeout=120)
        client.close()
    return {'start_to_first_answer_s': first_answer, 'feedback_sent': sent,
            'other_users_ranking_ms': {kind: summary(values) for kind, values in latencies.items()},
            'fold_in_during_blocks': {kind: fold_in_work(values) for kind, values in diagnostics.items()}}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--checkpoint', default='', help='the checkpoint served (default: the packaged model)')
    parser.add_argument('--data-root', default=str(DEFAULT_SOCNAV1))
    parser.add_argument('--sizes', default=','.join(f'{p}x{r}' for p, r in SIZES), help='people x ratings, ...')
    parser.add_argument('--updates', type=int, default=300)
    parser.add_argument('--no-node', action='store_true', help='only the in-process figures')
    parser.add_argument('--node-sizes', help='sizes to run the node on (default: all of --sizes)')
    parser.add_argument('--blocks', type=int, default=2, help='blocks of each kind (quiet, feedback), alternating')
    parser.add_argument('--requests-per-block', type=int, default=100)
    parser.add_argument('--paced-period', type=float, default=0.05)
    parser.add_argument('--feedback-rate', type=float, default=50.0)
    parser.add_argument('--max-legacy-ratings', type=int, default=500000,
                        help='measure the import of a legacy state file for sizes of at most this many ratings')
    parser.add_argument('--out', default=str(REPO / 'results' / 'state_scale.json'))
    args = parser.parse_args(argv)
    sizes = [tuple(int(v) for v in size.split('x')) for size in args.sizes.split(',')]
    node_sizes = sizes if args.node_sizes is None else [tuple(int(v) for v in s.split('x'))
                                                        for s in args.node_sizes.split(',')]
    scenes = [s for name in 'abcdefgh' for s in read_scenes(Path(args.data_root) / 'raw' / f'{name}.jsonl')]
    checkpoint = resolve_checkpoint(args.checkpoint)
    predictor = Predictor.load(checkpoint)
    model = serving_stack(predictor).require_foldin().fit([Rating(scenes[0], 'navigate', 0.5)], 'probe')
    results = {'command': shlex.join(program_argv('benchmarks/state_scale.py', argv)), 'git': git_state(),
               'sizes': {}, 'settings': {**{k: v for k, v in vars(args).items() if k not in ('out', 'data_root')},
                                         'checkpoint': checkpoint, 'scenes': f'{len(scenes)} SocNav1 scenes (a-h)',
                                         'machine': machine()}}
    rng = random.Random(25)
    encoded = encodings(predictor, scenes)
    with tempfile.TemporaryDirectory() as work:
        for people, ratings in sizes:
            name = f'{people}x{ratings}'
            folder = Path(work) / name
            started = time.perf_counter()
            updates = fill(folder, predictor, model, scenes, people, ratings, rng, encoded)
            figures = {'fill_s': time.perf_counter() - started,
                       'database_bytes': (folder / 'state.db').stat().st_size}
            shutil.copytree(folder, Path(work) / f'node-{name}')  # as filled: every model solved from its ratings
            figures['update'] = measure_updates(folder, predictor, model, scenes, updates, args.updates, ratings, rng)
            figures['restart_in_process'] = measure_restart(folder, checkpoint, ratings, people)
            if people * ratings <= args.max_legacy_ratings:
                legacy = Path(work) / f'legacy-{name}'
                figures['legacy_file_bytes'] = write_legacy_file(legacy, predictor.fingerprint, updates)
                figures['migration_in_process'] = measure_migration(legacy, checkpoint, ratings, people)
            results['sizes'][name] = figures
            print(f"{name}: {figures['database_bytes'] / 1e6:.1f} MB; update: commit p50 "
                  f"{figures['update']['commit_ms']['p50']:.2f} ms p99 {figures['update']['commit_ms']['p99']:.2f} ms, "
                  f"executor p50 {figures['update']['executor_ms']['p50']:.3f} ms, "
                  f"{figures['update']['bytes_written_per_update']['mean'] / 1024:.1f} KiB written; restart "
                  f"{figures['restart_in_process']['open_load_restore_s']:.2f} s", flush=True)
        if not args.no_node:
            from test_support.loopback import domain_id
            domain = domain_id(16)
            runs = [('empty', 0)] + [(f'{p}x{r}', p) for p, r in node_sizes]
            for name, people in runs:
                folder = Path(work) / f'node-{name}'
                folder.mkdir(exist_ok=True)
                figures = measure_node(folder, checkpoint, scenes, max(people, 50), domain, args)
                results.setdefault('node', {})[name] = figures
                ranking = figures['other_users_ranking_ms']
                print(f"node on {name}: first answer {figures['start_to_first_answer_s']:.1f} s; other users' ranking "
                      f"quiet p50 {ranking['quiet']['p50']:.2f} p99 {ranking['quiet']['p99']:.2f} ms, with feedback "
                      f"p50 {ranking['feedback']['p50']:.2f} p99 {ranking['feedback']['p99']:.2f} ms", flush=True)
    Path(args.out).write_text(json.dumps(results, indent=2) + '\n')
    print(f'written {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
