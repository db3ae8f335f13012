"""The viewer's playback thread (app/viewer/player.py) on a stand-in localizer with 1 ms steps:
replay and real-time pacing, max speed, single steps, refused settings, and a failing step."""

import re
import threading
import time

import numpy as np
import pytest
from helpers import wait_for
from lidarloc.app.viewer.player import TRACE_LATE_ENV, Player
from lidarloc.core.errors import LidarlocError

# Upper bounds below only catch a player that hangs or paces an order of magnitude too slowly: a
# loaded 2-core machine can delay a thread by a large fraction of a second. The lower bounds are
# the pacing itself (a player never starts a scan before it is due, however loaded the machine).
SLOW_BOUND_S = 5.0


class InstantSteps:
    """What the Player needs of a localizer, with 1 ms steps: the pacing is all the player's."""

    def __init__(self, n=100_000, dt=0.1):
        self.k, self.n = 0, n
        self.seq = type("Seq", (), {"timestamps": np.arange(n) * dt})()
        self.lock = threading.Lock()

    @property
    def done(self):
        return self.k >= self.n

    def step(self, deadline=None):
        time.sleep(0.001)
        self.k += 1
        return self.k


def time_scans(player, loc, n):
    """Seconds from play() until ``n`` more scans are done (then paused and idle)."""
    k0, t0 = loc.k, time.perf_counter()
    player.play()
    wait_for(lambda: loc.k >= k0 + n, what=f"{n} scans")
    elapsed = time.perf_counter() - t0
    player.pause()
    assert player.wait_idle(5)
    return elapsed


def test_player_pacing():
    loc = InstantSteps()
    player = Player(loc, lambda s: None, lambda m: None, speed=20.0)
    player.start()
    try:
        # replay at 20 scans/s: 6 scans are 5 intervals of 50 ms after the first
        assert 0.23 <= time_scans(player, loc, 6) < SLOW_BOUND_S
        player.set_speed(None)  # max: as fast as the localizer goes …
        # … so 50 scans take less than the 2.5 s that pacing them at 20 scans/s would
        assert time_scans(player, loc, 50) < 50 / 20.0
        # realtime at the sequence's timestamps (0.1 s apart), whatever the speed says (at 100
        # scans/s, 5 scans would take 0.04 s)
        player.set_clock("realtime")
        player.set_speed(100.0)
        assert 0.38 <= time_scans(player, loc, 5) < SLOW_BOUND_S
        # step: exactly one scan, then idle
        k = loc.k
        player.step_once()
        assert player.wait_idle(5) and loc.k == k + 1
        with pytest.raises(LidarlocError):
            player.set_speed(0)
        with pytest.raises(LidarlocError):
            player.set_clock("fast")
    finally:
        t0 = time.perf_counter()
        player.stop()
        # stop() joins the thread for at most 1.5 s; more means it did not return
        assert time.perf_counter() - t0 < SLOW_BOUND_S
    assert not player.playing


def test_player_survives_a_failing_step():
    class Failing(InstantSteps):
        def step(self, deadline=None):
            if self.k == 2:
                raise LidarlocError("scan 2: corrupt file")
            return super().step()

    loc, errors = Failing(), []
    player = Player(loc, lambda s: None, errors.append, speed=None)
    player.start()
    try:
        player.play()
        wait_for(lambda: errors, what="the error")
        assert errors == ["scan 2: corrupt file"] and not player.playing
        loc.k = 3  # past the bad scan: playback resumes
        player.play()
        wait_for(lambda: loc.k >= 10, what="playing again")
    finally:
        player.stop()


def test_player_reports_the_achieved_rate():
    loc = InstantSteps()
    player = Player(loc, lambda s: None, lambda m: None, speed=20.0)
    player.start()
    try:
        assert player.achieved_rate() is None  # nothing played yet
        player.play()
        wait_for(lambda: loc.k >= 12, what="12 scans")
        rate = player.achieved_rate()
        # paced at 20 scans/s: never above it; well above half of it unless the machine stalls
        assert rate is not None and 8.0 < rate <= 20.0 * 1.01
        player.pause()
        assert player.wait_idle(5)
        assert player.achieved_rate() is None  # paused: no rate to show
        assert player.lag_s is None  # replay: no sensor clock to lag behind
    finally:
        player.stop()


