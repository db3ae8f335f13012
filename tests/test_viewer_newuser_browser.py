"""The viewer as a new user finds it, in a real (headless) Chromium: a kidnap while a step is in
flight leaves the status live, a display update that fails says the status is not current and the
next one recovers, a click on no particle leaves no lasting refusal, and notifications do not
cover the status window.

WebGL is software-rendered here (no GPU), so waits are generous; every wait polls for a
condition, none sleeps for a fixed time."""

from __future__ import annotations

import threading

import pytest
from browser import JS_SCAN, LOAD_TIMEOUT, STEP_TIMEOUT, serving
from helpers import browser_localizer, wait_for
from lidarloc.app.bench.viewer import JS_CAMERA, camera_moved_by

pytestmark = [pytest.mark.browser, pytest.mark.slow]

# the status window's text (the element with the scan counter and the figures' table), and a box
JS_STATUS_TEXT = """(() => {
    let best = null;
    for (const el of document.querySelectorAll('div')) {
        const t = el.innerText || '';
        if (/Scan (\\d+|–) of \\d+/.test(t) && (!best || best.contains(el))) best = el;
    }
    return best ? best.innerText : '';
})()"""
JS_STATUS_BOX = """(() => {
    let best = null;
    for (const el of document.querySelectorAll('div')) {
        const t = el.innerText || '';
        if (/Scan (\\d+|–) of \\d+/.test(t) && t.includes('position std') && (!best || best.contains(el))) best = el;
    }
    const r = best.getBoundingClientRect();
    return {x: r.x, y: r.y, width: r.width, height: r.height};
})()"""


@pytest.fixture(scope="module")
def served(cache_root):
    """A run playing at 2 scans/s, long enough (300 scans, 150 s at least) for every test here
    (the street's map from the session's cache, shared with the other browser tests' runs)."""
    loc = browser_localizer(cache_root, n_scans=300)
    with serving(loc, autoplay=True, speed="2") as handle:
        yield handle


def open_viewer(browser, url, ready: str = f"{JS_SCAN} >= 0"):
    """A tab on ``url``, once the page shows the status (``ready``: a condition in the page)."""
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    page.goto(url, timeout=LOAD_TIMEOUT)
    page.wait_for_selector("canvas", timeout=LOAD_TIMEOUT)
    page.wait_for_function(ready, timeout=LOAD_TIMEOUT)
    return page


# a paused run before its first scan: the status is there, Play can be pressed
PAUSED_READY = "document.body.innerText.includes('Scan – of') && document.body.innerText.includes('paused')"


def test_kidnap_while_a_snapshot_is_published_keeps_the_status_live(browser, served, monkeypatch):
    """A kidnap waits for the step's lock and rebases the player while that step's snapshot is
    still being published (recorded, handed to the display). The test holds the publishing until
    the rebase is done, so the kidnap lands there every time."""
    v, loc = served.viewer, served.localizer
    page = open_viewer(browser, served.url)
    page.wait_for_function(f"{JS_SCAN} >= 3", timeout=STEP_TIMEOUT)
    armed, holding, rebased = threading.Event(), threading.Event(), threading.Event()
    rebase, on_step = v.player.rebase, v.travel.on_step

    def rebase_and_say():
        rebase()
        rebased.set()

    def held_on_step(localizer, snap):
        if armed.is_set():
            armed.clear()
            holding.set()
            rebased.wait(STEP_TIMEOUT / 1000)
        return on_step(localizer, snap)

    monkeypatch.setattr(v.player, "rebase", rebase_and_say)
    monkeypatch.setattr(v.travel, "on_step", held_on_step)
    v.controls.kidnap_skip.value = 20
    page.wait_for_function("[...document.querySelectorAll('input')].some(i => i.value === '20')", timeout=STEP_TIMEOUT)
    armed.set()
    assert holding.wait(STEP_TIMEOUT / 1000), "no step published a snapshot"
    page.get_by_role("button", name="Kidnap").click()
    assert rebased.wait(STEP_TIMEOUT / 1000), f"the kidnap did not reach the player (message {v.message!r})"
    assert any(e.kind == "kidnap" for e in loc.events)
    k = loc.k  # the scan after the jump, or one past it
    # the status follows the filter past the jump (it stayed at the kidnap's scan for good)
    page.wait_for_function(f"{JS_SCAN} >= {k + 2}", timeout=STEP_TIMEOUT)
    assert v.display_faults.count == 0, v.display_faults.last
    page.close()


