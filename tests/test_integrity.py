"""Never green while wrong: the rule needs S2M's word, a whole-map second opinion once localized,
loss detection from the scan's fit (core/rules/integrity.py), and how a run reports them."""

from __future__ import annotations

import contextlib
import math

import numpy as np
import pytest
from helpers import short_town
from lidarloc.core.config import Config, load_config
from lidarloc.core.geometry import pose_matrix
from lidarloc.core.localizer import Localizer
from lidarloc.core.rules.integrity import (
    CLEARED_DOUBT_HOLDS_SCANS,
    DISAGREEMENTS_FOR_CHECK,
    FIRST_FIX_WORD_AGE_SCANS,
    FIT_MIN_SAMPLES,
    WITHDRAW_AFTER_POOR_FIT_SCANS,
    Integrity,
    fits_clearly_better,
    judge,
)
from lidarloc.core.rules.paper import LocalizationRules
from lidarloc.core.rules.truth import truth_alarm


# ------------------------------------------------------------------------------ the rule's word
def _feed(rules, n, confirmed=None, start=0):
    """Scans start…start+n−1 with a small std, 2 m driven per scan."""
    out = []
    for k in range(start, start + n):
        out.append(rules.update(k, np.array([1.0, 1.0, 0.1]), 2.0, 0.0, confirmed))
    return out


def test_the_rule_waits_for_s2m_to_agree_within_its_window():
    cfg = Config().localize
    rules = LocalizationRules(cfg)
    agreed_at = {"k": None}

    def confirmed(k0):
        return agreed_at["k"] is not None and agreed_at["k"] >= k0

    outcomes = _feed(rules, 15, confirmed)
    # the paper's conditions hold from the 10th scan on, but nothing agreed: no fire, and it says why
    assert not any(o.localized for o in outcomes) and rules.awaiting_confirmation
    assert not any(o.event for o in outcomes)
    agreed_at["k"] = 15
    o = _feed(rules, 1, confirmed, start=15)[0]
    assert o.localized and o.event == "localized" and rules.localized_since == 15
    assert not rules.awaiting_confirmation


def test_an_agreement_before_the_streak_does_not_count():
    rules = LocalizationRules(Config().localize)
    # a match agreed at scan 2, then the std rose (a false positive) and a new streak began
    rules.update(0, np.array([1.0, 1.0, 0.1]), 2.0, 0.0, lambda k0: 2 >= k0)
    rules.update(1, np.array([30.0, 30.0, 1.0]), 2.0, 0.0, lambda k0: 2 >= k0)
    outcomes = _feed(rules, 12, lambda k0: 2 >= k0, start=3)
    assert not any(o.localized for o in outcomes)


def test_without_confirmation_the_paper_rule_fires_on_the_filter_alone():
    rules = LocalizationRules(Config().localize)
    outcomes = _feed(rules, 10, None)
    assert outcomes[-1].event == "localized" and outcomes[-1].localized


def test_the_paper_preset_keeps_the_papers_rule():
    cfg = load_config(preset="paper")
    assert not cfg.localize.require_s2m_confirmation
    assert cfg.s2m.global_check_interval == 0 and cfg.localize.lost_after_scans == 0
    assert Config().localize.require_s2m_confirmation


# ------------------------------------------------------------------------------ verdicts
def _pose(x, y, yaw_deg=0.0):
    return pose_matrix(x, y, 0.0, math.radians(yaw_deg), 0.0, 0.0)


@pytest.mark.parametrize(
    "mode, accepted, unbeaten, match, score, start, kind",
    [
        ("global", True, False, (2.0, 1.0, 5.0), 300, 100, "agrees"),
        ("global", False, True, (0.0, 0.0, 0.0), 300, 300, "agrees"),  # nothing in the map beat the start
        ("global", True, False, (80.0, 0.0, 0.0), 900, 100, "disagrees"),  # written as the paper does
        ("local", True, False, (0.0, 0.0, 40.0), 300, 100, "disagrees"),  # turned too far
        ("check", True, False, (80.0, 0.0, 0.0), 200, 100, "relocalize"),  # 2× the estimate's score
        ("check", True, False, (80.0, 0.0, 0.0), 110, 100, "look_alike"),  # far, but not clearly better
        ("check", False, False, (80.0, 0.0, 0.0), 900, 100, "no_opinion"),  # refused by GICP
    ],
)
def test_a_match_is_judged_against_the_estimate(mode, accepted, unbeaten, match, score, start, kind):
    v = judge(mode, accepted, unbeaten, _pose(*match), _pose(0.0, 0.0), score, start, Config())
    assert v.kind == kind
    if kind != "no_opinion":
        assert v.distance_m == pytest.approx(math.hypot(match[0], match[1]))


