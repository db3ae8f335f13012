"""The viewer never shows green "localized" while the filter is unconfirmed or wrong, and says
what it is doing: S2M not ready (building, held back, off), PF converged but unconfirmed, the
truth alarm (status line, one notification per onset, the timeline's false-fire events), what a
step waits for, the rate it achieves, scans the real-time clock dropped (no kidnap), the Layers
after an S2M match, the truth's colour and where new tabs look first."""

from __future__ import annotations

import re
import threading
import time
from dataclasses import replace

import numpy as np
from helpers import wait_for
from lidarloc.app.viewer.readouts import GREEN_CSS, status_markdown
from lidarloc.core.snapshot import Event, Snapshot

GREEN = f"color:{GREEN_CSS}"


def snapshot(**kw) -> Snapshot:
    base = dict(
        scan_index=30,
        n_scans=100,
        timestamp=3.0,
        particles=np.zeros((4, 11)),
        weights=np.full(4, 0.25),
        best_index=0,
        mean_pose=np.eye(4),
        cov_xyz=np.eye(3) * 0.01,
        std_xyz=np.full(3, 0.1),
        ellipse_xy=(0.2, 0.2, 0.0),
        n_eff=4.0,
        localized=False,
        localized_since=None,
        scan_world=np.zeros((0, 3), np.float32),
        gt_pose=np.eye(4),
        error_m=0.3,
        pf_ms=5.0,
        s2m=None,
        s2m_running=False,
        s2m_acceptance=0.0,
        converged=True,
    )
    base.update(kw)
    return Snapshot(**base)


def status(snap, **kw) -> str:
    return status_markdown(snap, "playing", "replay", "10", kw.pop("events", []), **kw)


def row(text: str, label: str) -> str:
    return next(line for line in text.splitlines() if line.startswith(f"| {label}"))


# ---------------------------------------------------------------------------------- the verdict
def test_s2m_not_ready_reads_amber_pf_only_never_green():
    building = status(snapshot(s2m_status="building", s2m_status_detail="road removal 40 %"))
    assert "PF only — S2M not ready (building: road removal 40 %)" in building and GREEN not in building
    held = status(snapshot(s2m_status="held", s2m_status_detail="held back until scan 100"))
    assert "PF only — S2M not ready (held back until scan 100)" in held and GREEN not in held
    off = status(snapshot(), s2m_enabled=False)
    assert "PF only — S2M off" in off and GREEN not in off
    # the localizer's live word wins over the snapshot's (it moves on while paused)
    live = status(snapshot(), s2m_status=("building", "BEV pyramid"))
    assert "PF only — S2M not ready (building: BEV pyramid)" in live


def test_pf_converged_without_s2m_is_amber_and_the_converged_row_says_so():
    text = status(snapshot(awaiting_confirmation=True))
    assert "PF converged — waiting for S2M to confirm" in text and GREEN not in text
    assert "not confirmed by S2M" in row(text, "PF converged")
    assert "localized since" not in text
    ok = status(snapshot(localized=True, localized_since=20, confirmed_at=28))
    assert GREEN in ok and "localized since scan 20" in ok
    assert "S2M confirmed at scan 28" in ok and row(ok, "PF converged").endswith("| yes |")


def test_truth_alarm_is_red_not_green():
    alarm = "the rule says localized; the truth is 102 m away"
    text = status(snapshot(localized=True, localized_since=25, error_m=102.0, truth_alarm=alarm))
    assert f"false fire: {alarm}" in text and GREEN not in text
    # a recorded step has no alarm field: the same test on its figures
    recorded = status(snapshot(localized=True, localized_since=25, error_m=40.0))
    assert "false fire: the rule says localized; the truth is 40 m away" in recorded
    # without truth there is nothing to alarm about
    assert "false fire" not in status(snapshot(localized=True, gt_pose=None, error_m=None, truth_alarm=alarm))


def test_dropped_scans_are_not_called_a_kidnap():
    snap = snapshot(scan_index=5)
    realtime = status_markdown(snap, "playing", "realtime", "10", [], next_scan=8)
    assert "next scan: 8 (2 scans dropped to keep up with the sensor)" in realtime
    assert "vehicle was moved" not in realtime
    kidnap = [Event(5, "kidnap", "vehicle moved from scan 6 to 8")]
    assert "the vehicle was moved; the filter was not told" in status_markdown(
        snap, "paused", "realtime", "10", kidnap, next_scan=8
    )


