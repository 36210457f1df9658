"""Rank a batch of queued scene requests with one model snapshot, and keep the figures the
ranker reports (``BusySpans``, ``PeriodStats``, ``Problems``); ``stars_ros.node.core`` uses them.

ROS-free. When scenes arrive faster than they are scored, the node scores everything
queued (up to ``max_batch``) in one call, and requests of the same user are encoded in one
forward pass, which is what lets a single core keep up. Results are those of ``Predictor.rank`` and
``Predictor.rank_scenes`` on the same input (same scores, ties kept in input order). A bad
request only fails itself: a group that raises is scored again one request at a time.
"""
from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass

import numpy as np

from stars_ros.errors import StarsError
from stars_ros.messages import SceneRequest
from stars_ros.model.explain import explain, removal_effects
from stars_ros.model.model import UNKNOWN
from stars_ros.model.predictor import rank_order

# kinds of problem that are warnings, not errors
WARNINGS = ('unknown_user', 'unknown_scene', 'user_models', 'fleet', 'no_question')


@dataclass(frozen=True)
class Pending:
    """A validated request waiting to be scored.

    ``user_id`` is the one it is served for (the message's own, else the latest on
    /stars/user_id at arrival); ``received`` is when the middleware received it (system
    clock, ns, as ``time.time_ns()``), so a ranking's processing time includes any wait
    behind other callbacks; ``text`` and ``log_time`` (ROS time, ns) are the message as
    received, which the node records once the ranking is out.
    """

    request: SceneRequest
    user_id: str | None
    received: int
    text: str = ''
    log_time: int = 0


@dataclass(frozen=True)
class Scored:
    """The ranking of one request (best first, cut to ``top_k``), for candidate scenes the
    action that ranked them, h_i of the request's scenes [len(graphs), dim] (float32:
    feedback on them is folded in without encoding them again), and the probability that the
    first entry is truly the best (None without fold-in)."""

    ranked: list
    action: str | None
    h: np.ndarray
    p_first_is_best: float | None = None


def _ranking_action(predictor, request: SceneRequest) -> str | None:
    """Check the request's action names against the model; the action that ranks candidate
    scenes (None for action ranking)."""
    if request.ranks_scenes:
        return predictor.ranking_action(request.action)
    predictor.action_columns(request.actions or ())
    return None


def _whys(predictor, user_id, request, entry_h, scene_rows, columns, entities: int) -> list:
    """``explain.Why`` of each entry of ``request`` (its scenes' removal variants in one pass)."""
    scene_ids = None if request.ranks_scenes else [request.scene_id]
    effects = removal_effects(predictor, user_id, request.graphs, scene_ids)
    if request.ranks_scenes:
        per_entry = [(found, effect[:, columns[0]]) for found, effect in effects]
    else:
        per_entry = [(effects[0][0], effects[0][1][:, column]) for column in columns]
    return explain(predictor, user_id, entry_h, scene_rows, np.asarray(columns), per_entry, entities)


def _score_group(predictor, user_id, members, top_k, uncertainty=None, explanations=None) -> list:
    """Scores of ``members`` [(request, action)] of one user and one mode in one pass; with
    ``uncertainty`` (personalisation.uncertainty.Uncertainty) each entry's score_sd and the
    ranking's p_first_is_best too; with ``explanations`` (explain every request?, entities
    per why) each entry's why where it or the request asks."""
    ranks_scenes = members[0][0].ranks_scenes
    graphs = [graph for request, _ in members for graph in request.graphs]
    scene_ids = None if ranks_scenes else [request.scene_id for request, _ in members]
    h = predictor.encode(graphs, validate=False)  # parse_scene_request validated them
    scores = predictor.scores_from_h(user_id, h, scene_ids)
    if not np.isfinite(scores).all():
        raise StarsError('the model produced a non-finite score')
    results, row = [], 0
    for request, action in members:
        if ranks_scenes:
            names = request.labels
            columns = predictor.action_columns([action]) * len(names)
            entry_h, scene_rows = h[row:row + len(names)], np.full(len(names), UNKNOWN)
            entry_scores = scores[row:row + len(names), columns[0]]
        else:
            names = request.actions or predictor.actions
            columns = predictor.action_columns(names)
            entry_h = np.repeat(h[row:row + 1], len(names), axis=0)
            scene_rows = predictor.recommender.scene_vocabulary.rows([request.scene_id] * len(names))
            entry_scores = scores[row, columns]
        spread = None if uncertainty is None else uncertainty.spread(predictor, user_id, entry_h, scene_rows, columns)
        explained = explanations is not None and (explanations[0] or request.explain)
        whys = _whys(predictor, user_id, request, entry_h, scene_rows, columns, explanations[1]) if explained else None
        ranked = rank_order(names, entry_scores, None if spread is None else spread.sd, whys)
        p_first = None if spread is None else spread.p_first_is_best(list(names).index(ranked[0].name))
        results.append(Scored(ranked[:top_k] if top_k else ranked, action, h[row:row + len(request.graphs)], p_first))
        row += len(request.graphs)
    return results


