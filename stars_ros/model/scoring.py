"""Rating data scored by the served form: the one way a reported prediction is made.

Every figure of a fitted model (``StarsRecommender.test``, ``evaluate``, k-shot, the learning
curve) comes from what ``StarsRecommender.load`` of its checkpoint would serve: a
``model.predictor.Predictor`` over its ``model.serving.ServedModel`` (``Predictor.from_model``
builds it from the content the checkpoint would hold), each rating's person scored as the
node scores them (trained row, prior's mean, or the plain encoder for a stranger). Torch's
forward is training's loss only.

Each example (one person's ratings of one scene) is scored as one request for its actions,
its scene encoded on its own: a batch of scenes differs from one scene at a time by float
rounding, and a figure must be the number ``predict`` gives for that row, to the last bit.
"""
from __future__ import annotations

import numpy as np

from stars_ros.model.predictor import RankQuery


def served_predictions(predictor, data, rows) -> np.ndarray:
    """The score ``predictor`` serves each rating of ``rows`` of ``data`` (RatingData): its
    person, its scene (by its content, q_i and b_i by its item key) and its action, on the
    rating scale and clipped to it, as ``StarsRecommender.predict`` gives it."""
    rows = np.asarray(rows, dtype=np.int64)
    items = data.item_keys(predictor.served.config.model.item_key)
    names = data.action_names
    predictions = np.empty(len(rows))
    order = np.argsort(data.examples[rows], kind='stable')
    starts = np.flatnonzero(np.r_[True, np.diff(data.examples[rows][order]) != 0])
    for mine in np.split(order, starts[1:]):  # one example's ratings
        row = rows[mine[0]]
        scene = int(data.scenes[row])
        actions = tuple(names[a] for a in data.actions[rows[mine]])
        query = RankQuery((data.store.scene(scene),), items[scene], actions)
        ranked = predictor.rank_many(data.users[row], [query])[0].ranked
        scored = {entry.name: entry.score for entry in ranked}
        predictions[mine] = [scored[action] for action in actions]
    return predictions


def served_encodings(predictor, data, scenes=None) -> np.ndarray:
    """h_i [len(scenes), dim] (float64) of scene rows ``scenes`` of ``data`` (all by
    default), each encoded on its own by the served encoder, as a request of it is."""
    scenes = range(len(data.scene_keys)) if scenes is None else scenes
    encoded = [predictor.encode([data.store.scene(int(s))], validate=False) for s in scenes]
    if not encoded:
        return np.zeros((0, predictor.inference.dim))
    return np.concatenate(encoded).astype(np.float64)


def served_plain_scores(predictor, data, scenes=None) -> np.ndarray:
    """The plain encoder's unclipped scores [len(scenes), actions] of scene rows ``scenes`` of
    ``data`` (all by default), each scene on its own, as a stranger's request is scored
    (``Predictor.stranger_scores``; the model must keep one, ``model.strangers`` 'base_encoder')."""
    scenes = range(len(data.scene_keys)) if scenes is None else scenes
    inputs = (predictor.encoder_input([data.store.scene(int(s))], validate=False) for s in scenes)
    return np.concatenate([predictor.stranger_scores(one, 1) for one in inputs])
