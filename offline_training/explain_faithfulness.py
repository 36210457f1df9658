"""How faithful the removal effects of a checkpoint's explanations are, on SocNav1 scenes it
never trained on, and how GNNExplainer (torch_geometric.explain) compares.

    python -m offline_training.explain_faithfulness --data-root ../shared/datasets/socnav1 \
        --scenes 200 --gnnexplainer-scenes 30 --out results/explain-faithfulness-socnav1

Held-out scenes are those none of whose ratings is in the checkpoint's training rows: the
split the checkpoint records (``data.split``: test fraction and seed of ``split_rows``) redrawn
on the same data (its fingerprint must match). Each scene is explained for the annotator who
rated it. Writes ``command.txt``, ``machine.json``, ``results.json`` and ``results.md`` (see
``stars_ros.evaluation.explanations`` for what each figure is).
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

from stars_ros.data.ratings import load_dataset
from stars_ros.data.scene_source import read_scenes
from stars_ros.errors import StarsError
from stars_ros.evaluation.explanations import compare_gnnexplainer, faithfulness, held_out_scenes
from stars_ros.evaluation.provenance import program_argv, run_record, write_run_files
from stars_ros.model.checkpoint import load_checkpoint
from stars_ros.model.predictor import Predictor
from stars_ros.model.training import split_rows
from stars_ros.resources import resolve_checkpoint

from .common import DEFAULT_SOCNAV1


def parse_args(argv=None):
    parser = argparse.ArgumentParser(prog='python -m offline_training.explain_faithfulness',
                                     description=__doc__.split('\n\n')[0])
    parser.add_argument('--checkpoint', default='', help='default: the packaged models/socnav1_gat_stars.pt')
    parser.add_argument('--data-root', type=Path, default=DEFAULT_SOCNAV1, help='SocNav1 root (default: %(default)s)')
    parser.add_argument('--scenes', type=int, default=200, help='held-out scenes sampled (default: %(default)s)')
    parser.add_argument('--gnnexplainer-scenes', type=int, default=30,
                        help='of those, the first N compared with GNNExplainer (default: %(default)s)')
    parser.add_argument('--epochs', type=int, default=100, help="GNNExplainer's epochs (default: %(default)s)")
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--out', type=Path, required=True, help='results folder')
    return parser.parse_args(argv)


def _sample(predictor, data, root: Path, count: int, seed: int) -> tuple[list, list, int]:
    """([scene JSON], [user]) of ``count`` held-out scenes drawn with ``seed``, and how many there are."""
    split = predictor.metadata.get('data', {}).get('split')
    if not isinstance(split, dict):
        raise StarsError(f'the checkpoint records no row split ({split!r}): it trained on every rating')
    if predictor.metadata['data'].get('fingerprint') != data.fingerprint:
        raise StarsError(f'{root} is not the data the checkpoint was trained on (fingerprints differ)')
    train, test = split_rows(data, split['test_fraction'], split['seed'])
    held = [(row, user) for row, user in held_out_scenes(data, train, test) if '#' not in data.scene_keys[row]]
    chosen = np.random.default_rng(seed).permutation(len(held))[:count]
    lines = {}
    scenes, users = [], []
    for k in chosen:
        row, user = held[int(k)]
        if user not in lines:
            lines[user] = {s['identifier']: s for s in read_scenes(root / 'raw' / f'{user}.jsonl')}
        scenes.append(lines[user][data.scene_keys[row]])
        users.append(user)
    return scenes, users, len(held)


def _shown(path) -> str:
    """``path`` relative to the current folder when it is inside it (results stay portable)."""
    path = Path(path).resolve()
    return str(path.relative_to(Path.cwd())) if path.is_relative_to(Path.cwd()) else str(path)


def _markdown(results: dict) -> str:
    f, g = results['faithfulness'], results['gnnexplainer']
    return f"""# Faithfulness of the removal effects, and GNNExplainer, on held-out SocNav1 scenes