def test_a_rebase_while_a_snapshot_is_published_keeps_the_rate_readable():
    """A kidnap waits for the step's lock, then rebases the player while the step's snapshot is
    still being published: the rate must stay readable, and count again from the next steps."""
    loc = InstantSteps()
    publishing, rebased = threading.Event(), threading.Event()
    hold = threading.Event()

    def on_snapshot(_snap):
        if hold.is_set():
            hold.clear()
            publishing.set()
            assert rebased.wait(10), "the test did not rebase"

    player = Player(loc, on_snapshot, lambda m: None, speed=20.0)
    player.start()
    try:
        player.play()
        wait_for(lambda: loc.k >= 3, what="3 scans")
        hold.set()
        assert publishing.wait(10), "no step published a snapshot"
        player.rebase()
        rebased.set()
        k = loc.k
        wait_for(lambda: loc.k >= k + 6, what="6 scans after the rebase")
        rate = player.achieved_rate()  # raised TypeError (None among the step starts)
        assert rate is not None and 0.0 < rate <= 20.0 * 1.01
    finally:
        player.stop()


def test_player_reports_how_far_behind_the_sensor_clock_it_is():
    class SlowSteps(InstantSteps):
        """Scans every 0.1 s on the sensor clock, each taking 0.25 s to process."""

        def step(self, deadline=None):
            time.sleep(0.25)
            self.k += 1
            return self.k

    loc = SlowSteps()
    player = Player(loc, lambda s: None, lambda m: None, clock="realtime")
    player.start()
    try:
        player.play()
        wait_for(lambda: loc.k >= 4, what="4 scans")
        # scan k arrives at 0.1·k s but starts at ≥ 0.25·k s: the 4th started ≥ 0.45 s late
        lag = player.lag_s
        assert lag is not None and lag >= 0.3
        assert player.achieved_rate() <= 1 / 0.25 * 1.01
    finally:
        player.stop()


def test_player_loops_counts_late_scans_and_names_a_failing_block():
    """At the end of the sequence ``on_finished`` runs (here: start again, a loop); the late-scan
    counts are per call; a failing display/recorder pauses playback with one line naming it."""
    from lidarloc.app.viewer.faults import BlockFailed

    loc, errors, loops = InstantSteps(n=5), [], []

    def again():
        loops.append(loc.k)
        if len(loops) < 3:
            loc.k = 0
            player.play()

    player = Player(loc, lambda s: None, errors.append, speed=None, on_finished=again)
    player.start()
    try:
        player.play()
        wait_for(lambda: len(loops) == 3, what="three loops")
        assert loops == [5, 5, 5] and not errors
        counts = player.take_counts()
        assert counts["steps"] == 15 and counts["late"] == 0  # replay clock: nothing is late
        assert player.take_counts()["steps"] == 0
    finally:
        player.stop()

    def failing(snap):
        if snap == 3:
            raise BlockFailed("recorder", OSError("No space left on device"))

    loc2, errors2 = InstantSteps(), []
    p2 = Player(loc2, failing, errors2.append, speed=None)
    p2.start()
    try:
        p2.play()
        wait_for(lambda: errors2, what="the recorder's failure")
        assert not p2.playing and loc2.k == 3
        assert errors2 == [
            "recorder failed after scan 2: OSError: No space left on device; playback paused "
            "(the filter's results up to that scan stand)"
        ]
    finally:
        p2.stop()


