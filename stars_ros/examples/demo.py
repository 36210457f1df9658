"""The main-job demo: the ranker serving two people, their rankings side by side, feedback
recorded to MCAP, then a summary. Ends by itself.

    python -m stars_ros.examples.demo [--checkpoint PATH] [--scenes 8] [--placements 6]

Set-up loads the checkpoint (the packaged default unless one is given) and picks, among the
annotators it knows, the two whose rankings of alternative robot placements differ most on
SocNav1 scenes both of them rated. Then it starts the ranker and one scene_publisher per
person (separate processes, as ``ros2 launch`` would), prints each pair of rankings as it
arrives, then sends each person's real SocNav1 rating of each scene as it was (placement
``stay``) as feedback (before that, the first scene's placements are ranked once more for the
first person through the typed service ``~/rank_candidates``, docs/interfaces.md, and printed
beside its JSON twin's ranking), stops the ranker with SIGINT and reads the feedback back from the
MCAP bag. Last, it draws the first scene for both people (``offline_training.plot_scene``'s
picture) into its temporary folder and prints the PNG's path. Runs on the current
ROS_DOMAIN_ID unless ``--domain-id`` is given.

Every run starts from a clean state: the ranker records into a new temporary folder unless
``--record-folder`` is given, so no earlier run's folded-in users are restored, and the
feedback goes out once every ranking is in, so no ranking depends on how fast a fold-in
overtook the other person's scenes: the scores printed come from the checkpoint alone and a
second run prints the same rankings.
"""
from __future__ import annotations

import argparse
import itertools
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from stars_ros.errors import StarsError, StoreError
from stars_ros.figures.scene import plot_people
from stars_ros.model.predictor import Predictor
from stars_ros.recording.bag import read_messages
from stars_ros.resources import resolve_checkpoint
from stars_ros.data.scene_source import PLACEMENTS, placement_candidates, read_scenes, socnav1_root
from stars_ros.typed_messages import scene_message
from stars_ros import state

SOCNAV1 = socnav1_root()


def parse_args(argv=None):
    parser = argparse.ArgumentParser(prog='python -m stars_ros.examples.demo', description=__doc__.split('\n\n')[0])
    parser.add_argument('--checkpoint', default='', help='default: the packaged models/socnav1_gat_stars.pt')
    parser.add_argument('--data-root', type=Path, default=SOCNAV1, help='SocNav1 root (default: %(default)s)')
    parser.add_argument('--scenes', type=int, default=8, help='scenes per person (default: %(default)s)')
    parser.add_argument('--placements', type=int, default=6, choices=range(2, len(PLACEMENTS) + 1),
                        metavar=f'2..{len(PLACEMENTS)}',
                        help='robot placements ranked per scene (default: %(default)s)')
    parser.add_argument('--rate', type=float, default=4.0, help='scenes per second per person (default: %(default)s)')
    parser.add_argument('--record-folder', type=Path, help="where the ranker records (default: a new temporary "
                        "folder, so that no earlier run's folded-in users are restored)")
    parser.add_argument('--domain-id', type=int, help='ROS domain for the demo (default: ROS_DOMAIN_ID)')
    parser.add_argument('--timeout', type=float, default=180.0,
                        help='give up after this many seconds (default: %(default)s)')
    return parser.parse_args(argv)


def _order(scores) -> tuple:
    return tuple(np.argsort(-np.asarray(scores), kind='stable'))


def choose_people(predictor, root: Path, n_scenes: int, placements: int):
    """The two known annotators whose placement orders differ on most shared scenes, and
    those scenes with both ratings: (user_a, user_b, [(scene, rating_a, rating_b)])."""
    rated = {}
    for user in predictor.users:
        path = root / 'raw' / f'{user}.jsonl'
        if path.exists():
            rated[user] = {s['identifier']: s for s in read_scenes(path)}
    best = None
    orders = {}
    for a, b in itertools.combinations(sorted(rated), 2):
        shared = [k for k in rated[a] if k in rated[b]][:n_scenes]
        if len(shared) < n_scenes:
            continue
        for user in (a, b):
            for key in shared:
                if (user, key) not in orders:
                    graphs = [c['graph'] for c in placement_candidates(rated[a][key], placements)]
                    orders[user, key] = _order(predictor.score(user, graphs)[:, 0])
        differ = sum(orders[a, k] != orders[b, k] for k in shared)
        if best is None or differ > best[0]:
            best = (differ, a, b, shared)
    if best is None:
        raise StarsError(f'no two annotators known to this checkpoint rated {n_scenes} of the same scenes in {root}')
    _, a, b, shared = best
    return a, b, [(rated[a][k], rated[a][k]['score'] / 100, rated[b][k]['score'] / 100) for k in shared]


def score_decimals(*replies, least: int = 3, most: int = 5) -> int:
    """The fewest decimals (``least`` to ``most``) at which the different scores within each
    ranking print differently, so that an order the demo calls different shows in the numbers."""
    scores = [[e['score'] for e in reply['ranking']] for reply in replies]
    for decimals in range(least, most):
        if all(len({f'{score:.{decimals}f}' for score in ranking}) == len(set(ranking)) for ranking in scores):
            return decimals
    return most