def test_local_disagreements_in_a_row_ask_for_the_second_opinion():
    cfg = Config()
    integ = Integrity(cfg)
    integ.on_localized(0)
    far = judge("local", True, False, _pose(20.0, 0.0), _pose(0.0, 0.0), 200, 100, cfg)
    near = judge("local", True, False, _pose(0.5, 0.0), _pose(0.0, 0.0), 200, 100, cfg)
    for i in range(DISAGREEMENTS_FOR_CHECK - 1):
        integ.note_verdict(20 + i, far)
    assert integ.check_due(22, localized=True) is None
    integ.note_verdict(22, near)  # an agreement resets the count
    for i in range(DISAGREEMENTS_FOR_CHECK):
        integ.note_verdict(23 + i, far)
    assert "did not agree" in integ.check_due(26, localized=True)
    integ.check_started(26)
    assert integ.check_due(27, localized=True) is None
    # and periodically
    assert (
        integ.check_due(26 + cfg.s2m.global_check_interval, localized=True)
        == f"every {cfg.s2m.global_check_interval} scans"
    )
    assert integ.check_due(200, localized=False) is None  # before localization every match is global


def test_a_poor_fit_is_judged_against_the_recent_baseline_and_a_long_one_is_a_loss():
    cfg = Config()
    integ = Integrity(cfg)
    integ.on_localized(0)
    # a VLP-16's correct estimate: ~0.9 m mean residual is its normal
    for k in range(FIT_MIN_SAMPLES + 5):
        assert integ.note_fit(k, True, 0.8, 0.9) is None
    assert integ.poor_fit(0.8, 1.0) is None
    assert "mean residual" in integ.poor_fit(0.8, 2.5)
    assert "inlier share" in integ.poor_fit(0.2, 0.9)
    k0 = 100
    lost = [integ.note_fit(k0 + i, True, 0.8, 2.5) for i in range(cfg.localize.lost_after_scans)]
    assert all(v is None for v in lost[:-1]) and "poorly" in lost[-1]
    assert integ.check_reason is not None  # the poor fit asked for the second opinion
    # a whole-map match agreeing with the estimate says the poor fit is the world's change
    integ.note_fit(200, True, 0.8, 2.5)
    integ.note_verdict(201, judge("check", False, True, _pose(0, 0), _pose(0, 0), 5, 5, cfg))
    assert integ.poor_fit_scans == 0


def test_a_share_of_the_scan_no_longer_fitting_is_a_poor_fit():
    cfg = Config()
    integ = Integrity(cfg)
    integ.on_localized(0)
    for k in range(FIT_MIN_SAMPLES + 5):  # a VLP-16's correct estimate: 83 % of the points fit
        integ.note_fit(k, True, 0.83, 0.9)
    assert integ.poor_fit(0.76, 0.9) is None  # a truck hides some of the scan
    assert "inlier share 0.60 against 0.83" in integ.poor_fit(0.60, 1.5)  # moved 60 m: residual not yet 2×


def test_a_poor_fit_the_whole_map_check_does_not_clear_withdraws_localized():
    cfg = Config()
    integ = Integrity(cfg)
    integ.on_localized(0)
    for k in range(1, FIT_MIN_SAMPLES + 5):  # a VLP-16's correct estimate
        integ.note_fit(k, True, 0.83, 0.9)
    look_alike = judge("check", True, False, _pose(80.0, 0.0), _pose(0.0, 0.0), 110, 100, cfg)
    agrees = judge("check", False, True, _pose(0.0, 0.0), _pose(0.0, 0.0), 300, 300, cfg)
    # local matches that disagree ask for the check, but its look-alike withdraws nothing (a
    # VLP-16's local matches disagree with a correct estimate now and then)
    far = judge("local", True, False, _pose(20.0, 0.0), _pose(0.0, 0.0), 200, 100, cfg)
    for i in range(DISAGREEMENTS_FOR_CHECK):
        assert integ.note_verdict(20 + i, far) is None
    assert "did not agree" in integ.check_due(23, localized=True)
    integ.check_started(23)
    assert integ.doubt is None and integ.note_verdict(25, look_alike) is None
    # a poor fit: the check decides, and a look-alike withdraws "localized"
    assert integ.note_fit(40, True, 0.53, 1.6) is None
    assert "inlier share 0.53" in integ.check_due(40, localized=True)
    integ.check_started(40)
    why = integ.note_verdict(42, look_alike)
    assert why is not None and "inlier share 0.53" in why and "look-alike" in why
    # a periodic check carries no doubt: its look-alike changes nothing
    assert integ.check_due(90, localized=True) == f"every {cfg.s2m.global_check_interval} scans"
    integ.check_started(90)
    assert integ.doubt is None and integ.note_verdict(92, look_alike) is None
    # a poor fit the check clears (the world changed, the estimate is right): no withdrawal
    integ.note_fit(110, True, 0.53, 1.6)
    integ.check_started(110)
    assert integ.note_verdict(112, agrees) is None and integ.doubt is None and integ.poor_fit_scans == 0


