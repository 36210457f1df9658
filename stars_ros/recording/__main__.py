"""``python -m stars_ros.recording recover BAG...``: repair bags left by a hard kill.
``python -m stars_ros.recording state FOLDER [--json]``: the people a node's state store
holds (ratings per person, whether a model is stored, last update), read without taking
the store from the node that holds it."""
import argparse
import datetime
import json
import sys
from pathlib import Path

from stars_ros.recording.recovery import recover
from stars_ros.errors import StoreError
from stars_ros.state import open_reader


def _time(seconds: float) -> str:
    return datetime.datetime.fromtimestamp(seconds, datetime.timezone.utc).strftime('%Y-%m-%d %H:%M:%S UTC')


def show_state(folder: Path, as_json: bool) -> int:
    try:
        with open_reader(folder) as reader:
            meta, people, feedback = reader.meta(), reader.summary(), reader.feedback_count()
    except (FileNotFoundError, StoreError) as error:
        print(f'error: {error}', file=sys.stderr)
        return 1
    if as_json:
        print(json.dumps({'store': str(reader.path), 'schema_version': int(meta['schema_version']),
                          'fingerprint': meta.get('fingerprint'), 'feedback': feedback, 'people': people}, indent=1))
        return 0
    print(f"{reader.path}: schema version {meta['schema_version']}, checkpoint "
          f"{(meta.get('fingerprint') or 'none')[:12]}, {len(people)} people, {feedback} feedback messages journaled")
    for person in people:
        model = ('model solved from them' if person['solved'] else 'model to solve again') if person['model'] else \
            'no model'
        print(f"  {person['person']}: {person['ratings']} ratings, {person['peer_ratings']} from peers, "
              f"{person['dropped']} dropped; {model}; updated {_time(person['updated'])}")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='python -m stars_ros.recording',
                                     description='Repair bags left by a hard kill; list the people of a state store.')
    commands = parser.add_subparsers(dest='command', required=True)
    repair = commands.add_parser('recover', help='repair bags left by a hard kill')
    repair.add_argument('bags', nargs='+', type=Path)
    state = commands.add_parser('state', help="list the people of a record folder's state store")
    state.add_argument('folder', type=Path, help='the record folder (or its state.db)')
    state.add_argument('--json', action='store_true', help='one JSON object instead of lines')
    args = parser.parse_args(argv)
    if args.command == 'state':
        return show_state(args.folder, args.json)
    for bag in args.bags:
        try:
            print(f'{bag}: {recover(bag)}')
        except StoreError as error:
            print(f'error: {bag}: {error}', file=sys.stderr)
            return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
