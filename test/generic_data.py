"""Writing small data sets in the generic format (``scenes.csv`` + ``annotations.csv``) for tests."""
import csv
from pathlib import Path


def write_generic_data(root: Path, features, ratings) -> Path:
    """``features``: one row of floats per scene (named s0, s1, ...); ``ratings``: (user, scene,
    action, score) rows. Returns ``root``."""
    with (root / 'scenes.csv').open('w', newline='') as handle:
        writer = csv.writer(handle)
        writer.writerow(['scene'] + [f'f{j}' for j in range(len(features[0]))])
        writer.writerows([f's{i}'] + list(row) for i, row in enumerate(features))
    with (root / 'annotations.csv').open('w', newline='') as handle:
        writer = csv.writer(handle)
        writer.writerow(['user', 'scene', 'action', 'score'])
        writer.writerows(ratings)
    return root
