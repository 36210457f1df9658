"""What one ranking costs, in process, for each kind of person a checkpoint serves: a trained
person, a person folded in from feedback, and a stranger (served the plain encoder where the
checkpoint keeps one for them, ``model.strangers: base_encoder``, else the prior's mean).

    python benchmarks/stranger_cost.py [--checkpoint models/socnav1_gat_stars.pt] [--rankings 400] \
        [--data-root ../shared/datasets/socnav1] [--out results/stranger_cost.json]

(``results/stranger_cost_prior_mean.json``: the same for the packaged checkpoint before it kept a
plain encoder, ``git show 5eea9e7:models/socnav1_gat_stars.pt``, whose strangers get the prior's mean.)

A ranking: the JSON scene request parsed, then ``rank(person, scene, uncertainty=True)``
through the front door (``StarsRecommender.load``). The three people take turns over the
requests, so the machine's drift reaches
all alike. BLAS on one thread, as in the node.
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
from stars_ros.resources import resolve_checkpoint  # noqa: E402

FOLDED_RATINGS = 5  # the folded-in person's ratings


def percentiles(values) -> dict:
    values = np.asarray(values, dtype=float)
    return {'p50': float(np.percentile(values, 50)), 'p99': float(np.percentile(values, 99)),
            'n': len(values)}


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
    parser.add_argument('--rankings', type=int, default=400, help='rankings per person (default: %(default)s)')
    parser.add_argument('--data-root', default=str(DEFAULT_SOCNAV1))
    parser.add_argument('--out', default=str(REPO / 'results' / 'stranger_cost.json'))
    args = parser.parse_args(argv)
    checkpoint, scenes, texts = serving_setup(args)

    recommender = StarsRecommender.load(checkpoint)
    action = recommender.actions[0]
    recommender.fold_in('folded', [(scene, action, scene['score'] / 100) for scene in scenes[:FOLDED_RATINGS]])
    people = {'trained': recommender.users[0], 'folded_in': 'folded', 'stranger': 'stranger'}
    for person in people.values():
        recommender.rank(person, scenes[0], uncertainty=True)  # warm: the kernels compiled, the caches made
    ranking_ms = {kind: [] for kind in people}
    kinds = list(people)
    for n in range(args.rankings):
        text = texts[n % len(texts)]
        for kind in np.roll(kinds, n):
            started = time.perf_counter()
            request = messages.parse_scene_request(text, messages.DEFAULT_MAX_BYTES)
            recommender.rank(people[kind], request.graphs[0], uncertainty=True)
            ranking_ms[kind].append((time.perf_counter() - started) * 1e3)

    strangers = recommender.config.model.strangers
    by_person = {kind: percentiles(values) for kind, values in ranking_ms.items()}
    for kind, figures in by_person.items():
        print(f'{kind}: ranking p50 {figures["p50"]:.3f} ms p99 {figures["p99"]:.3f} ms')
    print(f'strangers served: {strangers}; checkpoint {checkpoint.stat().st_size / 2 ** 20:.2f} MiB')
    record = {**run_record(program_argv('benchmarks/stranger_cost.py', argv)),
              'settings': {**vars(args), 'checkpoint': str(checkpoint)}, 'checkpoint_digest': recommender.fingerprint,
              'strangers': strangers,
              'checkpoint_bytes': checkpoint.stat().st_size, 'ranking_ms': by_person}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(record, indent=1) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
