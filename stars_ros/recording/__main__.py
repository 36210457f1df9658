"""``python -m stars_ros.recording recover BAG...``: repair bags left by a hard kill."""
import argparse
import sys
from pathlib import Path

from stars_ros.recording.recovery import recover


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='python -m stars_ros.recording', description=__doc__)
    parser.add_argument('command', choices=['recover'])
    parser.add_argument('bags', nargs='+', type=Path)
    args = parser.parse_args(argv)
    for bag in args.bags:
        print(f'{bag}: {recover(bag)}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