def test_notifications_hints_and_a_failed_display_update_in_one_tab(browser, served, monkeypatch):
    """One tab: notifications leave the status window uncovered; a click on no particle leaves
    a hint that goes by itself, no lasting refusal; a display update that fails says the status
    is not current, and the next one recovers by itself."""
    v = served.viewer
    page = open_viewer(browser, served.url)

    # --- notifications beside the status window, not over it
    page.wait_for_function(f"{JS_STATUS_TEXT}.includes('position std')", timeout=STEP_TIMEOUT)
    page.get_by_role("button", name="Reset globally").click()
    toast = page.locator(".mantine-Notification-root", has_text="particles reset globally").first
    toast.wait_for(timeout=STEP_TIMEOUT)
    status = page.evaluate(JS_STATUS_BOX)
    # every notification on screen (viser's own about software WebGL too), none over the status;
    # read at one moment in the page (one may close meanwhile)
    boxes = page.evaluate(
        "[...document.querySelectorAll('.mantine-Notification-root')].map(e => e.getBoundingClientRect())"
        ".map(r => ({x: r.x, y: r.y, width: r.width, height: r.height}))"
    )
    assert boxes, "no notification on screen"
    for box in boxes:
        overlap_x = min(box["x"] + box["width"], status["x"] + status["width"]) - max(box["x"], status["x"])
        overlap_y = min(box["y"] + box["height"], status["y"] + status["height"]) - max(box["y"], status["y"])
        assert overlap_x <= 0 or overlap_y <= 0, f"a notification {box} covers the status {status}"
        # still inside the window: readable, not pushed off screen
        assert box["x"] + box["width"] <= 1400 and box["y"] >= 0, box

    # --- a click on no particle: a hint, not a state of the run
    clients = v.server.get_clients()
    client = clients[max(clients)]  # this page's tab: the newest
    v.cameras._tabs[client.client_id].follow.value = False  # the camera stays where it is put
    # the tab looks up into the sky from high above: no particle is near any click
    client.camera.position = (0.0, 0.0, 800.0)
    client.camera.look_at = (1.0, 0.0, 1600.0)
    page.wait_for_function("window.__viserMutable.camera.position.length() > 700", timeout=STEP_TIMEOUT)
    box = page.locator("canvas").first.bounding_box()
    page.mouse.click(box["x"] + box["width"] * 0.5, box["y"] + box["height"] * 0.6)
    page.wait_for_function("document.body.innerText.includes('no particle near that click')", timeout=STEP_TIMEOUT)
    assert "refused" not in v.message and "no particle near" in v.message, v.message
    page.wait_for_function(
        f"!{JS_STATUS_TEXT}.includes('no particle near') && "
        "!document.body.innerText.includes('no particle near that click')",
        timeout=STEP_TIMEOUT,
    )

    # --- a display update that fails: "not current", no stale green, then a good one by itself
    failing = threading.Event()
    failing.set()
    draw = v.scene.draw

    def failing_draw(*args, **kwargs):
        if failing.is_set():
            raise RuntimeError("a display failure made by the test")
        return draw(*args, **kwargs)

    monkeypatch.setattr(v.scene, "draw", failing_draw)
    page.wait_for_function(f"{JS_STATUS_TEXT}.includes('not current')", timeout=STEP_TIMEOUT)
    stale = page.evaluate(JS_STATUS_TEXT)
    assert "localized" not in stale and "not current" in stale, stale
    assert "#5be35b" not in v.controls.status.content  # the green of "localized"
    shown = page.evaluate(JS_SCAN)
    failing.clear()
    page.wait_for_function(f"{JS_SCAN} > {shown} && !{JS_STATUS_TEXT}.includes('not current')", timeout=STEP_TIMEOUT)
    page.close()


@pytest.fixture
def paused(cache_root):
    """A run that waits for Play in the page (60 scans)."""
    loc = browser_localizer(cache_root, n_scans=60)
    with serving(loc, autoplay=False, speed="10") as handle:
        yield handle


# every 100 ms, the status's line of the achieved rate (window.__rates)
JS_RECORD_RATES = """window.__rates = [];
setInterval(() => { const m = document.body.innerText.match(/achieved ([\\d.]+) scans\\/s/);
                    const s = document.body.innerText.match(/Scan (\\d+) of/);
                    if (m && s) window.__rates.push([+s[1], +m[1]]); }, 100);"""


def test_slow_scans_show_the_rate_they_advance_at(browser, paused, monkeypatch):
    """Each scan takes 4.5 s, longer than the rate's window (a replay that waits for S2M on a
    loaded machine): the status says the rate the scans advance at, never 0."""
    loc = paused.localizer
    step = loc.step

    def slow_step(deadline=None):
        threading.Event().wait(4.5)  # a slow block, as a loaded machine's S2M
        return step(deadline)

    monkeypatch.setattr(loc, "step", slow_step)
    page = open_viewer(browser, paused.url, PAUSED_READY)
    page.evaluate(JS_RECORD_RATES)
    page.get_by_role("button", name="Play").click()
    page.wait_for_function(f"{JS_SCAN} >= 4", timeout=STEP_TIMEOUT)
    rates = page.evaluate("window.__rates")
    assert rates, "no rate shown while playing"
    zero = [r for r in rates if r[1] == 0.0]
    assert not zero, f"the status said 0 scans/s while the scans advanced: {rates}"
    assert all(0.1 <= r <= 0.3 for _, r in rates), rates  # about one scan per 4.5 s
    page.close()


