"""Scene-graph featurisation speed on one core, over every SocNav1 line.

    python benchmarks/featurise.py [--data-root ../shared/datasets/socnav1]

Prints scenes per second with and without schema validation, and writes
results/featurise.json.
"""
import argparse
import json
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # offline_training is the checkout's, not installed

from offline_training.common import DEFAULT_SOCNAV1  # noqa: E402
from stars_ros.evaluation.provenance import git_state, machine  # noqa: E402
from stars_ros.data.scene_graph import featurise, validate_scene  # noqa: E402


def rate(function, scenes, repeats=3):
    best = float('inf')
    for _ in range(repeats):
        started = time.perf_counter()
        for scene in scenes:
            function(scene)
        best = min(best, time.perf_counter() - started)
    return len(scenes) / best


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--data-root', default=str(DEFAULT_SOCNAV1))
    parser.add_argument('--out', default=str(Path(__file__).resolve().parents[1] / 'results' / 'featurise.json'))
    args = parser.parse_args()
    torch.set_num_threads(1)
    scenes = [json.loads(line) for path in sorted(Path(args.data_root, 'raw').glob('*.jsonl'))
              for line in path.read_text().splitlines()]
    figures = {
        'scenes': len(scenes),
        'validate_only_per_s': rate(validate_scene, scenes),
        'featurise_without_validation_per_s': rate(lambda s: featurise(s, validate=False), scenes),
        'featurise_with_validation_per_s': rate(featurise, scenes),
        'machine': machine(), 'git': git_state(),
    }
    for key, value in figures.items():
        if key.endswith('_per_s'):
            print(f'{key}: {value:,.0f} scenes/s ({1e3 / value:.3f} ms/scene)')
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(figures, indent=2) + '\n')


if __name__ == '__main__':
    main()
