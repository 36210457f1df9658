"""Refit a checkpoint from the feedback in the ranker's MCAP logs, or from its state store.

    python -m offline_training.refit --checkpoint IN.pt --logs BAG_OR_MCAP [...] --out OUT.pt \
        [--mode user|full] [--data-root ROOT] [--regularisation L] [--epochs N]
    python -m offline_training.refit --checkpoint IN.pt --state RECORD_FOLDER --out OUT.pt [...]

People forgotten in the record folders the logs or the state lie in, and in the folders
``--forgotten`` names (a bag copied out of its folder), are left out (docs/privacy.md).

``--state`` takes each person's ratings as the node's state store holds them now (the most
recent ``fold_in_max_ratings`` it kept, with λ from each stored model), read through
``state.open_reader`` while the node runs or not; the logs hold every rating ever given.

Each /stars/feedback message is joined with the scene request it names: the latest
/stars/scene message with that scene_id logged before it, in the same log (what the node
remembered when the feedback came). The rating that gives is the node's
(foldin.rating_from_feedback), so both sides fold in the same data.

``--mode user`` (default) solves (p_u, b_u) of every user in the logs in closed form, as
the node's online fold-in does (same prior, same λ: by default the one the node logged on
stars/user_model for that user, else 1.0), so the refit checkpoint ranks as the online
fold-in did. New users get rows in the user tables; known users' rows are replaced.
``--mode full`` starts from that and fine-tunes every parameter for ``--epochs`` joint
epochs on the feedback (plus the original ratings when ``--data-root`` is given), with the
checkpoint's own training settings and rating normalisation.

The new checkpoint's metadata keeps the provenance (parent fingerprint, logs, ratings per
user, mode, λ, problems found). Problems with the logs (truncated files, foreign topics,
feedback for scenes never recorded, unknown actions or candidates, unparsable messages)
are counted and printed at the end; the exit code is non-zero only when no usable rating
was found (1) or the inputs cannot be read at all (2).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from stars_ros import StarsRecommender
from stars_ros.data.ratings import load_dataset
from stars_ros.errors import StarsError, StoreError
from stars_ros.evaluation.provenance import program_argv, run_record
from stars_ros.personalisation.refit import LogRatings, forgotten_in, read_logs, read_state, record_folders_of

from .common import setup_logging


def print_report(found: LogRatings, solved: dict, out=None) -> None:
    """What was read, each user's ratings (and λ once solved), and the problems found."""
    out = out or sys.stdout
    print(f'read {len(found.files)} {found.read}, {found.messages} messages; {found.n_ratings} usable ratings '
          f'from {len(found.ratings)} user(s)', file=out)
    if found.not_needed:
        print('not needed for a refit: ' + ', '.join(f'{t} {n}' for t, n in sorted(found.not_needed.items())),
              file=out)
    for user, ratings in sorted(found.ratings.items()):
        model = solved.get(user)
        print(f'  {user}: {len(ratings)} ratings' + (f', λ {model.regularisation:g}' if model else ''), file=out)
    if not found.problems:
        print('problems: none', file=out)
        return
    print(f'problems ({sum(found.problems.values())} messages or files not used):', file=out)
    for kind, count in found.problems.most_common():
        print(f'  {kind}: {count}  e.g. ' + ' | '.join(found.examples[kind]), file=out)


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--checkpoint', required=True, help='the checkpoint the node served')
    inputs = parser.add_mutually_exclusive_group(required=True)
    inputs.add_argument('--logs', nargs='+', help='bag folders or .mcap files recorded by the node')
    inputs.add_argument('--state', help="a record folder (or its state.db): the ratings the node's state store holds")
    parser.add_argument('--out', required=True, help='checkpoint to write')
    parser.add_argument('--mode', choices=['user', 'full'], default='user', help='(default: %(default)s)')
    parser.add_argument('--data-root', help='original ratings to fine-tune on as well (full mode)')
    parser.add_argument('--regularisation', type=float,
                        help="fold-in λ for every user (default: the node's, from stars/user_model, else 1.0)")
    parser.add_argument('--epochs', type=int, default=3, help='joint epochs of full mode (default: %(default)s)')
    parser.add_argument('--forgotten', nargs='+', default=[], metavar='RECORD_FOLDER',
                        help='record folders whose forgotten people are left out (always: the folders the logs '
                             'or the state lie in)')
    parser.add_argument('--verbose', action='store_true')
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    setup_logging(args.verbose)
    started = time.perf_counter()
    try:
        if args.regularisation is not None and not args.regularisation > 0:
            raise StarsError('--regularisation must be positive')
        parent = StarsRecommender.load(args.checkpoint)
        original = load_dataset(args.data_root) if args.data_root and args.mode == 'full' else None
    except (StarsError, OSError) as error:
        print(f'error: {error}', file=sys.stderr)
        return 2
    if args.data_root and args.mode == 'user':
        print('note: --data-root is used by --mode full only; user mode keeps every other parameter fixed')
    try:
        folders = [*map(Path, args.forgotten), *record_folders_of([args.state] if args.state else args.logs)]
        forgotten = forgotten_in(dict.fromkeys(folders))
        found = read_state(args.state, parent.predictor, forgotten) if args.state else \
            read_logs(args.logs, parent.predictor, forgotten)
    except (FileNotFoundError, StoreError) as error:
        print(f'error: {error}', file=sys.stderr)
        return 2
    if not found.ratings:
        print_report(found, {})
        print('error: no usable feedback in the logs; no checkpoint written', file=sys.stderr)
        return 1
    try:
        recommender, solved, failed, losses, fine_tuned_on = parent.refit(
            found.ratings, None if args.regularisation else found.regularisation, original,
            args.epochs if args.mode == 'full' else 0, args.regularisation)
    except StarsError as error:
        print(f'error: {error}', file=sys.stderr)
        return 2
    for user, reason in failed.items():
        found.problem('scene the model cannot encode', f'{user}: {reason}')
        del found.ratings[user]
    print_report(found, solved)
    if not solved:
        print('error: no usable feedback in the logs; no checkpoint written', file=sys.stderr)
        return 1
    if args.mode == 'full':
        print(f'full fine-tune: {args.epochs} joint epochs on {fine_tuned_on} ratings, '
              f'loss {[round(v, 4) for v in losses]}')
    refit = {'mode': args.mode, 'parent_fingerprint': parent.fingerprint,
             'parent_checkpoint': str(args.checkpoint), 'logs': [str(p) for p in args.logs or []],
             'state': args.state, 'files': found.files,
             'ratings_per_user': {u: found.dropped.get(u, 0) + len(r) for u, r in found.ratings.items()},
             'regularisation': {u: m.regularisation for u, m in solved.items()},
             'problems': dict(found.problems), 'epochs': args.epochs if args.mode == 'full' else 0,
             'fine_tune_losses': losses, 'data_root': args.data_root if original is not None else None,
             **run_record(program_argv('offline_training.refit', argv)),
             'seconds': round(time.perf_counter() - started, 2)}
    digest = recommender.save(args.out, provenance={'refit': refit})
    print(f'wrote {args.out} ({args.mode} mode, {len(solved)} user(s), digest {digest[:12]}) in '
          f'{time.perf_counter() - started:.1f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
