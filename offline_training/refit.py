"""Refit a checkpoint from the feedback in the ranker's MCAP logs, or from its state store.

    python -m offline_training.refit --checkpoint IN.pt --logs BAG_OR_MCAP [...] --out OUT.pt \
        [--mode user|full] [--data-root ROOT] [--regularisation L] [--epochs N]
    python -m offline_training.refit --checkpoint IN.pt --state RECORD_FOLDER --out OUT.pt [...]

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
import collections
import shlex
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from mcap.exceptions import McapError

from stars_ros import messages
from stars_ros import recording, state
from stars_ros.model.checkpoint import save_checkpoint
from stars_ros.data.ratings import RatingData, load_dataset
from stars_ros.errors import OutOfScaleError, StarsError, StoreError
from stars_ros.personalisation.foldin import DEFAULT_REGULARISATION, FoldIn, rating_from_feedback
from stars_ros.state import check_score, scene_digest
from stars_ros.model.predictor import Predictor
from stars_ros.data.scene_graph import featurise
from stars_ros.data.scene_store import GraphStore, TabularStore
from stars_ros.model.training import StarsTrainer

from .common import setup_logging

USED_TOPICS = ('stars/scene', 'stars/feedback', 'stars/user_model')
OTHER_STARS_TOPICS = ('stars/ranking', 'stars/errors', 'stars/user_id')


@dataclass
class LogRatings:
    """What the logs hold: ratings per user (in log order), λ the node used, problems."""

    ratings: dict = field(default_factory=dict)          # user -> [Rating]
    regularisation: dict = field(default_factory=dict)   # user -> λ last logged on stars/user_model
    problems: collections.Counter = field(default_factory=collections.Counter)
    examples: dict = field(default_factory=dict)         # problem -> first few details
    messages: int = 0
    dropped: dict = field(default_factory=dict)          # user -> older ratings the store no longer keeps
    read: str = 'MCAP file(s)'                           # what ``files`` are
    not_needed: collections.Counter = field(default_factory=collections.Counter)  # rankings, errors, user ids
    files: list = field(default_factory=list)

    def problem(self, kind: str, detail: str):
        self.problems[kind] += 1
        self.examples.setdefault(kind, [])
        if len(self.examples[kind]) < 3:
            self.examples[kind].append(detail)

    @property
    def n_ratings(self) -> int:
        return sum(len(r) for r in self.ratings.values())


def _topic(name: str) -> str | None:
    """The stars topic a recorded channel carries (any namespace), or None if foreign."""
    for topic in USED_TOPICS + OTHER_STARS_TOPICS:
        if name == topic or name.endswith('/' + topic):
            return topic
    return None


def read_log_file(path: Path, found: LogRatings) -> list:
    """(topic, text, log_time) of one MCAP file; a damaged file gives what precedes the damage."""
    try:
        return list(recording.read_messages(path))
    except (McapError, EOFError, ValueError, OSError, RuntimeError, KeyError, AssertionError) as error:
        try:
            salvaged, damage = recording.salvage_messages(path)
        except OSError as second:
            found.problem('unreadable file', f'{path}: {second}')
            return []
        found.problem('truncated or damaged file', f'{path}: {damage or error}; {len(salvaged)} messages before '
                      'the damage were read')
        return salvaged


def log_files(paths) -> list:
    """MCAP files named by ``paths`` (bag folders or files), in order."""
    files = []
    for path in map(Path, paths):
        if path.is_dir():
            files.append((path, recording.bag_files(path)))
        else:
            files.append((path, [path]))
    return files


def read_logs(paths, predictor) -> LogRatings:
    """Join feedback with scene requests in every log; see the module docstring."""
    found = LogRatings()
    for log, files in log_files(paths):
        if not files:
            found.problem('no MCAP files', f'{log}: missing or holds no .mcap files')
            continue
        items = []
        for path in files:
            if not path.exists():
                found.problem('no MCAP files', f'{path}: no such file')
                continue
            found.files.append(str(path))
            items += read_log_file(path, found)
        items.sort(key=lambda item: item[2])  # log time: rotated files and recovered feedback interleave
        scenes = {}
        for channel, text, log_time in items:
            found.messages += 1
            topic = _topic(channel)
            if topic is None:
                found.problem('foreign topic', channel)
            elif topic in OTHER_STARS_TOPICS:
                found.not_needed[topic] += 1
            elif topic == 'stars/scene':
                try:
                    request = messages.parse_scene_request(text, 1 << 30)
                except messages.BadMessage as error:
                    found.problem('unusable scene message', f'{log}: {error}')
                    continue
                scenes[request.scene_id] = request
            elif topic == 'stars/feedback':
                join_feedback(text, scenes, predictor, found, log)
            elif topic == 'stars/user_model':
                try:
                    payload = messages.load_json(text, 1 << 30)
                    messages.check('user_model', payload)
                except messages.BadMessage as error:
                    found.problem('unusable user_model message', f'{log}: {error}')
                    continue
                found.regularisation[payload['user_id']] = float(payload['regularisation'])
    return found


def read_state(folder, predictor) -> LogRatings:
    """Each person's own ratings in the state store of ``folder`` (oldest first), and the
    λ of their stored model; peers' ratings are in the peers' logs and stores."""
    found = LogRatings(read='state store')
    with state.open_reader(folder) as store:
        found.files.append(str(store.path))
        if store.fingerprint not in (None, predictor.fingerprint):
            found.problem('people of another checkpoint', f'{store.path} holds people solved against '
                          f'{store.fingerprint[:12]}: their ratings are used, their models are not')
        for person in store.people():
            for rating in person.ratings:
                found.messages += 1
                if rating.action not in predictor.actions:
                    found.problem('unknown action', f"{store.path}: '{rating.action}' ({person.user_id})")
                    continue
                if not _on_scale(rating.score, predictor, found, f'{store.path} ({person.user_id})'):
                    continue
                found.ratings.setdefault(person.user_id, []).append(rating)
            found.dropped[person.user_id] = person.dropped
            if person.model is not None:
                found.regularisation[person.user_id] = person.model.regularisation
    return found


def _on_scale(score: float, predictor, found: LogRatings, where: str) -> bool:
    """False, and an ``out_of_scale`` problem naming the scale, for a score off the
    checkpoint's rating scale: it is not refit on."""
    try:
        check_score(score, predictor.recommender.rating_scale)
    except OutOfScaleError as error:
        found.problem('out_of_scale', f'{where}: {error}')
        return False
    return True