# ---------------------------------------------------------------------------------- on a live viewer
def step(v, loc, n: int) -> None:
    k = loc.k
    for _ in range(n):
        v.controls.step.value = True
    wait_for(lambda: v.player.idle and loc.k == k + n, what=f"{n} steps")
    v.update_display(force_plots=True)


def test_status_reads_s2m_readiness_live_from_the_localizer(viewer, monkeypatch):
    v, loc = viewer.viewer, viewer.localizer
    step(v, loc, 1)
    monkeypatch.setattr(loc, "s2m_status", lambda k=None: ("building", "road removal 40 %"), raising=False)
    text = v.status_markdown(loc.snapshot())
    assert "PF only — S2M not ready (building: road removal 40 %)" in text
    assert row(text, "S2M").startswith("| S2M | building in the background: road removal 40 %")


def test_truth_alarm_is_notified_once_per_onset(viewer, monkeypatch):
    v, loc = viewer.viewer, viewer.localizer
    step(v, loc, 2)
    sent = []
    monkeypatch.setattr(v, "show_message", lambda text, **kw: sent.append((text, kw.get("error"))))
    base = loc.snapshot()
    alarm = "the rule says localized; the truth is 102 m away"
    for k, since in ((base.scan_index, 1), (base.scan_index + 1, 1)):  # one onset, two scans
        v.publish(replace(base, scan_index=k, localized=True, localized_since=since, error_m=102.0, truth_alarm=alarm))
        v.update_display()
    assert sent == [(f"false fire at scan {base.scan_index}: {alarm}", True)]
    assert "false fire: " + alarm in v.controls.status.content
    v.publish(replace(base, scan_index=base.scan_index + 2))  # the alarm goes …
    v.update_display()
    v.publish(
        replace(
            base,
            scan_index=base.scan_index + 3,
            localized=True,
            localized_since=base.scan_index + 3,
            error_m=60.0,
            truth_alarm="the rule says localized; the truth is 60 m away",
        )
    )
    v.update_display()  # … and comes back
    assert len(sent) == 2 and sent[1][0].startswith(f"false fire at scan {base.scan_index + 3}")


class _Run:
    """The part of a RecordedRun the timeline reads, with the events it is given."""

    first_kept = 0  # a whole recording (no rolling window)

    def __init__(self, n, events):
        self.n, self._events = n, events

    def events(self):
        return self._events

    def event_steps(self, kinds):
        return np.array(sorted({s for s, e in self._events if e.kind in kinds}), np.int64)

    def scan_of(self, i):
        return i


def test_timeline_lists_and_jumps_to_false_fires(viewer):
    from lidarloc.app.viewer.history import MARKED_EVENTS
    from lidarloc.app.viewer.plots import RUN_MARKS

    assert "false_fire" in MARKED_EVENTS and any("false_fire" in kinds for _, _, kinds in RUN_MARKS)
    tl = viewer.viewer.travel.timeline
    events = [
        (s, Event(s, kind))
        for s, kind in (
            (3, "s2m_accepted"),
            (5, "s2m_rejected"),
            (7, "localized"),
            (7, "false_fire"),
            (9, "s2m_accepted"),
            (12, "relocalized"),
        )
    ]
    tl.set_run(_Run(20, events), live_available=False)
    tl.go(0)
    assert tl.next_event() == 7  # the default passes over the S2M verdicts
    assert tl.next_event() == 12
    tl.kinds.value = "false fire"
    assert "7 false fire" in tl.event_list.content and "localized" not in tl.event_list.content
    tl.go(0)
    assert tl.next_event() == 7
    tl.kinds.value = "S2M"
    tl.go(0)
    assert [tl.next_event(), tl.next_event(), tl.next_event()] == [3, 5, 9]


