"""What serving a seed ensemble of K StARS members would cost, K = 1…5, in process: the
ranking and the fold-in update a node would do K times (issue 47's budgets: ranking p50
≤ 1.3× the echo floor, update ≤ 1 ms), the memory the members hold and their checkpoints' size.

    python benchmarks/ensemble_cost.py [--checkpoint models/socnav1_gat_stars.pt] [--members 5] \
        [--rankings 400] [--data-root ../shared/datasets/socnav1] [--out results/ensemble_cost.json]

Each member is the packaged checkpoint loaded again through the front door
(``StarsRecommender.load``): K members of one architecture cost what K differently seeded
members cost, so no ensemble needs training to be timed. A ranking: the JSON scene request
parsed once, then every member ranks the scene for one folded-in person with ``score_sd``
(``rank(..., uncertainty=True)``) and the scores are averaged. An update: the rated scene's
request parsed once, then every member re-solves the person from all their ratings so far,
the rated scene's h (and the plain encoder's scores the person is served around) cached from
its ranking (as ``benchmarks/foldin.py`` times one model).
K = 1…5 take turns over the requests, so the machine's drift reaches all alike. Memory: the
process's resident size after loading each member, less before the first (so K = 1 also
holds the serving libraries the first load imports). BLAS on one thread, as in the node.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from offline_training.common import DEFAULT_SOCNAV1  # noqa: E402
from stars_ros import StarsRecommender, messages  # noqa: E402
from stars_ros.data.scene_source import read_scenes  # noqa: E402
from stars_ros.evaluation.provenance import program_argv, run_record  # noqa: E402
from stars_ros.personalisation.foldin import FoldIn, Rating  # noqa: E402
from stars_ros.resources import resolve_checkpoint  # noqa: E402


def resident_bytes() -> int:
    for line in Path('/proc/self/status').read_text().splitlines():
        if line.startswith('VmRSS:'):
            return int(line.split()[1]) * 1024
    raise RuntimeError('no VmRSS in /proc/self/status')


def percentiles(values) -> dict:
    values = np.asarray(values, dtype=float)
    return {'p50': float(np.percentile(values, 50)), 'p99': float(np.percentile(values, 99)), 'n': len(values)}


def serving_setup(args) -> tuple:
    """(checkpoint path, SocNav1 scenes of annotator b, their JSON scene requests) for a
    process set up as the node serves: BLAS on one thread, the request schema compiled."""
    threadpool_limits(1, user_api='blas')  # as the node does
    scenes = read_scenes(Path(args.data_root) / 'raw' / 'b.jsonl')
    messages.validator('scene_request')  # compiled once per process, as in the node before any request
    return (Path(resolve_checkpoint(args.checkpoint)), scenes,
            [json.dumps({'scene_id': s['identifier'], 'graph': s}) for s in scenes])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--checkpoint', help='default: the packaged model')
    parser.add_argument('--members', type=int, default=5, help='largest K (default: %(default)s)')
    parser.add_argument('--rankings', type=int, default=400, help='rankings and updates per K (default: %(default)s)')
    parser.add_argument('--ratings', type=int, default=20,
                        help='ratings the person has before the timed updates (default: %(default)s)')
    parser.add_argument('--data-root', default=str(DEFAULT_SOCNAV1))
    parser.add_argument('--out', default=str(REPO / 'results' / 'ensemble_cost.json'))
    args = parser.parse_args(argv)
    checkpoint, scenes, texts = serving_setup(args)

    before = resident_bytes()
    members, memory = [], []
    for _ in range(args.members):
        members.append(StarsRecommender.load(checkpoint))
        memory.append(resident_bytes() - before)
    action = members[0].actions[0]
    solvers = [FoldIn(member.predictor) for member in members]
    ratings = []
    for scene, text in zip(scenes[:args.ratings], texts):
        request = messages.parse_scene_request(text, messages.DEFAULT_MAX_BYTES)
        ratings.append(Rating(request.graphs[0], action, scene['score'] / 100, request.scene_id))
    for member, solver in zip(members, solvers):  # the person every member serves: folded in
        solver.remember([r.scene for r in ratings], member.predictor.encode([r.scene for r in ratings]))
        member.predictor.set_user_model('person', solver.fit(ratings, 'person', 0.0))
        member.rank('person', scenes[0], uncertainty=True)  # warm: the kernels compiled, the caches made

    ranking_ms = {k: [] for k in range(1, args.members + 1)}
    update_ms = {k: [] for k in range(1, args.members + 1)}
    for n in range(args.rankings):
        text, scene = texts[n % len(texts)], scenes[n % len(scenes)]
        for k in np.roll(np.arange(1, args.members + 1), n):
            started = time.perf_counter()
            request = messages.parse_scene_request(text, messages.DEFAULT_MAX_BYTES)
            rankings = [member.rank('person', request.graphs[0], uncertainty=True) for member in members[:k]]
            np.mean([[entry.score for entry in sorted(ranking, key=lambda e: e.name)] for ranking in rankings],
                    axis=0)  # the ensemble's scores: part of what a ranking costs
            ranking_ms[k].append((time.perf_counter() - started) * 1e3)
            scored = [member.predictor.rank_many('person', [request], validate=False)[0]  # h and the plain
                      for member in members[:k]]  # encoder's scores, as its ranking made them
            started = time.perf_counter()
            request = messages.parse_scene_request(text, messages.DEFAULT_MAX_BYTES)
            rated = [*ratings, Rating(request.graphs[0], action, scene['score'] / 100, request.scene_id)]
            for solver, member_scored in zip(solvers[:k], scored):
                solver.remember([request.graphs[0]], member_scored.h, plain=member_scored.plain)
                solver.fit(rated, 'person', 0.0)
            update_ms[k].append((time.perf_counter() - started) * 1e3)

    size = checkpoint.stat().st_size
    by_members = [{'members': k, 'ranking_ms': percentiles(ranking_ms[k]), 'update_ms': percentiles(update_ms[k]),
                   'resident_bytes': memory[k - 1], 'checkpoint_bytes': k * size}
                  for k in range(1, args.members + 1)]
    for row in by_members:
        print(f"K={row['members']}: ranking p50 {row['ranking_ms']['p50']:.3f} ms p99 {row['ranking_ms']['p99']:.3f}"
              f" | update p50 {row['update_ms']['p50']:.3f} ms p99 {row['update_ms']['p99']:.3f}"
              f" | memory {row['resident_bytes'] / 2 ** 20:.1f} MiB | checkpoints {row['checkpoint_bytes'] / 2 ** 20:.2f} MiB")
    record = {**run_record(program_argv('benchmarks/ensemble_cost.py', argv)),
              'settings': {**vars(args), 'checkpoint': str(checkpoint)}, 'by_members': by_members}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(record, indent=1) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