def rank_batch(predictor, batch, top_k: int = 0, uncertainty=None, explanations=None) -> list:
    """One ``Scored`` or one exception per ``Pending`` of ``batch``, in order (with
    ``uncertainty``: with each entry's score_sd and the ranking's p_first_is_best; with
    ``explanations`` = (explain every request?, entities per why): each entry's why where
    that or its request's ``explain`` asks)."""
    results = [None] * len(batch)
    groups = {}
    for k, item in enumerate(batch):
        try:
            action = _ranking_action(predictor, item.request)
        except StarsError as error:
            results[k] = error
            continue
        groups.setdefault((item.user_id, item.request.ranks_scenes), []).append((k, item.request, action))
    for (user_id, _), members in groups.items():
        try:
            scored = _score_group(predictor, user_id, [(r, a) for _, r, a in members], top_k, uncertainty,
                                  explanations)
        except StarsError:
            scored = []
            for _, request, action in members:  # find which request spoils the group
                try:
                    scored.append(_score_group(predictor, user_id, [(request, action)], top_k, uncertainty,
                                                  explanations)[0])
                except StarsError as error:
                    scored.append(error)
        for (k, _, _), result in zip(members, scored):
            results[k] = result
    return results


class BusySpans:
    """The latest spans (start, end; ns of one clock) in which the executor did one kind of
    work, fold-in say: a request's wait runs from its reception to the batch that serves
    it, and only the part of the spans inside that window held it up."""

    def __init__(self, keep: int = 64):
        self._spans = collections.deque(maxlen=keep)

    def add(self, start: int, end: int):
        """Spans come in time order and do not overlap (one executor thread does the work)."""
        self._spans.append((start, end))

    def overlap(self, since: int, until: int) -> int:
        """ns of the kept spans inside [since, until]."""
        total = 0
        for start, end in reversed(self._spans):
            if end <= since:
                break
            total += max(0, min(end, until) - max(start, since))
        return total


class PeriodStats:
    """What /diagnostics reports of one period: the rankings' processing time (reception to
    publication; percentiles over the latest ``keep``, so a long period at a high rate
    stays bounded), the rankings that waited behind fold-in work and how long, and the
    fold-in updates: turns of fold-in work, each a solve or a step of building the rows of a
    person restored with many ratings (all ms)."""

    def __init__(self, keep: int = 10000):
        self.rankings, self.processing_max, self.latest = 0, 0.0, collections.deque(maxlen=keep)
        self.fold_in_updates, self.fold_in_max = 0, 0.0
        self.delayed, self.delay_max, self.delayed_processing_max = 0, 0.0, 0.0

    def ranking(self, processing_ms: float, fold_in_delay_ms: float):
        self.rankings += 1
        self.processing_max = max(self.processing_max, processing_ms)
        self.latest.append(processing_ms)
        if fold_in_delay_ms > 0:
            self.delayed += 1
            self.delay_max = max(self.delay_max, fold_in_delay_ms)
            self.delayed_processing_max = max(self.delayed_processing_max, processing_ms)

    def fold_in_update(self, ms: float):
        self.fold_in_updates += 1
        self.fold_in_max = max(self.fold_in_max, ms)

    def values(self) -> dict:
        """Diagnostic key-values; percentiles and maxima only where the period had any."""
        values = {'period.rankings': self.rankings, 'period.fold_in_updates': self.fold_in_updates,
                  'period.rankings_delayed_by_fold_in': self.delayed}
        if self.rankings:
            p50, p99 = np.percentile(self.latest, [50, 99])
            values.update({'period.processing_ms.p50': round(float(p50), 3),
                           'period.processing_ms.p99': round(float(p99), 3),
                           'period.processing_ms.max': round(self.processing_max, 3)})
        if self.fold_in_updates:
            values['period.fold_in_update_ms.max'] = round(self.fold_in_max, 3)
        if self.delayed:
            values['period.fold_in_delay_ms.max'] = round(self.delay_max, 3)
            values['period.delayed_processing_ms.max'] = round(self.delayed_processing_max, 3)
        return values


class Problems:
    """The problems a node reports, by kind: totals since start, and the count and latest
    detail of each kind since the last /diagnostics. Decides which reports are logged: at
    most one line per kind every ``throttle`` seconds. Thread-safe (the node's own threads
    report too)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._counts = collections.Counter()
        self._period = {}  # kind -> (count, latest detail) since the last take_period
        self._last_log = {}

    def add(self, kind: str, detail: str, throttle: float) -> int | None:
        """Count one problem; its kind's total when it is to be logged, else None."""
        now = time.monotonic()
        with self._lock:
            self._counts[kind] += 1
            self._period[kind] = (self._period.get(kind, (0, ''))[0] + 1, detail)
            if now - self._last_log.get(kind, -1e9) < throttle:
                return None
            self._last_log[kind] = now
            return self._counts[kind]

    def ranked(self) -> None:
        with self._lock:
            self._counts['ranking'] += 1

    def take_period(self) -> tuple[dict, dict]:
        """(kind -> (count, latest detail) since the last call, totals since start); a new
        period starts."""
        with self._lock:
            period, self._period = self._period, {}
            return period, dict(self._counts)