def _holds_people(folder: Path) -> bool:
    try:
        with state.open_reader(folder) as store:
            return bool(store.summary())
    except (FileNotFoundError, StoreError):
        return False


def record_folder(given: Path | None, work: Path) -> Path:
    """Where the demo's ranker records: ``work``/records, a folder of this run's own, unless a
    folder is ``given``; one given that holds folded-in users of an earlier run is said to,
    since the ranker restores them and their scores then differ from a fresh start."""
    if given is None:
        return work / 'records'
    if _holds_people(given):
        print(f'Note: {given / state.DATABASE} holds folded-in users of an earlier run: the ranker restores them, '
              'so their scores differ from a fresh start')
    return given


def ranking_line(user, reply, decimals: int) -> str:
    return f'  {user:>3}: ' + ' > '.join(f"{e['candidate']} {e['score']:.{decimals}f}" for e in reply['ranking'])


def typed_ranking(node, user: str, scene: dict, placements: int, timeout: float):
    """``scene``'s placements ranked for ``user`` through the typed service ~/rank_candidates
    (stars_ros_msgs, REP 103): the response's ranking, as a reply dict ``ranking_line`` prints."""
    import rclpy
    from geometry_msgs import msg as geometry
    from stars_ros_msgs import msg as typed
    from stars_ros_msgs.srv import RankCandidates

    client = node.create_client(RankCandidates, '/ranker/rank_candidates')
    if not client.wait_for_service(timeout_sec=timeout):
        raise StarsError('the ranker offers no ~/rank_candidates service')
    request = RankCandidates.Request(scene_id=f'{user}/typed', user_id=user, candidates=[
        typed.CandidateScene(label=c['candidate'], scene=scene_message(c['graph'], 'base_link', typed, geometry))
        for c in placement_candidates(scene, placements)])
    future = client.call_async(request)
    rclpy.spin_until_future_complete(node, future, timeout_sec=timeout)
    response = future.result()
    if response is None or not response.success:
        raise StarsError(f"~/rank_candidates failed: {'no answer' if response is None else response.message}")
    return {'ranking': [{'candidate': e.name, 'score': e.score} for e in response.ranking.entries]}