def join_feedback(text: str, scenes: dict, predictor, found: LogRatings, log) -> None:
    try:
        feedback = messages.parse_feedback(text, 1 << 30)
    except messages.BadMessage as error:
        found.problem('unusable feedback message', f'{log}: {error}')
        return
    if feedback.action is not None and feedback.action not in predictor.actions:
        found.problem('unknown action', f"{log}: '{feedback.action}' (scene {feedback.scene_id})")
        return
    if not _on_scale(feedback.score, predictor, found, f'{log} ({feedback.user_id}, scene {feedback.scene_id})'):
        return
    request = scenes.get(feedback.scene_id)
    if request is None:
        found.problem('feedback for a scene never recorded', f'{log}: scene {feedback.scene_id}')
        return
    rating = rating_from_feedback(feedback, request, predictor)
    if isinstance(rating, str):
        found.problem('feedback that does not match its scene', f'{log}: {rating}')
        return
    found.ratings.setdefault(feedback.user_id, []).append(rating)


def set_user_rows(recommender: StarsTrainer, solved: dict) -> None:
    model = recommender.model
    with torch.no_grad():
        for user, user_model in solved.items():
            row = recommender.user_vocabulary.row(user)
            model.user_embedding.weight[row] = torch.as_tensor(user_model.p, dtype=torch.float32)
            model.user_bias.weight[row, 0] = float(user_model.b)


def _store(parent_kind: str, scenes: list):
    if parent_kind == 'graph':
        return GraphStore([featurise(scene) for scene in scenes])
    return TabularStore(np.asarray(scenes, dtype=np.float32), [])


