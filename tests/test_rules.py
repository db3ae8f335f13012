"""The localization rules (core/rules/paper.py): localized after ten consecutive scans below the std
threshold with enough motion or turning, false positives and losses."""

import numpy as np
from lidarloc.core.config import DEG, LocalizeConfig
from lidarloc.core.rules.paper import LocalizationRules


def feed(rules, stds, step=1.5, yaw_rate=0.0):
    events = []
    for k, s in enumerate(stds):
        out = rules.update(k, np.array([s, s, s]), step, yaw_rate * k)
        if out.event:
            events.append((k, out.event))
    return events


def test_rule_needs_ten_scans_and_motion():
    rules = LocalizationRules(LocalizeConfig())
    assert feed(rules, [100] * 5 + [3] * 20) == [(14, "localized")]
    # stopped car: a long streak that never moves or turns is neither localized nor false
    rules = LocalizationRules(LocalizeConfig())
    assert feed(rules, [3] * 30, step=0.0) == []
    # turning in place by > 30° also satisfies the rule
    rules = LocalizationRules(LocalizeConfig())
    assert feed(rules, [3] * 30, step=0.0, yaw_rate=4 * DEG) == [(9, "localized")]


def test_false_positive_and_loss():
    rules = LocalizationRules(LocalizeConfig())
    ev = feed(rules, [100] * 3 + [3] * 5 + [30] * 2)
    assert ev == [(8, "false_positive")]
    rules = LocalizationRules(LocalizeConfig())
    ev = feed(rules, [3] * 12 + [20] * 3 + [60])
    assert ev == [(9, "localized"), (15, "loss")]
    assert not rules.localized
