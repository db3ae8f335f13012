"""What a new user trips over in the viewer, each on a real viser server (no browser): the last
S2M match after a restart, a kidnap while paused, the S2M status after the run and while S2M is
off, playback that waits for the first tab, notifications to the tab that acted, the achieved
rate, and the map shown before the localizer is ready. The browser side (late tabs, the plots)
is in test_viewer_browser.py."""

from __future__ import annotations

import threading
from dataclasses import replace

import numpy as np
import pytest
from helpers import make_localizer, wait_for
from lidarloc.app.bench.socket_tabs import SocketTab as Tab  # a tab as the server sees it


def step(v, loc, n: int) -> None:
    k = loc.k
    for _ in range(n):
        v.controls.step.value = True
    wait_for(lambda: v.player.idle and loc.k == k + n, what=f"{n} steps")
    v.update_display(force_plots=True)


def s2m_row(text: str) -> str:
    return next(line for line in text.splitlines() if line.startswith("| S2M |"))


# ---------------------------------------------------------------------------------- restart
def test_restart_removes_the_last_runs_s2m_match(viewer):
    v, loc = viewer.viewer, viewer.localizer
    step(v, loc, 4)
    assert loc.snapshot().s2m is not None
    nodes = [v.scene.node(n) for n in ("s2m_scan", "s2m_region", "s2m_label")]
    assert all(n is not None and n.visible for n in nodes)
    v.controls.restart.value = True
    v.update_display()
    assert v.drawn.scan_index == -1 and v.drawn.s2m is None
    assert not any(n.visible for n in nodes)
    # toggling the layer does not bring the old match back …
    v.controls.layers["s2m"].value = False
    v.controls.layers["s2m"].value = True
    assert not any(n.visible for n in nodes)
    # … and the new run's first match shows again
    step(v, loc, 4)
    assert v.drawn.s2m is not None
    assert all(v.scene.node(n).visible for n in ("s2m_scan", "s2m_region", "s2m_label"))


# ---------------------------------------------------------------------------------- kidnap while paused
def test_kidnap_while_paused_updates_the_status_at_once(viewer):
    v, loc = viewer.viewer, viewer.localizer
    step(v, loc, 2)
    before = v.controls.status.content
    v.controls.kidnap_skip.value = 5
    v.controls.kidnap.value = True
    assert loc.k == 7 and not v.player.playing
    v.update_display()  # what the display thread does next; no step in between
    text = v.controls.status.content
    assert text != before
    assert "next scan: 7" in text
    assert "kidnap — vehicle moved from scan 2 to 7" in text  # the recent events
    assert "not localized" in text


# ---------------------------------------------------------------------------------- S2M status line
def test_s2m_status_is_not_running_after_the_run_and_says_off_when_off(viewer):
    v, loc = viewer.viewer, viewer.localizer
    v.controls.speed.value = "max"
    v.controls.play.value = True
    wait_for(lambda: loc.done and v.player.idle, what="the end of the run")
    v.update_display()
    text = v.controls.status.content
    assert "finished" in text and "running" not in s2m_row(text)
    # even when a match was still in flight at the last scan
    last = replace(loc.snapshot(), s2m_running=True)
    assert "running" not in s2m_row(v.status_markdown(last))
    # S2M off: the row says so instead of the last match's figures
    v.controls.s2m_enabled.value = False
    v.update_display()
    assert s2m_row(v.controls.status.content) == "| S2M | off |"
    v.controls.s2m_enabled.value = True
    v.update_display()
    assert s2m_row(v.controls.status.content) != "| S2M | off |"


def test_s2m_status_says_running_while_a_match_is_in_flight():
    from lidarloc.app.viewer.readouts import status_markdown
    from lidarloc.core.snapshot import Snapshot

    snap = Snapshot(
        scan_index=3,
        n_scans=10,
        timestamp=0.3,
        particles=np.zeros((4, 11)),
        weights=np.full(4, 0.25),
        best_index=0,
        mean_pose=np.eye(4),
        cov_xyz=np.eye(3),
        std_xyz=np.ones(3),
        ellipse_xy=(2.0, 2.0, 0.0),
        n_eff=4.0,
        localized=False,
        localized_since=None,
        scan_world=np.zeros((0, 3), np.float32),
        gt_pose=None,
        error_m=None,
        pf_ms=5.0,
        s2m=None,
        s2m_running=True,
        s2m_acceptance=0.0,
    )
    assert "running" in s2m_row(status_markdown(snap, "playing", "replay", "10", []))
    assert "running" not in s2m_row(status_markdown(snap, "finished", "replay", "10", []))
    assert s2m_row(status_markdown(snap, "playing", "replay", "10", [], s2m_enabled=False)) == "| S2M | off |"