def feedback_data(recommender: StarsTrainer, ratings: dict, original: RatingData | None) -> RatingData:
    """The feedback ratings as RatingData (scenes keyed by their training key when they
    have one, else by content), appended to ``original`` when given."""
    keys, scenes, rows = [], [], []
    index = {}
    for user, user_ratings in ratings.items():
        for rating in user_ratings:
            key = rating.scene_id if rating.scene_id in recommender.scene_vocabulary else f'feedback:{scene_digest(rating.scene)}'
            if key not in index:
                index[key] = len(keys)
                keys.append(key)
                scenes.append(rating.scene)
            rows.append((user, index[key], recommender.action_names.index(rating.action), rating.score))
    store = _store(recommender.model.encoder.input_kind, scenes)
    users = np.array([r[0] for r in rows])
    scene_rows = np.array([r[1] for r in rows], dtype=np.int64)
    actions = np.array([r[2] for r in rows], dtype=np.int64)
    scores = np.array([r[3] for r in rows], dtype=np.float64)
    if original is None:
        return RatingData(users, scene_rows, actions, scores, keys, store, recommender.action_names, 'feedback', 'logs')
    if tuple(original.action_names) != tuple(recommender.action_names):
        raise StarsError(f'--data-root actions {list(original.action_names)} differ from the checkpoint\'s '
                         f'{list(recommender.action_names)}')
    offset = len(original.scene_keys)
    return RatingData(np.concatenate([original.users, users]), np.concatenate([original.scenes, scene_rows + offset]),
                      np.concatenate([original.actions, actions]), np.concatenate([original.scores, scores]),
                      list(original.scene_keys) + keys, type(store).concatenate([original.store, store]),
                      recommender.action_names, original.fingerprint, original.source)


def fine_tune(recommender: StarsTrainer, data: RatingData, epochs: int) -> list:
    """``epochs`` joint epochs over every row of ``data``, from the current weights, with the
    checkpoint's optimiser settings and rating normalisation."""
    return recommender.fine_tune(data, epochs)


def print_report(found: LogRatings, solved: dict, out=None) -> None:
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
    parser.add_argument('--verbose', action='store_true')
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    setup_logging(args.verbose)
    started = time.perf_counter()
    try:
        if args.regularisation is not None and not args.regularisation > 0:
            raise StarsError('--regularisation must be positive')
        predictor = Predictor.load(args.checkpoint)
        foldin = FoldIn(predictor)
        original = load_dataset(args.data_root) if args.data_root and args.mode == 'full' else None
    except (StarsError, OSError) as error:
        print(f'error: {error}', file=sys.stderr)
        return 2
    if args.data_root and args.mode == 'user':
        print('note: --data-root is used by --mode full only; user mode keeps every other parameter fixed')
    try:
        found = read_state(args.state, predictor) if args.state else read_logs(args.logs, predictor)
    except (FileNotFoundError, StoreError) as error:
        print(f'error: {error}', file=sys.stderr)
        return 2
    solved = {}
    for user, ratings in found.ratings.items():
        regularisation = args.regularisation or found.regularisation.get(user, DEFAULT_REGULARISATION)
        try:
            solved[user] = foldin.fit(ratings, user, regularisation)
        except StarsError as error:
            found.problem('scene the model cannot encode', f'{user}: {error}')
    for user in list(found.ratings):
        if user not in solved:
            del found.ratings[user]
    print_report(found, solved)
    if not solved:
        print('error: no usable feedback in the logs; no checkpoint written', file=sys.stderr)
        return 1
    recommender = predictor.recommender.extended(users=list(solved))
    set_user_rows(recommender, solved)
    losses = []
    if args.mode == 'full':
        try:
            data = feedback_data(recommender, found.ratings, original)
        except StarsError as error:
            print(f'error: {error}', file=sys.stderr)
            return 2
        recommender = recommender.extended(scene_keys=data.scene_keys)
        losses = fine_tune(recommender, data, args.epochs)
        print(f'full fine-tune: {args.epochs} joint epochs on {len(data)} ratings, loss {[round(v, 4) for v in losses]}')
    parent = predictor.metadata
    provenance = {
        'refit': {'mode': args.mode, 'parent_fingerprint': predictor.fingerprint,
                  'parent_checkpoint': str(args.checkpoint), 'logs': [str(p) for p in args.logs or []],
                  'state': args.state, 'files': found.files,
                  'ratings_per_user': {u: found.dropped.get(u, 0) + len(r) for u, r in found.ratings.items()},
                  'regularisation': {u: m.regularisation for u, m in solved.items()},
                  'problems': dict(found.problems), 'epochs': args.epochs if args.mode == 'full' else 0,
                  'fine_tune_losses': losses, 'data_root': args.data_root if original is not None else None,
                  'command': shlex.join(['python', '-m', 'offline_training.refit',
                                         *(sys.argv[1:] if argv is None else argv)]),
                  'seconds': round(time.perf_counter() - started, 2)},
        'parent': parent.get('provenance', {}),
    }
    digest = save_checkpoint(recommender, args.out, data=parent.get('data', {}),
                             metrics={'parent': parent.get('metrics', {})}, provenance=provenance)
    print(f'wrote {args.out} ({args.mode} mode, {len(solved)} user(s), digest {digest[:12]}) in '
          f'{time.perf_counter() - started:.1f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
