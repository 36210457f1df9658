"""The figures the ranker reports on /diagnostics and stars/errors: the spans of fold-in work
(``BusySpans``), one period's processing times (``PeriodStats``), the problems by kind
(``Problems``) and one period's report (``period_report``). ROS-free; ``stars_ros.node.core``
keeps one of each.
"""
from __future__ import annotations

import collections
import threading
import time
from typing import Callable

import numpy as np

# kinds of problem that are warnings, not errors
WARNINGS = ('unknown_user', 'unknown_scene', 'user_models', 'fleet', 'no_question', 'qos')


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
        if round(fold_in_delay_ms, 3) > 0:  # under a microsecond is not a wait (and would print as 0)
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

    def __init__(self, clock: Callable[[], float] = time.monotonic):
        self._clock = clock  # seconds, for the throttle
        self._lock = threading.Lock()
        self._counts = collections.Counter()
        self._period = {}  # kind -> (count, latest detail) since the last take_period
        self._last_log = {}

    def add(self, kind: str, detail: str, throttle: float) -> int | None:
        """Count one problem; its kind's total when it is to be logged, else None."""
        now = self._clock()
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

    def forget(self, named: Callable[[bytes], bool]) -> int:
        """Let go of the latest details that ``named`` finds a person in (a forget); how many."""
        with self._lock:
            gone = [kind for kind, (_, detail) in self._period.items() if named(detail.encode('utf-8'))]
            for kind in gone:
                self._period[kind] = (self._period[kind][0], '(withheld: it named a person since forgotten)')
        return len(gone)

    def take_period(self) -> tuple[dict, dict]:
        """(kind -> (count, latest detail) since the last call, totals since start); a new
        period starts."""
        with self._lock:
            period, self._period = self._period, {}
            return period, dict(self._counts)


def period_report(period: dict, counts: dict, failure: str | None, values: dict) -> tuple[str, str, dict, list]:
    """(level: 'ok', 'warn' or 'error'; summary; key-values; [(kind, level, count, latest
    detail)] of each kind of problem) of one /diagnostics period: ``period`` and ``counts``
    are ``Problems.take_period``'s, ``failure`` what stops the recording (None: nothing),
    ``values`` the node's own key-values, to which the error totals are added."""
    level = 'error' if set(period) - set(WARNINGS) or failure else ('warn' if period else 'ok')
    summary = 'serving' if not period else 'serving; problems since last report: ' + ', '.join(
        f'{k} x{n}' for k, (n, _) in sorted(period.items()))
    values = {**values, **{f'errors.{k}': n for k, n in sorted(counts.items()) if k != 'ranking'}}
    kinds = [(kind, 'warn' if kind in WARNINGS else 'error', count, detail)
             for kind, (count, detail) in sorted(period.items())]
    return level, summary, values, kinds