# ---------------------------------------------------------------------------------- playback waits for a tab
def test_playback_waits_for_the_first_tab(street, cache_root):
    from lidarloc.app.viewer.serve import serve

    loc = make_localizer(street, cache_root)
    handle = serve(loc, port=0)
    tab = None
    try:
        assert handle.wait_ready(30)
        v = handle.viewer
        assert not v.player.playing and loc.k == 0  # attach returned without playing
        tab = Tab(handle.port)
        wait_for(lambda: loc.k >= 2, what="playback after the first tab connected")
        # a second tab does not resume a run the user paused
        v.controls.play.value = True
        wait_for(lambda: v.player.idle, what="pause")
        k = loc.k
        second = Tab(handle.port)
        wait_for(lambda: len(handle.server.get_clients()) == 2, what="the second tab")
        assert not v.player.playing and loc.k == k
        second.close()
    finally:
        if tab is not None:
            tab.close()
        handle.stop()
        loc.close()


@pytest.mark.parametrize("command", ["demo", "view"])
def test_autoplay_option(command, monkeypatch):
    from helpers import viewer_options

    assert viewer_options(command, [], monkeypatch)["autoplay"] is False
    assert viewer_options(command, ["--autoplay"], monkeypatch)["autoplay"] is True


def test_autoplay_true_plays_without_a_tab(street, cache_root):
    from lidarloc.app.viewer.serve import serve

    loc = make_localizer(street, cache_root)
    handle = serve(loc, port=0, autoplay=True)
    try:
        assert handle.viewer.player.playing
        wait_for(lambda: loc.k >= 2, what="autoplay")
    finally:
        handle.stop()
        loc.close()


# ---------------------------------------------------------------------------------- notifications
def test_messages_are_notified_to_the_tab_that_acted(viewer, monkeypatch):
    import viser

    sent = []
    real = viser.ClientHandle.add_notification

    def record(self, title, body, **kwargs):
        sent.append((self.client_id, body, kwargs.get("color")))
        return real(self, title, body, **kwargs)

    monkeypatch.setattr(viser.ClientHandle, "add_notification", record)
    v, _loc = viewer.viewer, viewer.localizer
    a, b = Tab(viewer.port), Tab(viewer.port)
    try:
        wait_for(lambda: len(viewer.server.get_clients()) == 2, what="two tabs")
        first, second = sorted(viewer.server.get_clients())
        a.click(v.controls.reset)
        wait_for(lambda: sent, what="a notification")
        assert sent == [(first, "particles reset globally", "blue")]
        assert v.message == "particles reset globally"  # the panel line stays
        v.controls.kidnap_skip.value = 0
        b.click(v.controls.kidnap)
        wait_for(lambda: len(sent) == 2, what="the refusal")
        assert sent[1][0] == second and sent[1][1].startswith("refused: kidnap skip") and sent[1][2] == "red"
    finally:
        a.close()
        b.close()


# ---------------------------------------------------------------------------------- achieved rate
def test_status_shows_the_achieved_rate_while_playing(viewer):
    v, _loc = viewer.viewer, viewer.localizer
    v.controls.speed.value = "5"
    v.controls.play.value = True
    wait_for(lambda: v.player.achieved_rate() is not None, what="a measured rate")
    rate = v.player.achieved_rate()
    assert 0 < rate <= 5.5  # never faster than the set speed
    wait_for(lambda: "achieved" in v.controls.status.content, what="the rate in the status")
    assert "scans/s" in v.controls.status.content
    v.controls.play.value = True  # pause: no rate
    wait_for(lambda: v.player.idle)
    v.update_display()
    assert "achieved" not in v.controls.status.content


