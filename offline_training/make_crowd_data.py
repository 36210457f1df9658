"""Write the generated MannersDB+-shaped crowd data set (stars_ros.evaluation.crowd_data) in the generic
format.

    python -m offline_training.make_crowd_data --out data/crowd [--seed 0]

Then point the tabular programs at it, e.g.
``python -m offline_training.evaluate --config config/eval_tabular.yaml --data-root data/crowd``.
"""
from __future__ import annotations

import argparse
import sys

from stars_ros.evaluation import crowd_data


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--out', required=True, help='folder for annotations.csv and scenes.csv')
    parser.add_argument('--seed', type=int, default=0, help='generator seed (default: %(default)s)')
    args = parser.parse_args(argv)
    root = crowd_data.write(args.out, seed=args.seed)
    annotations, scenes = (root / 'annotations.csv'), (root / 'scenes.csv')
    print(f'wrote {annotations} and {scenes}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
