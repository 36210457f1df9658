"""The Bayesian head (``training.posterior_sweeps``) on one outer fold of SocNav1: point
estimate, posterior-mean model and averaged prediction for each sweep count
(``stars_ros.evaluation.bayes_head_fold`` says what is compared).

    OMP_NUM_THREADS=1 python -m offline_training.bayes_head_fold --sweeps 50 200

Writes ``results.json`` into ``--out``.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import torch

from stars_ros.data.ratings import load_dataset
from stars_ros.evaluation.bayes_head_fold import heads_on_first_fold
from stars_ros.evaluation.protocol import ProtocolConfig
from stars_ros.evaluation.provenance import program_argv, run_record

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--data', default='socnav1')
    parser.add_argument('--protocol', default='config/eval_socnav1_peers.yaml', help='relative to the repository root')
    parser.add_argument('--backbone', default='gat')
    parser.add_argument('--epochs', type=int, nargs=2, default=(10, 40), metavar=('T1', 'T2'))
    parser.add_argument('--embedding-l2', type=float, default=0.01)
    parser.add_argument('--sweeps', type=int, nargs='+', default=(50, 200))
    parser.add_argument('--burn-in', type=int, default=20)
    parser.add_argument('--out', default=str(REPO / 'results/bayes-head-socnav1-fold0'))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format='%(asctime)s %(message)s')
    torch.set_num_threads(1)
    record = run_record(program_argv('offline_training.bayes_head_fold', argv))
    data = load_dataset(args.data)
    protocol = ProtocolConfig.from_yaml(REPO / args.protocol)
    results = heads_on_first_fold(data, protocol, args.backbone, tuple(args.epochs), args.embedding_l2,
                                  list(args.sweeps), args.burn_in, log=lambda line: print(line, flush=True))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / 'results.json').write_text(json.dumps({**record, 'protocol': args.protocol, **results}, indent=2))
    print(f'wrote {out / "results.json"}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