def test_replay_waiting_for_s2m_says_why_and_offers_the_realtime_clock(browser, paused):
    v, loc = paused.viewer, paused.localizer
    gate = threading.Event()  # every match waits here until the test opens it
    for name in ("match_local", "match_global"):
        real = getattr(loc.s2m.matcher, name, None)
        if real is None:  # a matcher without that kind of match
            continue
        setattr(loc.s2m.matcher, name, lambda *a, _real=real, **k: (gate.wait(120), _real(*a, **k))[1])
    try:
        page = open_viewer(browser, paused.url, PAUSED_READY)
        page.get_by_role("button", name="Play").click()
        page.wait_for_function("document.body.innerText.includes('waiting for the S2M match')", timeout=STEP_TIMEOUT)
        # why it waits, and what the other clock costs
        page.wait_for_function(
            "document.body.innerText.includes('The replay clock waits for every S2M match')", timeout=STEP_TIMEOUT
        )
        text = page.evaluate("document.body.innerText")
        assert "repeat exactly" in text and "depend on the machine's load" in text, text
        # one click to the real-time clock: the click does not hang on the step waiting for its
        # match; the page says when the clock takes over, and the note goes
        page.get_by_role("button", name="Switch to the real-time clock (do not wait for S2M)").click()
        page.wait_for_function(
            "document.body.innerText.includes('clock: realtime once the scan in progress has its S2M match')",
            timeout=STEP_TIMEOUT,
        )
        page.wait_for_function(
            "!document.body.innerText.includes('The replay clock waits for every S2M match')",
            timeout=STEP_TIMEOUT,
        )
        assert v.controls.clock.value == "realtime"
        gate.set()
        wait_for(lambda: v.player.clock == "realtime", what="the real-time clock")
        assert loc.cfg.localize.clock == "realtime"  # the localizer lands S2M as it finishes
        page.wait_for_function("document.body.innerText.includes('(realtime)')", timeout=STEP_TIMEOUT)
        page.close()
    finally:
        gate.set()


def test_the_camera_follows_by_default_and_answers_while_the_display_is_busy(browser, paused, monkeypatch):
    v = paused.viewer
    page = open_viewer(browser, paused.url, PAUSED_READY)
    clients = v.server.get_clients()
    tab = v.cameras._tabs[max(clients)]
    assert tab.follow.value is True  # a new tab follows the vehicle
    # the camera goes along as the scans play: 5 scans at 8 m/s, 10 Hz are 4 m
    v.step_once()
    page.wait_for_function(f"{JS_SCAN} >= 0", timeout=STEP_TIMEOUT)
    wait_for(lambda: v.player.idle and v.drawn is not None and v.drawn.scan_index == 0, what="scan 0 drawn")
    before = page.evaluate(JS_CAMERA)
    for _ in range(5):
        v.step_once()
        wait_for(lambda: v.player.idle, what="a step")
    page.wait_for_function(f"{JS_SCAN} >= 5", timeout=STEP_TIMEOUT)
    page.wait_for_function(camera_moved_by(before, 3.0), timeout=STEP_TIMEOUT)

    # a display update that takes long (a loaded machine): the tab's camera buttons still answer
    hold, holding = threading.Event(), threading.Event()
    draw = v.scene.draw

    def held_draw(*args, **kwargs):
        holding.set()
        hold.wait(STEP_TIMEOUT / 1000)
        return draw(*args, **kwargs)

    monkeypatch.setattr(v.scene, "draw", held_draw)
    try:
        v.step_once()
        assert holding.wait(STEP_TIMEOUT / 1000), "the display did not draw the step"
        before = page.evaluate(JS_CAMERA)
        page.get_by_role("button", name="Top-down view").click()
        page.wait_for_function(camera_moved_by(before, 30.0), timeout=STEP_TIMEOUT)
        assert not hold.is_set()  # answered while the display update was still held
    finally:
        hold.set()
    # the vehicle's next scans keep the view straight down (a follow step from the camera the tab
    # reported before the click would put the old view back); in the page, y is up
    for _ in range(3):
        v.step_once()
        wait_for(lambda: v.player.idle, what="a step")
    page.wait_for_function(f"{JS_SCAN} >= 9", timeout=STEP_TIMEOUT)
    assert page.evaluate("window.__viserMutable.camera.position.y") > 100
    page.close()