def test_a_late_scan_leaves_every_threads_stack_in_the_trace_file(tmp_path, monkeypatch):
    """With $LIDARLOC_TRACE_LATE set, the moment the next scan becomes late the player writes
    every thread's stack (the one stuck in the slow step among them), then names the late scan."""
    trace = tmp_path / "late.txt"
    monkeypatch.setenv(TRACE_LATE_ENV, str(trace))

    class OneStall(InstantSteps):
        def step(self, deadline=None):
            if self.k == 5:
                self.stuck_in_scan_five()
            return super().step()

        def stuck_in_scan_five(self):
            time.sleep(0.4)  # the next scans arrive meanwhile: scan 6 starts ≥ 0.3 s late

    loc = OneStall()
    player = Player(loc, lambda s: None, lambda m: None, clock="realtime")
    player.start()
    try:
        player.play()
        wait_for(lambda: loc.k >= 9, what="9 scans")
    finally:
        player.stop()
    text = trace.read_text()
    assert "Timeout" in text and "stuck_in_scan_five" in text  # faulthandler's dump, the culprit named
    assert text.count("Thread 0x") >= 2  # every thread: the test's own and the player's at least
    late_lines = [line for line in text.splitlines() if line.startswith("^ the stacks above: scan 6 ")]
    assert late_lines and float(late_lines[0].split(" started ")[1].split(" s ")[0]) >= 0.2
    assert re.search(r"\(late, \d\d:\d\d:\d\d UTC\)$", late_lines[0])  # when, to lay beside other logs


def test_no_trace_file_unless_asked_and_one_line_if_it_cannot_be_written(tmp_path, monkeypatch):
    monkeypatch.delenv(TRACE_LATE_ENV, raising=False)
    player = Player(InstantSteps(), lambda s: None, lambda m: None, clock="realtime")
    assert player._tracer is None
    monkeypatch.setenv(TRACE_LATE_ENV, str(tmp_path / "no-such-folder" / "late.txt"))
    with pytest.raises(LidarlocError, match="LIDARLOC_TRACE_LATE: cannot write .*late.txt"):
        Player(InstantSteps(), lambda s: None, lambda m: None, clock="realtime")


def test_realtime_steps_are_given_the_next_scans_arrival_less_the_publishing_as_their_deadline():
    """Real time: each step is handed the ``time.perf_counter()`` by which it should end (the next
    scan's arrival, less what publishing a snapshot took lately), so a landing's wait for the
    odometry leaves the next scan on time; a single step while paused has none."""
    publish_s = 0.03

    class Recording(InstantSteps):
        def __init__(self):
            super().__init__()
            self.calls = []  # (k, when the step started, its deadline)

        def step(self, deadline=None):
            self.calls.append((self.k, time.perf_counter(), deadline))
            return super().step()

    loc = Recording()
    player = Player(loc, lambda s: time.sleep(publish_s), lambda m: None, clock="realtime")
    player.start()
    try:
        time_scans(player, loc, 6)
        k = loc.k
        player.step_once()
        assert player.wait_idle(5) and loc.k == k + 1
    finally:
        player.stop()
    played, single = loc.calls[:-1], loc.calls[-1]
    assert single[2] is None
    assert all(d is not None for _, _, d in played)
    # the first deadline is the next scan's arrival (nothing published yet): within a period of
    # the step's start; every later one is its scan's next arrival less the publishing seen
    # lately (≥ publish_s: a sleep never ends early), the arrivals 0.1 s apart
    _, start0, d0 = played[0]
    assert start0 < d0 <= start0 + 0.1 + 1e-6
    for i, (_, _, d) in enumerate(played[1:], start=1):
        assert d0 + 0.1 * i - 0.5 < d <= d0 + 0.1 * i - publish_s + 1e-6, (i, d - d0)


def test_a_recent_peak_jumps_to_a_longer_duration_and_decays_slowly_after_it():
    from lidarloc.core.localizer.deadline import RecentPeak

    peak = RecentPeak(decay=0.1)
    assert peak.value == 0.0
    peak.add(0.02)
    assert peak.value == 0.02  # a longer one is the mark at once
    peak.add(0.2)
    assert peak.value == 0.2
    peak.add(0.0)  # shorter ones pull it down a tenth of the way each
    assert peak.value == pytest.approx(0.18)
    for _ in range(50):
        peak.add(0.01)
    assert 0.01 < peak.value < 0.02
    peak.add(-1.0)  # a clock that stepped back counts as nothing, not as a negative duration
    assert peak.value >= 0.0
