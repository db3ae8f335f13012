"""Metrics A–E (core/runs/metrics.py) on hand-made per-scan logs with known answers, and their
aggregate over runs."""

import numpy as np
from lidarloc.core.runs.metrics import ScanLog, aggregate, compute_metrics


def log(localized, error):
    return ScanLog(np.array(localized, bool), np.array(error, float))


def test_never_localized_fails_every_metric():
    m = compute_metrics(log([False] * 100, [50.0] * 100))
    assert all(m[k] is None for k in "ABCDE")


def test_clean_localization():
    # localized from scan 12 on; error ≤ 5 m from scan 15, ≤ 2.5 m from scan 20
    n = 100
    loc = [i >= 12 for i in range(n)]
    err = [40.0 if i < 15 else (4.0 if i < 20 else 1.0) for i in range(n)]
    m = compute_metrics(log(loc, err))
    assert m["B"] == 13 and m["A"] == 13
    assert m["C"] == 16 and m["D"] == 16 and m["E"] == 21
    assert m["rmse_pos_after_D_m"] == np.sqrt((5 * 16 + 80 * 1) / 85)


def test_false_positive_then_success():
    # localized at 10..14 on a wrong place (error 80 m), re-init, localized again at 30
    n = 120
    loc = [(10 <= i < 15) or i >= 30 for i in range(n)]
    err = [80.0 if i < 30 else 3.0 for i in range(n)]
    m = compute_metrics(log(loc, err))
    assert m["B"] == 11  # the rule was first met (falsely) at scan 10
    assert m["A"] == 10 + 15 + 2  # scans 0–9 and 15–29 not localized, 2 localizations
    assert m["C"] == 31 and m["D"] == 31 and m["E"] is None


def test_loss_then_relocalization():
    n = 200
    loc = [(10 <= i < 60) or i >= 80 for i in range(n)]
    err = [2.0 if (10 <= i < 55) or i >= 85 else 60.0 for i in range(n)]
    m = compute_metrics(log(loc, err))
    assert m["B"] == 11 and m["A"] == 10 + 20 + 2
    assert m["C"] == 11  # [10, 20] within 5 m
    assert m["D"] == 86  # 10..54 is only 45 long; the next window starts at 85
    assert m["E"] == 86


def test_window_past_the_end_is_not_met():
    m = compute_metrics(log([True] * 40, [1.0] * 40))
    assert m["C"] == 1 and m["D"] is None


def test_aggregate_counts_failures():
    agg = aggregate([{"B": 10}, {"B": 20}, {"B": None}, {"B": 12}])
    assert agg["B"]["success"] == 0.75 and agg["B"]["max"] is None and agg["B"]["median"] == 12
