"""One scene for two (or more) people side by side, as a PNG: the scene from above (REP 103
axes), each person's ranking of robot placements (or of the model's actions) and the entities
coloured by their removal effect on that person's best entry (docs/explanations.md).

    python -m offline_training.plot_scene --users a b --scene "00008 A" --placements 6 \
        --out docs/scene_two_people.png

The scene is the line of that identifier in the first person's SocNav1 file
(``<data-root>/raw/<user>.jsonl``; default: the first scene every person rated). Needs
matplotlib (requirements-train.txt, the train extra); without it the command says how to install it.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from stars_ros.data.scene_source import PLACEMENTS, read_scenes
from stars_ros.errors import StarsError
from stars_ros.figures.scene import plot_people
from stars_ros.model.predictor import Predictor
from stars_ros.resources import resolve_checkpoint

from .common import DEFAULT_SOCNAV1


def parse_args(argv=None):
    parser = argparse.ArgumentParser(prog='python -m offline_training.plot_scene', description=__doc__.split('\n\n')[0])
    parser.add_argument('--checkpoint', default='', help='default: the packaged models/socnav1_gat_stars.pt')
    parser.add_argument('--data-root', type=Path, default=DEFAULT_SOCNAV1, help='SocNav1 root (default: %(default)s)')
    parser.add_argument('--users', nargs='+', required=True, help='the people (annotators), one panel each')
    parser.add_argument('--scene', help='identifier of the scene (default: the first one every person rated)')
    parser.add_argument('--placements', type=int, default=6, choices=range(0, len(PLACEMENTS) + 1),
                        metavar=f'0..{len(PLACEMENTS)}',
                        help="robot placements ranked (0: rank the model's actions instead; default: %(default)s)")
    parser.add_argument('--action', help="the action whose score ranks placements (default: the model's first)")
    parser.add_argument('--out', type=Path, required=True, help='PNG to write')
    return parser.parse_args(argv)


def choose_scene(root: Path, users: list, identifier: str | None) -> dict:
    """The scene ``identifier`` from the first user's file, or the first every user rated."""
    rated = []
    for user in users:
        path = root / 'raw' / f'{user}.jsonl'
        if not path.exists():
            raise StarsError(f'no ratings of {user!r}: {path} does not exist')
        rated.append({scene.get('identifier'): scene for scene in read_scenes(path)})
    if identifier is not None:
        if identifier not in rated[0]:
            raise StarsError(f'{users[0]!r} did not rate scene {identifier!r}')
        return rated[0][identifier]
    shared = [key for key in rated[0] if all(key in other for other in rated[1:])]
    if not shared:
        raise StarsError(f'no scene rated by all of {users}')
    return rated[0][shared[0]]


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        predictor = Predictor.load(resolve_checkpoint(args.checkpoint))
        scene = choose_scene(args.data_root, args.users, args.scene)
        title = f"scene {scene.get('identifier', '')}: " + (
            f'{args.placements} robot placements by {args.action or predictor.actions[0]!r}'
            if args.placements else 'the actions')
        path = plot_people(predictor, scene, args.users, args.out, args.placements, args.action, title)
    except StarsError as error:
        print(f'plot_scene: {error}', file=sys.stderr)
        return 1
    print(path)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
