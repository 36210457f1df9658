"""What a person's placement map costs on one core with the packaged GAT (issue 64's goals:
p50 within 25 ms for 32 × 32 cells and 100 ms for 64 × 64, at least 3× faster than (b)),
beside, in the same run and on the same valid cells:

(a) the ranker's point-wise path: each cell's candidate scene (``placements.placed_scene``)
    through ``StarsRecommender.predict_batch`` with score_sd (one encoder pass per call);
(b) what a user would write with the trained torch encoder: each cell's candidate scene
    featurised, the graphs collated into one PyG ``Batch``, the encoder (for a stranger also
    the plain encoder they are served) run over it in torch, scores from h (no score_sd);
    its forward passes alone are kept too;
(c) the arithmetic's bound: the multiply-adds of the map's encoder passes and score_sd over
    this machine's single-core float32 matmul rate, measured in the same run.

    python benchmarks/placement_map.py [--scenes 20] [--rounds 3] [--data-root ../shared/datasets/socnav1] \
        [--out results/placement_map.json]

8 m grids (the issue's): 32 × 32 cells (0.25 m) and 64 × 64 (0.125 m), over ``--scenes`` SocNav1
scenes (every 50th line of annotator b's file), for a trained person (annotator a) and a
stranger. The paths take turns scene by scene, so the machine's drift reaches all alike. One
torch, BLAS and numba thread.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from threadpoolctl import threadpool_limits

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from ensemble_cost import percentiles  # noqa: E402  (figures summarised the same way)
from offline_training.common import DEFAULT_SOCNAV1  # noqa: E402
from stars_ros import StarsRecommender  # noqa: E402
from stars_ros.data.placements import featurise_placements, placed_scene  # noqa: E402
from stars_ros.data.scene_graph import featurise  # noqa: E402
from stars_ros.data.scene_source import read_scenes  # noqa: E402
from stars_ros.data.scene_store import GraphBatch  # noqa: E402
from stars_ros.evaluation.provenance import program_argv, run_record  # noqa: E402
from stars_ros.resources import resolve_checkpoint  # noqa: E402

GRIDS = {'32x32': 0.25, '64x64': 0.125}  # cells: resolution (m) over 8 m
GOALS_MS = {'32x32': 25.0, '64x64': 100.0}
GOAL_SPEEDUP = 3.0


def timed(run) -> float:
    started = time.perf_counter()
    run()
    return (time.perf_counter() - started) * 1e3


def matmul_gflops(rows: int = 65536, width: int = 64, repeats: int = 7) -> float:
    """Best single-thread float32 rate of the product the map does most: [rows, width] @ [width, width]."""
    rng = np.random.default_rng(0)
    a = rng.standard_normal((rows, width), dtype=np.float32)
    b = rng.standard_normal((width, width), dtype=np.float32)
    best = min(timed(lambda: a @ b) for _ in range(repeats))
    return 2 * rows * width * width / (best * 1e6)


def map_multiply_adds(batch, config, passes: int) -> int:
    """Multiply-adds of ``passes`` GAT passes over ``batch`` (projection, per layer the
    values, the attention scores and the weighted sums over each edge and self loop, the
    readout), plus the scores and score_sd (xᵀΣx) of its cells."""
    cells, nodes, features = batch.x.shape
    edges = batch.edge_index.shape[1] + nodes  # GATConv adds a self loop per node
    hidden, dim, layers = config.encoder.hidden, config.model.dim, config.encoder.layers
    per_layer = nodes * hidden * hidden + 2 * nodes * hidden + edges * hidden
    per_graph = nodes * features * hidden + layers * per_layer + 2 * hidden * hidden + hidden * dim
    return cells * (passes * per_graph + dim + (dim + 1) ** 2)


def torch_map(fitted, user_row, scene, x, y, heading, timings) -> np.ndarray:
    """Path (b): scores of the cells at (x, y) m, the stranger's plain encoder where ``user_row`` is None."""
    from torch_geometric.data import Batch, Data

    graphs = [featurise(placed_scene(scene, cx, cy, heading)) for cx, cy in zip(x, y)]
    batch = Batch.from_data_list([Data(x=torch.from_numpy(g.x), edge_index=torch.from_numpy(g.edge_index),
                                       edge_type=torch.from_numpy(g.edge_type)) for g in graphs])
    graphs = GraphBatch(batch.x, batch.edge_index, batch.edge_type, batch.batch, batch.ptr[:-1],
                        batch.num_graphs)
    started = time.perf_counter()
    with torch.inference_mode():
        unknown = torch.full((len(x),), -1)
        if user_row is None:
            fitted.model.encoder(graphs)  # the uncertainty's h, as the map computes it
            plain = fitted.stranger_model
            scores = plain.to_rating_scale(plain(unknown, unknown, plain.encoder(graphs)))
        else:
            model = fitted.model
            users = torch.full((len(x),), user_row)
            scores = model.to_rating_scale(model(users, unknown, model.encoder(graphs)))
    timings.append((time.perf_counter() - started) * 1e3)
    return scores.numpy()[:, 0]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--checkpoint', help='default: the packaged model')
    parser.add_argument('--scenes', type=int, default=20, help='SocNav1 scenes (default: %(default)s)')
    parser.add_argument('--rounds', type=int, default=3,
                        help="the map's timings per scene (default: %(default)s)")
    parser.add_argument('--data-root', default=str(DEFAULT_SOCNAV1))
    parser.add_argument('--out', default=str(REPO / 'results' / 'placement_map.json'))
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    threadpool_limits(1)
    checkpoint = Path(resolve_checkpoint(args.checkpoint))
    recommender = StarsRecommender.load(checkpoint)
    fitted, config, action = recommender.fitted, recommender.config, recommender.actions[0]
    scenes = read_scenes(Path(args.data_root) / 'raw' / 'b.jsonl')[::50][:args.scenes]
    people = {'trained': recommender.users[0], 'stranger': 'a stranger'}
    rows = {'trained': recommender.predictor.trained_row(people['trained']), 'stranger': None}
    for person in people.values():  # warm: kernels compiled, the uncertainty's solver made
        recommender.placement_map(person, scenes[0], 8.0, 0.25)
        recommender.predict_batch([(person, scenes[0], action)], uncertainty=True)
    rate = matmul_gflops()
    paths = ('map', 'pointwise', 'torch', 'torch_forward', 'bound')
    ms = {grid: {kind: {path: [] for path in paths} for kind in people} for grid in GRIDS}
    cells, worst = {grid: [] for grid in GRIDS}, 0.0
    for n, scene in enumerate(scenes):
        for grid, resolution in GRIDS.items():
            for kind in np.roll(list(people), n):
                person, figures = people[kind], ms[grid][kind]
                for _ in range(args.rounds):
                    figures['map'].append(timed(
                        lambda: recommender.placement_map(person, scene, 8.0, resolution)))
                placement_map = recommender.placement_map(person, scene, 8.0, resolution)
                x, y = (c[placement_map.valid] for c in placement_map.centres())
                requests = [(person, placed_scene(scene, cx, cy), action) for cx, cy in zip(x, y)]
                figures['pointwise'].append(timed(
                    lambda: recommender.predict_batch(requests, uncertainty=True)))
                scores = []
                figures['torch'].append(timed(lambda: scores.append(
                    torch_map(fitted, rows[kind], scene, x, y, None, figures['torch_forward']))))
                clipped = np.clip(scores[0], *recommender.rating_scale)  # as served
                worst = max(worst, float(np.abs(clipped - placement_map.score[placement_map.valid]).max()))
                batch = featurise_placements(scene, x, y)
                passes = 1 if kind == 'trained' else 2  # a stranger: the plain encoder and the uncertainty's
                figures['bound'].append(2 * map_multiply_adds(batch, config, passes) / (rate * 1e6))
                if kind == 'trained':
                    cells[grid].append(int(len(x)))
    summary, goals = {}, {}
    for grid in GRIDS:
        summary[grid] = {kind: {path: percentiles(values) for path, values in figures.items()}
                         for kind, figures in ms[grid].items()}
        for kind, figures in summary[grid].items():
            p50 = {path: figures[path]['p50'] for path in paths}
            print(f"{grid} {kind}: map p50 {p50['map']:.1f} ms p99 {figures['map']['p99']:.1f} | point-wise "
                  f"{p50['pointwise']:.1f} | torch+PyG {p50['torch']:.1f} "
                  f"(forward {p50['torch_forward']:.1f}) | bound {p50['bound']:.1f} ms")
            goals[f'{grid}_{kind}'] = {
                'p50_ms': p50['map'], 'goal_ms': GOALS_MS[grid], 'within_goal': p50['map'] <= GOALS_MS[grid],
                'speedup_vs_torch': p50['torch'] / p50['map'],
                'speedup_vs_torch_forward': p50['torch_forward'] / p50['map'],
                'at_least_3x_vs_torch': p50['torch'] / p50['map'] >= GOAL_SPEEDUP,
                'at_least_3x_vs_torch_forward': p50['torch_forward'] / p50['map'] >= GOAL_SPEEDUP,
                'speedup_vs_pointwise': p50['pointwise'] / p50['map'],
                'times_the_bound': p50['map'] / p50['bound']}
        print(f"{grid}: valid cells per map, median {np.median(cells[grid]):.0f} "
              f"of {(8 / GRIDS[grid]) ** 2:.0f}")
    print(f'single-core float32 matmul: {rate:.1f} GFLOP/s; '
          f'torch path vs map, largest score difference {worst:.1e}')
    for name, goal in goals.items():
        print(f"{name}: p50 {goal['p50_ms']:.1f} ms (goal {goal['goal_ms']:.0f}: {goal['within_goal']}), "
              f"{goal['speedup_vs_torch']:.1f}× torch+PyG, "
              f"{goal['speedup_vs_torch_forward']:.1f}× its forward")
    record = {**run_record(program_argv('benchmarks/placement_map.py', argv)),
              'settings': {**vars(args), 'checkpoint': str(checkpoint), 'grids_m': GRIDS, 'size_m': 8.0},
              'checkpoint_digest': recommender.fingerprint, 'matmul_gflops': rate,
              'valid_cells': {grid: {'median': float(np.median(v)), 'min': min(v), 'max': max(v)}
                              for grid, v in cells.items()},
              'torch_vs_map_largest_score_difference': worst, 'ms': summary, 'goals': goals}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(record, indent=1) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
