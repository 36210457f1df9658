"""Two levers of StARS, seeds averaged and a longer budget, on a nested protocol run's choices
(``stars_ros.evaluation.levers`` says what is trained and compared).

    OMP_NUM_THREADS=1 python -m offline_training.stars_levers --run gin=results/socnav1-bayes-rows \\
        --run graphsage=results/socnav1-bayes-rows --run gat=results/socnav1-bayes-gat-rows --jobs 2 \\
        --members 5 --peer-members 5 --out results/seed-ensemble-socnav1

Writes ``predictions/`` (each member's) and ``results.json`` into ``--out``; ``--resume``
trains only the members not yet there.
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from stars_ros.data.ratings import load_dataset
from stars_ros.errors import StarsError
from stars_ros.evaluation.levers import TESTS, Levers, run
from stars_ros.evaluation.provenance import program_argv, run_record

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--run', action='append', required=True, metavar='BACKBONE=FOLDER',
                        help='a backbone and the rows-protocol results folder whose choices it takes '
                             '(relative to the repository root)')
    parser.add_argument('--members', type=int, default=5, help='StARS seeds averaged (default: %(default)s)')
    parser.add_argument('--peer-members', type=int, default=0,
                        help='seeds of myFM on base h_i averaged (default: %(default)s, none)')
    parser.add_argument('--extra-epochs', type=int, default=0,
                        help='joint epochs past the chosen T2 for every StARS member (default: %(default)s)')
    parser.add_argument('--data-root', default='socnav1')
    parser.add_argument('--jobs', type=int, default=1)
    parser.add_argument('--resume', action='store_true', help='keep the members already in the folder')
    parser.add_argument('--out', required=True, help='results folder (predictions/ and results.json)')
    args = parser.parse_args(argv)
    if args.members < 1 or args.peer_members < 0 or args.extra_epochs < 0 or args.jobs < 1:
        parser.error('--members and --jobs must be positive, --peer-members and --extra-epochs not negative')
    logging.basicConfig(level=logging.WARNING, format='%(asctime)s %(message)s')
    record = run_record(program_argv('offline_training.stars_levers', argv))
    out = Path(args.out)
    (out / 'predictions').mkdir(parents=True, exist_ok=True)
    if not args.resume:
        for stale in (out / 'predictions').glob('*.npy'):
            stale.unlink()
    runs = [(backbone, REPO / folder) for backbone, _, folder in (spec.partition('=') for spec in args.run)]
    levers = Levers(args.members, args.peer_members, args.extra_epochs)
    try:
        data = load_dataset(args.data_root)
        summary = run(data, runs, levers, out, args.jobs, record, log=lambda line: print(line, flush=True))
    except (StarsError, OSError) as error:
        print(f'error: {error}', file=sys.stderr)
        return 2
    for backbone, entry in summary['backbones'].items():
        if 'peer_mse' in entry:
            print(f"{backbone}: the run's StARS {entry['run_stars_mse']:.5f}, one seed {entry['one_seed_mse']:.5f}, "
                  f"mean of {args.members} {entry['ensemble_mse']:.5f}, {entry['peer']} {entry['peer_mse']:.5f}")
            for name, _, _ in TESTS:
                if name in entry:
                    print(f"  {name}: {entry[name]['delta']:+.5f} (t {entry[name]['t']:.2f}, "
                          f"Holm p {entry[name]['holm_p']:.3f})")
    return 0


if __name__ == '__main__':
    sys.exit(main())