def test_status_says_what_a_step_waits_for(street, cache_root):
    from lidarloc.app.viewer.serve import serve
    from lidarloc.core.config import Config
    from lidarloc.core.localizer import Localizer

    cfg = Config()
    cfg.pf.n_particles = 300
    cfg.localize.s2m_process = False
    loc = Localizer(street, cfg, cache_root)
    gate = threading.Event()  # every match waits here until the test opens it
    for name in ("match_local", "match_global"):
        real = getattr(loc.s2m.matcher, name)
        setattr(loc.s2m.matcher, name, lambda *a, _real=real, **k: (gate.wait(60), _real(*a, **k))[1])
    handle = serve(loc, port=0, autoplay=False)
    v = handle.viewer
    try:
        v.controls.speed.value = "max"
        v.controls.play.value = True

        def says_waiting() -> bool:
            v.update_display()
            return "· waiting for the S2M match started at scan " in v.controls.status.content

        wait_for(says_waiting, what="the wait for the match in the status")
        first = v.controls.status.content.splitlines()[0]
        assert re.search(r"waiting for the S2M match started at scan \d+ \(\d+\.\d s\)", first), first
        # the rate achieved falls while the step waits, instead of the last one staying up
        wait_for(
            lambda: v.player.achieved_rate(window=1.0) is not None and v.player.achieved_rate(window=1.0) < 1.0,
            what="the rate falling while waiting",
        )
    finally:
        gate.set()
        handle.stop()
        loc.close()


def test_achieved_rate_counts_a_step_that_is_still_running():
    from lidarloc.app.viewer.player import Player

    class Steps:
        """Fast steps until the gate closes, then one that waits for it."""

        def __init__(self):
            self.k, self.gate = 0, threading.Event()
            self.gate.set()
            self.seq = type("Seq", (), {"timestamps": np.arange(10_000) * 0.1})()

        @property
        def done(self):
            return False

        def step(self, deadline=None):
            self.gate.wait()
            time.sleep(0.002)
            self.k += 1
            return self.k

    loc = Steps()
    player = Player(loc, lambda s: None, lambda m: None, speed=50.0)
    player.start()
    try:
        player.play()
        wait_for(lambda: loc.k >= 10, what="10 steps")
        assert player.achieved_rate(window=0.5) > 5.0
        loc.gate.clear()
        # it falls while the step waits (the last steps' rate does not stay up), and never
        # reads 0 while the scans still advance, however slowly
        wait_for(lambda: player.achieved_rate(window=0.5) < 1.0, what="the rate falling while a step waits")
        assert player.achieved_rate(window=0.5) > 0.0
    finally:
        loc.gate.set()
        player.stop()


def test_layers_come_back_after_an_s2m_match(viewer):
    v, loc = viewer.viewer, viewer.localizer
    step(v, loc, 4)
    assert v.drawn.s2m is not None
    for name, node in (("map", "map"), ("scan", "scan")):
        v.controls.layers[name].value = False
        assert not v.scene.node(node).visible
        v.controls.layers[name].value = True
        assert "internal error" not in v.message, v.message
        assert v.scene.node(node).visible


def test_truth_colour_stands_out_from_the_map_and_the_labels_name_it():
    from lidarloc.app.viewer import style
    from lidarloc.app.viewer.legend import legend_markdown
    from lidarloc.app.viewer.panel import LAYER_LABELS

    gt = np.asarray(style.GT_COLOR, float)
    assert np.linalg.norm(style.HEIGHT_LUT.astype(float) - gt, axis=1).min() > 120  # roofs are near white
    for other in (style.SCAN_COLOR, style.EST_COLOR, style.BEST_COLOR, style.S2M_ACCEPTED_COLOR, style.BEV_COLOR):
        assert np.linalg.norm(np.asarray(other, float) - gt) > 70
    assert style.css(style.GT_COLOR) in legend_markdown()
    assert all(style.GT_NAME in label for name, label in LAYER_LABELS if name in ("trajectories", "vehicles"))
    assert not any("white" in label for _, label in LAYER_LABELS)


def test_new_tabs_look_at_the_vehicle_not_the_whole_map(viewer, street):
    server, v = viewer.server, viewer.viewer
    start = street.pose(0)[:3, 3]
    look_at = np.asarray(server.initial_camera.look_at)
    assert np.linalg.norm(look_at - start) < 1.0
    assert np.linalg.norm(look_at - v.scene.map_center) > 10.0  # not the whole map's centre
    assert np.linalg.norm(np.asarray(server.initial_camera.position) - look_at) < 80.0  # close enough to see it