# ---------------------------------------------------------------------------------- the map before the tables
def test_map_is_shown_while_the_tables_are_built_and_sent_once(street, cache_root):
    from lidarloc.app.viewer.serve import serve
    from lidarloc.core.config import Config

    seen = threading.Event()
    go = threading.Event()
    built = []

    def factory(progress=None, on_map=None):
        from lidarloc.core.localizer import Localizer

        def shown(prior_map):
            on_map(prior_map)
            seen.set()
            go.wait(30)  # hold the build here: the tables are not built yet

        cfg = Config()
        cfg.pf.n_particles = 200
        built.append(Localizer(street, cfg, cache_root, progress=progress, on_map=shown))
        return built[-1]

    handle = serve(factory, port=0, autoplay=False)
    try:
        v = handle.viewer
        assert seen.wait(60)
        cloud = v.scene.node("map")
        assert cloud is not None and len(cloud.points) > 1000 and v.localizer is None
        # new tabs look at it
        assert np.allclose(handle.server.initial_camera.look_at, v.scene.map_center, atol=1e-3)
        assert np.linalg.norm(v.scene.map_center[:2]) > 10
        go.set()
        assert handle.wait_ready(60)
        assert v.scene.node("map") is cloud  # attach did not send it again
    finally:
        go.set()
        handle.stop()
    wait_for(lambda: built and built[0].closed, what="localizer closed")


def test_the_map_is_drawn_under_the_display_lock(viewer):
    """The build thread draws the map while the display thread may be drawing the overview and
    the map's tiles: it waits for a display update in progress, as every other scene write does."""
    v, loc = viewer.viewer, viewer.localizer
    v._map_shown = None  # as before the first map
    with v.drawing():
        t = threading.Thread(target=v.show_map, args=(loc.prior_map,))
        t.start()
        t.join(0.5)
        assert t.is_alive() and v._map_shown is None  # waiting for the display update to end
    t.join(30)
    assert not t.is_alive() and v._map_shown is loc.prior_map


# ---------------------------------------------------------------------------------- tabs that close at once
def test_tabs_that_close_at_once_leave_nothing_behind(viewer):
    """A tab closed while the server builds its camera folder (a reload, a page opened and shut):
    no write-to-a-closed-connection warning, and no camera folder kept for it."""
    import warnings

    handle = viewer
    assert handle.wait_ready(30)
    cameras = handle.viewer.cameras
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(30):
            Tab(handle.port).close()
        wait_for(lambda: not handle.server.get_clients(), what="every tab gone")
        wait_for(lambda: not cameras._tabs, what="every tab's camera folder dropped")
        # one tab that stays: its folder is built and kept
        tab = Tab(handle.port)
        try:
            wait_for(lambda: len(cameras._tabs) == 1, what="the open tab's camera folder")
        finally:
            tab.close()
        wait_for(lambda: not cameras._tabs, what="the last tab's camera folder dropped")
    closed = [str(w.message) for w in caught if "closed connection" in str(w.message)]
    assert not closed, closed[0]


# ------------------------------------------------------------------------ actions never dropped
def test_a_tabs_action_is_not_dropped_while_the_viewer_writes_values_on_another_thread(viewer):
    """The viewer quiets the callbacks of the values it writes itself (viser runs them in the
    writing thread); a tab's click handled on another thread meanwhile still runs. With one flag
    for all threads, a click handled while the display thread wrote a value (the BEV level's range
    when the pyramid arrives, a new run's live parameters) was dropped without a word: the likely
    cause of a browser test that waited a minute under load for the message of its Apply."""
    from types import SimpleNamespace

    v = viewer.viewer
    ran = []
    callback = v._guarded(lambda: ran.append(threading.current_thread().name), needs_localizer=False)
    with v._quietly():
        callback(SimpleNamespace(client=None))  # the viewer's own write, in this thread: quiet
        tab = threading.Thread(target=callback, args=(SimpleNamespace(client=None),), name="tab")
        tab.start()
        tab.join()
    assert ran == ["tab"]


# ---------------------------------------------------------------------------------- a run a branch took over
class SlowToClose:
    """A localizer whose close hangs (its children busy on a loaded machine) until released."""

    def __init__(self):
        self.release, self.closed, self.killed = threading.Event(), threading.Event(), threading.Event()

    def close(self):
        self.release.wait(30)
        self.closed.set()

    def kill_processes(self):
        self.killed.set()


def test_stopping_the_viewer_kills_the_children_of_a_run_still_closing(viewer):
    done, slow = SlowToClose(), SlowToClose()
    retired = viewer.viewer.retired
    closer = retired.close(done)
    done.release.set()
    closer.join(30)
    assert done.closed.is_set() and not closer.is_alive()
    retired.close(slow)  # a branch took over from it; its close hangs
    viewer.stop()
    assert slow.killed.is_set() and not done.killed.is_set()  # only the one still closing
    slow.release.set()
    assert slow.closed.wait(30)