def test_a_poor_fit_no_whole_map_match_decides_in_time_withdraws_localized():
    """S2M may not land in time (a long whole-map search, odometry behind the clock): a poor fit
    that lasts WITHDRAW_AFTER_POOR_FIT_SCANS scans with no whole-map agreement withdraws
    "localized" once, well before the loss; one the whole map agreed with lately does not."""
    cfg = Config()
    integ = Integrity(cfg)
    integ.on_localized(0)
    for k in range(1, FIT_MIN_SAMPLES + 5):
        integ.note_fit(k, True, 0.9, 0.2)
    assert 1 < WITHDRAW_AFTER_POOR_FIT_SCANS < cfg.localize.lost_after_scans
    said = []
    for k in range(20, 20 + cfg.localize.lost_after_scans - 1):
        integ.note_fit(k, True, 0.9, 1.5)
        said.append(integ.undecided_doubt(k))
    withdrawn = [i for i, why in enumerate(said) if why is not None]
    assert withdrawn == [WITHDRAW_AFTER_POOR_FIT_SCANS - 1]  # once, at the Nth scan in a row
    assert "poorly for 5 scans (mean residual 1.50 m against 0.20 m lately)" in said[withdrawn[0]]
    # a scan that fits ends the poor fit; the next one counts again from one
    integ.note_fit(60, True, 0.9, 0.2)
    assert integ.poor_fit_scans == 0
    # a whole-map check that agrees in spite of the poor fit: the world changed there
    integ.note_fit(61, True, 0.9, 1.5)
    integ.note_verdict(63, judge("check", False, True, _pose(0, 0), _pose(0, 0), 5, 5, cfg))
    assert integ.doubt_cleared_at == 63
    held = []
    for k in range(64, 64 + 2 * WITHDRAW_AFTER_POOR_FIT_SCANS):
        integ.note_fit(k, True, 0.9, 1.5)
        held.append(integ.undecided_doubt(k))
    assert held == [None] * len(held) and integ.poor_fit_scans == 2 * WITHDRAW_AFTER_POOR_FIT_SCANS
    # … for CLEARED_DOUBT_HOLDS_SCANS scans, then a new poor fit withdraws again
    k0 = 63 + CLEARED_DOUBT_HOLDS_SCANS
    integ.note_fit(k0, True, 0.9, 0.2)
    for k in range(k0 + 1, k0 + 1 + WITHDRAW_AFTER_POOR_FIT_SCANS):
        integ.note_fit(k, True, 0.9, 1.5)
    assert integ.undecided_doubt(k) is not None
    # the paper's rule (no S2M confirmation) has no such withdrawal
    paper = Integrity(load_config(preset="paper"))
    paper.on_localized(0)
    for k in range(1, 1 + FIT_MIN_SAMPLES + WITHDRAW_AFTER_POOR_FIT_SCANS):
        paper.note_fit(k, True, 0.9, 0.2 if k <= FIT_MIN_SAMPLES else 1.5)
    assert paper.poor_fit_scans == WITHDRAW_AFTER_POOR_FIT_SCANS and paper.undecided_doubt(k) is None


