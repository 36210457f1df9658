"""Refit a served model from the feedback people gave it: read the ratings back from the
ranker's MCAP logs or its state store, and turn them into trained rows or a fine-tune.

Each /stars/feedback message is joined with the scene request it names: the latest
/stars/scene message with that scene_id logged before it, in the same log (what the node
remembered when the feedback came). The rating that gives is the node's
(``foldin.rating_from_feedback``), so both sides fold in the same data. The state store
gives each person's ratings as the node holds them now (the most recent
``fold_in_max_ratings``), with λ from each stored model.

People forgotten in a record folder (docs/privacy.md) are left out by their tombstones
(``forgotten``: the record folders' ``state.Forgotten``), so a refit from a bag copied
before the forget does not bring them back.

``StarsRecommender.refit`` solves and writes the users; ``offline_training.refit`` is the
command line around both.
"""
from __future__ import annotations

import collections
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.exceptions import McapError

from stars_ros import messages, recording, state
from stars_ros.data.ratings import RatingData
from stars_ros.data.scene_graph import featurise
from stars_ros.data.scene_store import GraphStore, TabularStore
from stars_ros.errors import OutOfScaleError, StarsError
from stars_ros.personalisation.foldin import check_feedback_score, rating_from_feedback
from stars_ros.state import scene_digest

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


def record_folders_of(paths) -> list:
    """The record folders the bags or files ``paths`` lie in (those holding a state store)."""
    folders = []
    for path in map(Path, paths):
        for folder in (path, path.parent, path.parent.parent):
            if (folder / state.DATABASE).exists() and folder not in folders:
                folders.append(folder)
                break
    return folders


def forgotten_in(folders) -> list:
    """The tombstones (``state.Forgotten``) of each record folder in ``folders``."""
    return [state.forgotten_in(folder) for folder in folders]


def _is_forgotten(user_id: str, forgotten) -> bool:
    return any(user_id in tombstones for tombstones in forgotten)


def read_logs(paths, predictor, forgotten=()) -> LogRatings:
    """Join feedback with scene requests in every log, leaving out the people
    ``forgotten`` (``forgotten_in``); see the module docstring."""
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
        for channel, text, _ in items:
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
                join_feedback(text, scenes, predictor, found, log, forgotten)
            elif topic == 'stars/user_model':
                try:
                    payload = messages.load_json(text, 1 << 30)
                    messages.check('user_model', payload)
                except messages.BadMessage as error:
                    found.problem('unusable user_model message', f'{log}: {error}')
                    continue
                if not _is_forgotten(payload['user_id'], forgotten):
                    found.regularisation[payload['user_id']] = float(payload['regularisation'])
    return found


def read_state(folder, predictor, forgotten=()) -> LogRatings:
    """Each person's own ratings in the state store of ``folder`` (oldest first), and the
    λ of their stored model, but for the people ``forgotten``; peers' ratings are in the
    peers' logs and stores."""
    found = LogRatings(read='state store')
    with state.open_reader(folder) as store:
        found.files.append(str(store.path))
        if store.fingerprint not in (None, predictor.fingerprint):
            found.problem('people of another checkpoint', f'{store.path} holds people solved against '
                          f'{store.fingerprint[:12]}: their ratings are used, their models are not')
        for person in store.people():
            if _is_forgotten(person.user_id, forgotten):
                found.problem('forgotten person', f'{store.path}: a person forgotten there (their id is not kept)')
                continue
            for rating in person.ratings:
                found.messages += 1
                if rating.action not in predictor.actions:
                    found.problem('unknown action', f"{store.path}: '{rating.action}' ({person.user_id})")
                    continue
                if not _on_scale(rating, predictor, found, f'{store.path} ({person.user_id})'):
                    continue
                found.ratings.setdefault(person.user_id, []).append(rating)
            found.dropped[person.user_id] = person.dropped
            if person.model is not None:
                found.regularisation[person.user_id] = person.model.regularisation
    return found


def _on_scale(feedback, predictor, found: LogRatings, where: str) -> bool:
    """False, and an ``out_of_scale`` problem naming the scale, for feedback whose score the
    checkpoint's rating scale does not take (``foldin.check_feedback_score``): it is not refit on."""
    try:
        check_feedback_score(feedback, predictor.rating_scale)
    except OutOfScaleError as error:
        found.problem('out_of_scale', f'{where}: {error}')
        return False
    return True


def join_feedback(text: str, scenes: dict, predictor, found: LogRatings, log, forgotten=()) -> None:
    try:
        feedback = messages.parse_feedback(text, 1 << 30)
    except messages.BadMessage as error:
        found.problem('unusable feedback message', f'{log}: {error}')
        return
    if _is_forgotten(feedback.user_id, forgotten):
        found.problem('forgotten person', f'{log}: feedback of a person forgotten in its record folder (their id is '
                      'not kept)')
        return
    if feedback.action is not None and feedback.action not in predictor.actions:
        found.problem('unknown action', f"{log}: '{feedback.action}' (scene {feedback.scene_id})")
        return
    if not _on_scale(feedback, predictor, found, f'{log} ({feedback.user_id}, scene {feedback.scene_id})'):
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


def _store(parent_kind: str, scenes: list):
    if parent_kind == 'graph':
        return GraphStore([featurise(scene) for scene in scenes])
    return TabularStore(np.asarray(scenes, dtype=np.float32), [])


def feedback_data(recommender, ratings: dict, original: RatingData | None) -> RatingData:
    """The feedback ratings {user: [Rating]} as RatingData for ``recommender`` (a
    ``FittedModel``): scenes keyed by their training key when they have one, else by
    content, appended to ``original`` when given."""
    keys, scenes, rows = [], [], []
    index = {}
    for user, user_ratings in ratings.items():
        for rating in user_ratings:
            key = (rating.scene_id if rating.scene_id in recommender.scene_vocabulary
                   else f'feedback:{scene_digest(rating.scene)}')
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
