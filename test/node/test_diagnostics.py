"""The ranker's bookkeeping of waits behind fold-in work and of its per-period figures (ROS-free)."""
import pytest

from stars_ros.node.diagnostics import BusySpans, PeriodStats


def test_busy_spans_count_only_the_work_inside_a_requests_wait():
    spans = BusySpans()
    for start, end in [(0, 10), (20, 30), (40, 45)]:
        spans.add(start, end)
    assert spans.overlap(0, 100) == 25
    assert spans.overlap(25, 42) == 5 + 2  # the end of the second span, the start of the third
    assert spans.overlap(10, 20) == 0  # received after one solve, served before the next
    assert spans.overlap(50, 60) == 0
    assert spans.overlap(5, 5) == 0


def test_busy_spans_keep_only_the_latest():
    spans = BusySpans(keep=2)
    for start in (0, 10, 20):
        spans.add(start, start + 5)
    assert spans.overlap(0, 100) == 10


def test_period_stats_report_the_delayed_rankings_apart():
    stats = PeriodStats()
    assert stats.values() == {'period.rankings': 0, 'period.fold_in_updates': 0,
                              'period.rankings_delayed_by_fold_in': 0}
    for processing in (1.0, 2.0, 3.0, 4.0):
        stats.ranking(processing, 0.0)
    stats.ranking(6.0, 0.5)
    stats.ranking(2.5, 0.75)
    stats.ranking(2.0, 0.0004)  # under a microsecond: not counted as a wait
    stats.fold_in_update(0.4)
    stats.fold_in_update(0.9)
    values = stats.values()
    assert values['period.rankings'] == 7 and values['period.fold_in_updates'] == 2
    assert values['period.rankings_delayed_by_fold_in'] == 2
    assert values['period.processing_ms.p50'] == pytest.approx(2.5)
    assert values['period.processing_ms.max'] == 6.0
    assert values['period.processing_ms.p99'] == pytest.approx(6.0 - 0.06 * 2.0)  # between 4.0 and 6.0
    assert values['period.fold_in_update_ms.max'] == 0.9
    assert values['period.fold_in_delay_ms.max'] == 0.75
    assert values['period.delayed_processing_ms.max'] == 6.0


def test_period_stats_stay_bounded_in_a_long_period():
    stats = PeriodStats(keep=3)
    for processing in (50.0, 1.0, 2.0, 3.0):
        stats.ranking(processing, 0.0)
    values = stats.values()
    assert values['period.rankings'] == 4 and values['period.processing_ms.max'] == 50.0
    assert values['period.processing_ms.p50'] == 2.0  # over the latest three