def test_s2ms_word_goes_stale_after_confirm_within_scans():
    """The rule fires only on an agreement at most ``localize.confirm_within`` scans old, and
    once localized an agreement that old withdraws "localized"; 0 = never stale; the paper's rule
    has no such withdrawal."""
    cfg = Config()
    within = cfg.localize.confirm_within
    assert within > 0
    integ = Integrity(cfg)
    integ.on_localized(0)
    integ.note_verdict(10, judge("local", True, False, _pose(0.5, 0.0), _pose(0.0, 0.0), 200, 100, cfg))
    assert integ.confirmed_at == 10
    assert integ.confirmed_since(5, 10 + within) and not integ.confirmed_since(5, 11 + within)
    assert integ.confirmed_since(5) and not integ.confirmed_since(11)  # no scan given: any age
    assert integ.stale_word(10 + within) is None
    why = integ.stale_word(11 + within)
    assert why == f"no S2M match has agreed with the estimate for {within + 1} scans (since scan 10)"
    # a disagreement is no word for the estimate
    integ.note_verdict(30, judge("local", True, False, _pose(20.0, 0.0), _pose(0.0, 0.0), 200, 100, cfg))
    assert integ.stale_word(11 + within) is not None
    cfg.localize.confirm_within = 0
    assert integ.stale_word(10_000) is None and integ.confirmed_since(5, 10_000)
    paper = Integrity(load_config(preset="paper"))
    paper.confirmed_at = 0
    assert paper.stale_word(10_000) is None


def test_a_first_fix_needs_a_word_on_a_recent_estimate():
    """In real time a match may agree before the odometry lets it land: its word is about the
    estimate it started from. It lets the rule fire for the first time only if that estimate is at
    most FIRST_FIX_WORD_AGE_SCANS old (the filter may have slid along a street since); a landed
    agreement is about the estimate of the scan it lands in. Either keeps the word fresh."""
    from dataclasses import replace

    cfg = Config()
    integ = Integrity(cfg)
    agrees = judge("local", True, False, _pose(0.5, 0.0), _pose(0.0, 0.0), 200, 100, cfg)
    assert agrees.kind == "agrees" and agrees.judged_at is None
    integ.note_verdict(73, replace(agrees, judged_at=43))  # started at 43, agreed at 73
    assert integ.confirmed_at == 73 and integ.confirmed_about == 43
    assert integ.confirmed_since(20, 73) and not integ.confirms_first_fix(20, 73)
    assert integ.stale_word(73 + cfg.localize.confirm_within) is None  # still a fresh word
    integ.note_verdict(80, replace(agrees, judged_at=80 - FIRST_FIX_WORD_AGE_SCANS))
    assert integ.confirms_first_fix(20, 80) and not integ.confirms_first_fix(20, 81)
    integ.note_verdict(100, agrees)  # landed: about scan 100's estimate
    assert integ.confirmed_about == 100 and integ.confirms_first_fix(20, 100)
    # a checkpoint without it: the landing's own scan
    restored = Integrity(cfg)
    restored.load({k: v for k, v in integ.state().items() if k != "confirmed_about"})
    assert restored.confirmed_about == restored.confirmed_at == 100


def test_far_poses_must_fit_clearly_better_in_3d():
    assert fits_clearly_better((0.95, 0.15), (0.88, 1.1))  # 80 m off: 1.1 m vs 0.15 m
    assert not fits_clearly_better((0.80, 1.0), (0.81, 0.9))  # a VLP-16 look-alike
    assert not fits_clearly_better((0.70, 0.2), (0.90, 0.9))  # fewer of the points fit there
    assert not fits_clearly_better((0.0, math.nan), (0.9, 0.9))


def test_the_truth_alarm_is_the_false_fire_test():
    assert truth_alarm(True, 102.4) == "the rule says localized; the truth is 102 m away"
    assert truth_alarm(True, 4.9) is None and truth_alarm(False, 102.0) is None and truth_alarm(True, None) is None


def test_the_integrity_state_survives_a_checkpoint():
    cfg = Config()
    a = Integrity(cfg)
    a.on_localized(10)
    a.note_fit(11, True, 0.9, 0.2)
    a.want_check(30, "why not")
    b = Integrity(cfg)
    b.load(a.state())
    assert b.state() == a.state()


# ------------------------------------------------------------------------------ a real run
#: recorded odometry, and the S2M process at the PF's priority: the replay clock waits for every
#: match, and a niced S2M beside busy processes gets a sliver of a core (the priority never
#: changes a replay's result)
AT_PF_PRIORITY = ("localize.recorded_odometry=true", "s2m.replay_process_nice=0")


