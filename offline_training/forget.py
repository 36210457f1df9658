"""Forget a person in a record folder while no node runs on it: their ratings, model and
journal entries in the state store, their messages in every bag, and a tombstone that keeps
a refit or a late fleet message from bringing them back (docs/privacy.md).

    python -m offline_training.forget --record-folder DIR --user-id ID
    python -m offline_training.forget --record-folder DIR --finish

``--finish`` completes the forgets a kill interrupted (a forget re-run with the same id
does too). Exit 0: done; 2: the folder cannot be changed (a node holds its store, a bag is
damaged, the disk refuses).
"""
from __future__ import annotations

import argparse
import json
import sys

from stars_ros.errors import StarsError
from stars_ros.recording.erasure import finish_interrupted, forget


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--record-folder', required=True, help="the node's record folder (state.db and the bags)")
    what = parser.add_mutually_exclusive_group(required=True)
    what.add_argument('--user-id', help='the id of the person to forget')
    what.add_argument('--finish', action='store_true', help='finish the forgets a kill interrupted, and only those')
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        finished = finish_interrupted(args.record_folder)
        for removed in finished.values():
            print(f'finished an interrupted forget: {json.dumps(removed, sort_keys=True)}')
        if args.user_id is not None:
            removed = forget(args.record_folder, args.user_id)
            print(f'forgot the person: {json.dumps(removed, sort_keys=True)}')
    except (StarsError, OSError, ValueError) as error:
        print(f'error: {error}', file=sys.stderr)
        return 2
    return 0


if __name__ == '__main__':
    sys.exit(main())