`{results['command']}` ({results['checkpoint']}; {f['scenes']} of the {results['held_out_scenes']} scenes none of
whose ratings the checkpoint trained on, each for the annotator who rated it; action `{results['action']}`)

| figure | value |
| --- | --- |
| removing the top-\\|effect\\| entity changes the score more than removing a random other entity | {f['top_beats_random']:.1%} of scenes |
| interaction share (all removed − Σ single) / \\|all\\|, median (quartiles) | {f['interaction_share_median']:.2f} ({f['interaction_share_quartiles'][0]:.2f} … {f['interaction_share_quartiles'][1]:.2f}) |
| \\|interaction share\\|, median | {f['interaction_share_abs_median']:.2f} |
| Σ single-entity effects, median / effect of removing all, median | {f['sum_of_single_effects_median']:.4f} / {f['effect_of_removing_all_median']:.4f} |
| removal effects, ms per scene (p50) | {f['removal_ms_per_scene_p50']:.2f} |

GNNExplainer ({g['epochs']} epochs, node mask, regression; first {g['scenes']} scenes of the sample):

| figure | value |
| --- | --- |
| Spearman ρ of its node mask with \\|removal effect\\|, median (mean; scenes) | {g['spearman_with_removal_median']:.2f} ({g['spearman_with_removal_mean']:.2f}; {g['spearman_scenes']}) |
| same top entity as the removal effects | {g['same_top_entity']:.1%} of scenes |
| removing its top entity changes the score more than a random other entity | {g['gnnexplainer_top_beats_random']:.1%} of scenes |
| ms per scene (p50): GNNExplainer / removal effects | {g['gnnexplainer_ms_per_scene_p50']:.1f} / {g['removal_ms_per_scene_p50']:.2f} |

Captum (for `CaptumExplainer`, integrated gradients) is not installed, so only GNNExplainer is compared.
Wall time {results['wall_seconds']:.0f} s on {results['machine']['cpus']} CPUs, one torch and one BLAS thread.
"""  # noqa: E501 - a markdown table: one row a line


def main(argv=None) -> int:
    args = parse_args(argv)
    torch.set_num_threads(1)
    threadpool_limits(1, user_api='blas')
    started = time.perf_counter()
    try:
        checkpoint = resolve_checkpoint(args.checkpoint)
        predictor = Predictor.load(checkpoint)
        if predictor.input_kind != 'graph':
            raise StarsError('removal effects of scene entities need a graph model')
        data = load_dataset(args.data_root)
        scenes, users, held = _sample(predictor, data, args.data_root, args.scenes, args.seed)
    except StarsError as error:
        print(f'explain_faithfulness: {error}', file=sys.stderr)
        return 1
    action = predictor.actions[0]
    column = predictor.action_columns([action])[0]
    print(f'{held} held-out scenes; explaining {len(scenes)}', flush=True)
    results = {**run_record(program_argv('offline_training.explain_faithfulness', argv)),
               'checkpoint': _shown(checkpoint), 'fingerprint': predictor.fingerprint, 'held_out_scenes': held,
               'action': action, 'seed': args.seed,
               'faithfulness': faithfulness(predictor, scenes, users, column)}
    print(json.dumps(results['faithfulness']), flush=True)
    count = args.gnnexplainer_scenes
    model = load_checkpoint(checkpoint)[0].require_model()  # GNNExplainer differentiates the torch model
    results['gnnexplainer'] = compare_gnnexplainer(predictor, model, scenes[:count], users[:count], column,
                                                   args.epochs, args.seed)
    print(json.dumps(results['gnnexplainer']), flush=True)
    results['wall_seconds'] = time.perf_counter() - started
    args.out.mkdir(parents=True, exist_ok=True)
    write_run_files(args.out, results)
    (args.out / 'results.json').write_text(json.dumps(results, indent=2) + '\n')
    (args.out / 'results.md').write_text(_markdown(results))
    print(f'wrote {args.out}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