@pytest.mark.slow
def test_a_late_s2m_holds_the_rule_back_and_the_filter_recovers_once_it_joins(cache_root):
    """S2M held back until scan 20 (``s2m.join_at_scan``): the particle filter alone may converge,
    but nothing says localized before S2M's word; within 30 scans of joining the filter is localized
    within 5 m of the truth, and no scan was ever green and wrong."""
    join, n = 20, 50
    seq = short_town(n)
    cfg = load_config(overrides=[f"s2m.join_at_scan={join}", *AT_PF_PRIORITY])
    with Localizer(seq, cfg, cache_root) as loc:
        snaps = [loc.step() for _ in range(n)]
        events = list(loc.events)
        records = list(loc.records)
    held = [s for s in snaps if s.scan_index < join]
    assert all(s.s2m_status == "held" and f"until scan {join}" in s.s2m_status_detail for s in held)
    assert not any(s.localized for s in held)
    assert not any(e.kind.startswith("s2m_") and e.kind != "s2m_ready" for e in events if e.scan < join)
    assert [(e.scan, e.kind) for e in events if e.kind == "s2m_ready"] == [(join, "s2m_ready")]
    onset = next(r.scan for r in records if r.localized)
    assert join <= onset <= join + 30 and records[onset].error_m < 5.0
    assert not any(r.localized and r.error_m > 5.0 for r in records)
    assert not any(e.kind == "false_fire" for e in events)
    assert snaps[onset].confirmed_at is not None and snaps[onset].confirmed_at >= join


@contextlib.contextmanager
def _localized_at_40(cache_root, *overrides):
    """The short town's first 70 scans (recorded odometry), played to scan 40, localized there."""
    cfg = load_config(overrides=[*AT_PF_PRIORITY, *overrides])
    with Localizer(short_town(70), cfg, cache_root) as loc:
        while loc.k < 40:
            loc.step()
        assert loc.rules.localized
        yield loc


@pytest.mark.slow
def test_an_estimate_moved_unannounced_is_noticed_and_relocalized(cache_root):
    """Once localized, every particle moved 60 m without telling the filter: it is green and wrong
    for a few scans (a false_fire event and the truth alarm say so), then the poor fit asks for the
    whole-map check, which moves the filter back (a relocalized event with both scores)."""
    with _localized_at_40(cache_root) as loc:
        loc.move_estimate(0.0, 60.0)
        snaps = [loc.step() for _ in range(30)]
        events = list(loc.events)
    assert snaps[0].truth_alarm is not None and snaps[0].error_m > 50
    assert any(e.kind == "false_fire" and e.scan == 40 for e in events)
    moved = [e for e in events if e.kind == "relocalized"]
    assert len(moved) == 1 and moved[0].scan <= 48 and "score" in moved[0].detail
    after = [s for s in snaps if s.scan_index > moved[0].scan]
    assert all(s.error_m < 5.0 for s in after)
    assert all(s.truth_alarm is None for s in after)


@pytest.mark.slow
def test_an_estimate_moved_while_s2m_cannot_answer_is_withdrawn_within_the_undecided_doubt(cache_root):
    """Once localized, S2M switched off and every particle moved 60 m: no match can decide the
    poor fit, and "localized" is withdrawn after WITHDRAW_AFTER_POOR_FIT_SCANS scans (an
    ``unconfirmed`` event), not left green until the loss 30 scans on."""
    with _localized_at_40(cache_root) as loc:
        loc.set_params(s2m_enabled=False)
        loc.move_estimate(0.0, 60.0)
        snaps = [loc.step() for _ in range(20)]
        events = list(loc.events)
    withdrawn = [e for e in events if e.kind == "unconfirmed"]
    assert len(withdrawn) == 1 and "no whole-map match has agreed" in withdrawn[0].detail
    assert withdrawn[0].scan <= 40 + WITHDRAW_AFTER_POOR_FIT_SCANS + 1
    assert not any(e.kind == "loss" for e in events)
    green_and_wrong = [s.scan_index for s in snaps if s.localized and s.error_m > 5.0]
    assert green_and_wrong == list(range(40, withdrawn[0].scan))
    assert not any(s.localized for s in snaps if s.scan_index >= withdrawn[0].scan)