def run(args) -> int:
    checkpoint = resolve_checkpoint(args.checkpoint)
    predictor = Predictor.load(checkpoint)
    if not (args.data_root / 'raw').is_dir():
        raise StarsError(f'SocNav1 not found at {args.data_root}: set STARS_SOCNAV1_ROOT or --data-root')
    user_a, user_b, chosen = choose_people(predictor, args.data_root, args.scenes, args.placements)
    print(f'StARS demo: checkpoint {checkpoint} (fingerprint {predictor.fingerprint[:12]}), '
          f'{len(predictor.users)} people known, action {predictor.actions[0]!r}')
    print(f"People: '{user_a}' and '{user_b}', the two SocNav1 annotators whose rankings of {args.placements} "
          f'robot placements differ most on scenes both rated')

    env = dict(os.environ, PYTHONUNBUFFERED='1')
    env['PYTHONPATH'] = str(Path(__file__).resolve().parents[2]) + os.pathsep + env.get('PYTHONPATH', '')
    if args.domain_id is not None:
        env['ROS_DOMAIN_ID'] = str(args.domain_id)

    import rclpy
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    work = Path(tempfile.mkdtemp(prefix='stars_demo_'))
    scene_file = work / 'scenes.jsonl'
    scene_file.write_text(''.join(json.dumps(scene) + '\n' for scene, _, _ in chosen))
    records = record_folder(args.record_folder, work)
    records.mkdir(parents=True, exist_ok=True)
    before = set(records.glob('stars_*'))
    ranker = subprocess.Popen(
        [sys.executable, '-m', 'stars_ros.ros.ranker', '--ros-args', '-p', f'checkpoint:={checkpoint}',
         '-p', f'record_folder:={records}', '-p', 'flush_interval:=0.5', '--log-level', 'warn'], env=env)
    publishers = []
    rclpy.init(domain_id=args.domain_id)
    node = Node('stars_demo')
    reliable = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    replies = {}
    node.create_subscription(String, '/stars/ranking', lambda m: replies.setdefault(
        json.loads(m.data)['scene_id'], json.loads(m.data)), reliable)
    stored = {}  # user -> ratings of their latest stars/user_model: sent once the store has committed them

    def keep_model(msg):
        model = json.loads(msg.data)
        stored[model['user_id']] = model['n_ratings']
    node.create_subscription(String, '/stars/user_model', keep_model,
                             QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                                        durability=DurabilityPolicy.TRANSIENT_LOCAL))
    feedback = node.create_publisher(String, '/stars/feedback', reliable)
    deadline = time.monotonic() + args.timeout
    try:
        while not (node.count_subscribers('/stars/scene') and node.count_publishers('/stars/ranking')):
            rclpy.spin_once(node, timeout_sec=0.2)
            if ranker.poll() is not None or time.monotonic() > deadline:
                raise StarsError('the ranker did not start; see its log above')
        print(f'Ranker up (pid {ranker.pid}); two scene_publisher nodes send {len(chosen)} scenes each\n')
        for user in (user_a, user_b):
            publishers.append(subprocess.Popen(
                [sys.executable, '-m', 'stars_ros.ros.scene_publisher', '--ros-args', '-r', f'__node:=scenes_{user}',
                 '-p', f'source:={scene_file}', '-p', f'user_id:={user}', '-p', f'count:={len(chosen)}',
                 '-p', f'rate:={args.rate}', '-p', f'placements:={args.placements}',
                 '-p', f'scene_id_prefix:={user}/', '--log-level', 'warn'], env=env))
        shown, differ, sent = set(), 0, 0
        while len(shown) < len(chosen) and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.1)
            for n, (scene, _, _) in enumerate(chosen):
                a, b = replies.get(f'{user_a}/{n}'), replies.get(f'{user_b}/{n}')
                if n in shown or a is None or b is None:
                    continue
                shown.add(n)
                same = [e['candidate'] for e in a['ranking']] == [e['candidate'] for e in b['ranking']]
                differ += not same
                decimals = score_decimals(a, b)
                print(f"scene {scene['identifier']}: {'same order' if same else 'ORDERS DIFFER'}")
                print(ranking_line(user_a, a, decimals))
                print(ranking_line(user_b, b, decimals))
        if len(shown) < len(chosen):
            raise StarsError(f'timed out: {len(shown)} of {len(chosen)} scenes ranked for both people')
        served, twin = typed_ranking(node, user_a, chosen[0][0], args.placements,
                                     max(1.0, deadline - time.monotonic())), replies[f'{user_a}/0']
        theirs = {e['candidate']: e['score'] for e in twin['ranking']}
        gap = max(abs(e['score'] - theirs.get(e['candidate'], np.inf)) for e in served['ranking'])
        print(f"\nTyped service /ranker/rank_candidates (stars_ros_msgs, metres), the placements of "
              f"{chosen[0][0]['identifier']} again: "
              f"{ranking_line(user_a, served, score_decimals(served, twin)).strip()} "
              f'(largest difference from the JSON ranking above: {gap:.1e})')
        for n, (_, rating_a, rating_b) in enumerate(chosen):
            for user, rating in ((user_a, rating_a), (user_b, rating_b)):
                feedback.publish(String(data=json.dumps({'user_id': user, 'scene_id': f'{user}/{n}',
                                                         'candidate': 'stay', 'score': rating})))
                sent += 1
        folds_in = predictor.served.config.model.variant != 'base'  # a base model publishes no user models
        while folds_in and min(stored.get(user_a, 0), stored.get(user_b, 0)) < len(chosen):  # every rating stored
            rclpy.spin_once(node, timeout_sec=0.1)
            if ranker.poll() is not None or time.monotonic() > deadline:
                raise StarsError(f'timed out: the ranker stored {stored} of {len(chosen)} ratings per person')
    finally:  # the ranker first: each publisher waits for DDS to acknowledge its last scene, which
        # Fast DDS does at its periodic heartbeat (3 s) unless the subscriber has gone
        ranker.send_signal(signal.SIGINT)
        ranker.wait(timeout=30)
        for process in publishers:
            process.wait(timeout=30)
        node.destroy_node()
        rclpy.try_shutdown()

    bags = sorted(set(records.glob('stars_*')) - before)
    recorded = list(read_messages(bags[-1])) if bags else []
    count = {topic: sum(t == topic for t, _, _ in recorded) for topic in ('/stars/ranking', '/stars/feedback')}
    times = [replies[k]['processing_ms'] for k in replies]
    print(f'\nSummary: {len(times)} rankings (processing median {np.median(times):.1f} ms); '
          f'orders differ on {differ} of {len(chosen)} scenes; {sent} feedback ratings sent.')
    print(f"Recorded in {bags[-1] if bags else '(no bag)'}: {count['/stars/ranking']} rankings (the typed one "
          f"included) and "
          f"{count['/stars/feedback']} feedback ratings read back from MCAP. Ranker exit code {ranker.returncode}.")
    first = chosen[0][0]
    try:
        picture = plot_people(predictor, first, [user_a, user_b], work / 'scene.png', args.placements,
                              title=f"scene {first['identifier']}: {args.placements} robot placements")
        print(f"Picture (both people, {first['identifier']}): {picture}")
    except StarsError as error:  # matplotlib missing: the demo itself does not need it
        print(f'No picture: {error}')
    return 0 if count['/stars/feedback'] == sent and ranker.returncode == 0 else 1


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        return run(args)
    except (StarsError, OSError) as error:
        print(f'demo failed: {error}', file=sys.stderr)
        return 1


if __name__ == '__main__':
    raise SystemExit(main())
