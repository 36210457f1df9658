"""What implicit outcomes (stays engaged / disengages after the robot acts) are worth against
explicit ratings: the simulation of ``stars_ros.evaluation.implicit`` on SocNav1 and on the
generated crowd data.

    python -m offline_training.implicit_feedback --out results/implicit-feedback [--quick]

Per data set, people are dealt into ``--folds`` leave-people-out folds; per fold a model is
trained on the other people (SocNav1: config/socnav1_gat.yaml, the published settings; crowd:
config/implicit_crowd.yaml; ``--config DATASET=PATH`` trains with another) by the one recipe
(``stars_ros.personalisation.recipe``). Each held-out person's seeded pool of ``--pool`` examples is
where the robot acts; the rest are test rows.
MSE per number n of implicit outcomes (``--flips``: ε of the outcome model; its exact
expectation over every outcome sequence up to ``--exact-up-to`` outcomes, above that
``--draws`` Bernoulli draws per person and n, averaged) and per number k of explicit ratings, pooled over
a fold's test rows, mean ± sd over folds; people whose pool has fewer than max k ratings are
left out and counted. Writes results.json, results.md and implicit.png.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
from threadpoolctl import threadpool_limits

from stars_ros.evaluation.provenance import program_argv, run_record
from stars_ros.evaluation.implicit_run import CONFIGS, rewrite, run_dataset, write_report

from .common import DEFAULT_SOCNAV1, setup_logging

NS = (0, 1, 2, 4, 8, 16, 32, 64, 128)
KS = (0, 1, 2, 4, 8, 16)


def parse_args(argv=None):
    parser = argparse.ArgumentParser(prog='python -m offline_training.implicit_feedback', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--out', type=Path, default=Path('results/implicit-feedback'))
    parser.add_argument('--data-root', type=Path, default=DEFAULT_SOCNAV1, help='SocNav1 (default: %(default)s)')
    parser.add_argument('--datasets', nargs='+', choices=list(CONFIGS), default=list(CONFIGS))
    parser.add_argument('--config', dest='configs', action='append', default=[], metavar='DATASET=PATH',
                        help='train that data set\'s fold models with another config (default: '
                             + ', '.join(f'{name}={path}' for name, path in CONFIGS.items()) + ')')
    parser.add_argument('--folds', type=int, default=4, help='leave-people-out folds (default: %(default)s)')
    parser.add_argument('--pool', type=int, default=16, help='pool examples per held-out person (default: %(default)s)')
    parser.add_argument('--flips', type=float, nargs='+', default=[0.0, 0.2],
                        help='ε: share of outcomes that are coin flips (default: %(default)s)')
    parser.add_argument('--draws', type=int, default=16,
                        help='outcome draws per person and n above --exact-up-to (default: %(default)s)')
    parser.add_argument('--exact-up-to', type=int, default=4,
                        help='largest n whose expectation is computed exactly, over its 2^n outcome sequences '
                             '(default: %(default)s)')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--quick', action='store_true', help='pipeline check: 2 folds, 1 draw, n ≤ 16, k ≤ 4')
    parser.add_argument('--rewrite-report', action='store_true',
                        help="recompute the summary and results.md from --out's results.json, running nothing")
    parser.add_argument('--verbose', action='store_true')
    args = parser.parse_args(argv)
    configs = [item.partition('=') for item in args.configs]
    unknown = [name for name, _, _ in configs if name not in CONFIGS]
    if unknown or any(not path for _, _, path in configs):
        parser.error(f'--config takes DATASET=PATH, DATASET one of {list(CONFIGS)}; got {args.configs}')
    args.configs = {name: path for name, _, path in configs}
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    setup_logging(args.verbose)
    torch.set_num_threads(1)
    threadpool_limits(1, user_api='blas')  # the fold-ins' small solves: extra BLAS threads only wait for each other
    ns, ks = (NS, KS) if not args.quick else (tuple(n for n in NS if n <= 16), tuple(k for k in KS if k <= 4))
    if args.quick:
        args.folds, args.draws = 2, 1
    args.out.mkdir(parents=True, exist_ok=True)
    if args.rewrite_report:
        rewrite(args.out)
        return 0
    started = time.time()
    results = {**run_record(program_argv('offline_training.implicit_feedback', argv)),
               'ns': list(ns), 'ks': list(ks), 'flips': args.flips, 'draws': args.draws,
               'exact_up_to': args.exact_up_to,
               'pool': args.pool,
               'folds': args.folds, 'seed': args.seed,
               'datasets': {name: run_dataset(name, args, ns, ks) for name in args.datasets}}
    results['seconds'] = time.time() - started
    (args.out / 'results.json').write_text(json.dumps(results, indent=1) + '\n')
    write_report(args.out, results, ns, ks)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