@pytest.mark.slow
def test_localized_is_withdrawn_when_s2m_has_said_nothing_for_confirm_within_scans(cache_root):
    """Once localized, S2M switched off (nothing moved, the estimate stays right): after
    ``localize.confirm_within`` scans without an agreement "localized" is withdrawn, and the filter
    says "PF only" as before localization."""
    with _localized_at_40(cache_root, "localize.confirm_within=12") as loc:
        last = loc.integrity.confirmed_at
        loc.set_params(s2m_enabled=False)
        snaps = [loc.step() for _ in range(20)]
        events = list(loc.events)
    withdrawn = [e for e in events if e.kind == "unconfirmed"]
    assert len(withdrawn) == 1 and withdrawn[0].scan == last + 13
    assert f"for 13 scans (since scan {last})" in withdrawn[0].detail
    assert all(s.localized == (s.scan_index < last + 13) for s in snaps)
    assert all(s.error_m < 5.0 for s in snaps)  # right all along: honest amber, not a loss
    assert not any(e.kind in ("loss", "false_fire") for e in events)


def test_a_drive_that_ends_before_s2m_joins_is_not_counted_as_a_failed_recovery():
    from lidarloc.app.bench.integrity import summarize

    def figures(scans, recovery):
        return {
            "false_fires": 0,
            "wrong_green": 0,
            "noticed": 0,
            "recovery": recovery,
            "lost_after": None,
            "relocalizations": 0,
            "spurious_relocalizations": 0,
            "scans": scans,
        }

    done = {
        ("real", "s2m-at-100", 0): figures(100, None),  # S2M would join after the drive's end
        ("town", "s2m-at-100", 0): figures(300, 4),
        ("town", "s2m-at-50", 0): figures(300, None),  # joined and never recovered: a failure
    }
    s = summarize(done, {}, 1.0)
    assert s["cases"]["s2m-at-100"]["s2m_never_joined"] == 1
    assert s["cases"]["s2m-at-100"]["recovery_scans_max"] == 4
    assert s["recovery_scans_max"] is None  # the s2m-at-50 run that never recovered still counts
    del done[("town", "s2m-at-50", 0)]
    assert summarize(done, {}, 1.0)["recovery_scans_max"] == 4


def test_the_rules_floor_waits_for_a_vehicle_standing_still():
    from types import SimpleNamespace

    from lidarloc.app.bench.integrity_figures import floor_figures
    from lidarloc.core.config import LocalizeConfig

    def drive(stand_until: int, n: int = 80):
        rows, x = [], 0.0
        for k in range(n):
            if k > stand_until:
                x += 1.0  # 1 m per scan
            error = 40.0 if k < 5 else 0.2  # the estimate is right from scan 5 on …
            std = 30.0 if k < 5 else 1.0  # … where the filter converged
            rows.append(SimpleNamespace(scan=k, error_m=error, std_x=std, std_y=std, gt_x=x, gt_y=0.0, gt_yaw=0.0))
        return rows

    cfg = LocalizeConfig()  # a window of 10 scans, 10 m driven or 30° turned
    moving = floor_figures(drive(-1), 0, cfg)
    assert moving == {"estimate_recovery": 5, "rule_floor": 15}  # 10 m driven from scan 5 to 15
    standing = floor_figures(drive(40), 0, cfg)
    assert standing == {"estimate_recovery": 5, "rule_floor": 50}  # still until 40, then 10 m

    # right all along (S2M joining late on a filter that had found the truth alone): no floor
    def row(k, error):
        return SimpleNamespace(scan=k, error_m=error, std_x=1.0, std_y=1.0, gt_x=float(k), gt_y=0.0, gt_yaw=0.0)

    right = [row(k, 0.2) for k in range(60)]
    assert floor_figures(right, 30, cfg) == {"estimate_recovery": 0, "rule_floor": 0}
    # … unless the rule's streak started again (a false positive at scan 28): 10 m driven from there
    assert floor_figures(right, 30, cfg, resets={28}) == {"estimate_recovery": 0, "rule_floor": 8}
    # a filter converged 8 m off whose estimate slid onto the truth at 35: its running streak counts
    slid = [row(k, 8.0 if k < 35 else 0.5) for k in range(60)]
    assert floor_figures(slid, 30, cfg) == {"estimate_recovery": 5, "rule_floor": 5}
    wrong = [row(k, 40.0) for k in range(30)]
    assert floor_figures(wrong, 0, cfg) == {"estimate_recovery": None, "rule_floor": None}
