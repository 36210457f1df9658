"""The posterior head for strangers on SocNav1, point estimate against head in every outer
fold of the cold-user protocol (``stars_ros.evaluation.head_strangers`` says what is compared).

    OMP_NUM_THREADS=1 python -m offline_training.head_strangers

Writes ``results.json`` into ``--out``.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import torch

from stars_ros.data.ratings import load_dataset
from stars_ros.evaluation.head_strangers import compare
from stars_ros.evaluation.provenance import program_argv, run_record
from stars_ros.model.config import ExperimentConfig

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--config', default='config/socnav1_gat_posterior.yaml',
                        help='the head settings, relative to the repository root (default: %(default)s)')
    parser.add_argument('--folds', type=int, default=5)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--out', default=str(REPO / 'results/head-strangers-socnav1'))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format='%(asctime)s %(message)s')
    torch.set_num_threads(1)
    record = run_record(program_argv('offline_training.head_strangers', argv))
    config = ExperimentConfig.from_yaml(REPO / args.config)
    data = load_dataset('socnav1')
    started = time.perf_counter()
    folds, summary = compare(data, config, args.folds, args.seed, log=lambda line: print(line, flush=True))
    print(f"mean MSE point {summary['point_mse']:.5f}, head {summary['head_mse']:.5f}; "
          f"the head better in {summary['head_better_in']} of {len(folds)} folds")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / 'results.json').write_text(json.dumps(
        {**record, 'config': args.config, 'protocol': 'cold-user', 'folds_seed': args.seed,
         'folds': folds, 'summary': summary, 'seconds': round(time.perf_counter() - started, 1)}, indent=1) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
