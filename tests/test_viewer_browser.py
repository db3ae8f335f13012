"""The viewer (app/viewer/) in a real (headless) Chromium: the page loads, the 3D canvas draws
something, the Pause and Step buttons do what they say, the Reset button, a shift+click and a
shift+drag on the scene reset the particles, and a second tab sees the same run. Screenshots go
to test-artifacts/.

WebGL is software-rendered here (no GPU), so waits are generous; every wait polls for a
condition, none sleeps for a fixed time."""

from __future__ import annotations

import re

import numpy as np
import pytest
from browser import ARTIFACTS, JS_SCAN, LOAD_TIMEOUT, STEP_TIMEOUT, serving
from helpers import browser_localizer, wait_for

# ~40 s (software WebGL): the slow lane
pytestmark = [pytest.mark.browser, pytest.mark.slow]


@pytest.fixture(scope="module")
def served(cache_root):
    # 2 scans/s: slow enough that the test sees the counter move, pauses it mid-run and steps;
    # 300 scans (150 s at least): its Pause comes after a page load, two scans and a screenshot of
    # the canvas, and on a quiet machine a shorter run had ended by then (the button said Play).
    # The street's map is the session cache's, built once for the browser tests' 300-scan runs.
    loc = browser_localizer(cache_root, n_scans=300)
    with serving(loc, autoplay=True, speed="2") as handle:
        yield handle


@pytest.fixture
def playing(cache_root):
    """A run already playing before any tab is open (the usual case: start the demo, then open
    the page). 300 scans, at least 60 s at 5 scans/s: its test pauses it after a page load,
    twenty-odd scans of plots and a notification, well before the end (a Pause that lands after
    the last scan shows "finished", not "paused"; 150 scans had ended by then on a busy page).
    The run stops with the test, so a long one costs nothing."""
    loc = browser_localizer(cache_root, n_scans=300)
    with serving(loc, autoplay=True, speed="5") as handle:
        yield handle


# each plot's chart in the page (viser registers them for tests): points, x range, newest x
JS_PLOTS = """(() => Object.values((window.__viserTestpoints || {}).uplots || {}).map(t => {
    const x = t.chart.data[0];
    return {n: x.length, last: x[x.length - 1], min: t.chart.scales.x.min, max: t.chart.scales.x.max};
}))()"""


# each plot as drawn: its chart's width and height (px) and the legend entries it shows
JS_PLOT_BOXES = """[...document.querySelectorAll('.uplot')].map(u => {
    const r = u.querySelector('.u-wrap').getBoundingClientRect();
    const shown = [...u.querySelectorAll('.u-legend .u-series')].filter(e => getComputedStyle(e).display !== 'none');
    return {width: r.width, height: r.height, legend: shown.map(e => e.innerText.trim())};
})"""


# every press, release and click the page receives: the element's tag, text and whether it was disabled, and the
# element actually under the pointer (what a click lost to an overlay or a re-render would show)
JS_RECORD_CLICKS = """window.__clicks = [];
for (const kind of ['mousedown', 'mouseup', 'click']) document.addEventListener(kind, e => {
    const b = e.target.closest('button');
    const under = document.elementFromPoint(e.clientX, e.clientY);
    window.__clicks.push({kind, target: b ? b.innerText : e.target.tagName, disabled: b ? b.disabled : null,
                          under: under ? under.tagName + ':' + (under.innerText || '').slice(0, 30) : null});
}, true);"""


def watch_clicks(page, button) -> list:
    """Record the page's presses, releases and clicks from now on (``window.__clicks``); the
    returned list gets an entry each time the server runs ``button``'s callbacks."""
    page.evaluate(JS_RECORD_CLICKS)
    on_server: list[int] = []
    button.on_click(lambda _: on_server.append(1))
    return on_server


def press_and_wait(page, viewer, label: str, text: str, timeout_ms: float) -> None:
    """Press the Play/Pause button labelled ``label`` and wait for ``text`` in the page; if it
    does not come, say where the press went (the page's clicks, the server's callbacks) and
    where the run is."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    loc = viewer.localizer
    clicks = watch_clicks(page, viewer.controls.play)
    page.get_by_role("button", name=label).click()
    try:
        page.wait_for_function(f"document.body.innerText.includes({text!r})", timeout=timeout_ms)
    except PlaywrightTimeout as exc:
        raise AssertionError(
            f"{exc}; on the server: scan {loc.k} of {loc.n_scans}, done {loc.done}, playing "
            f"{viewer.player.playing}, {len(clicks)} {label} click(s), message {viewer.message!r}; "
            f"the page's clicks: {page.evaluate('window.__clicks')!r}"
        ) from None


def scan_counter(page) -> int:
    return page.evaluate(JS_SCAN)


def canvas_stats(png: bytes) -> tuple[int, float]:
    """(distinct colours, fraction of pixels unlike the most common one = the background)."""
    import io

    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).reshape(-1, 3)
    packed = (img[:, 0].astype(np.int64) << 16) | (img[:, 1].astype(np.int64) << 8) | img[:, 2]
    values, counts = np.unique(packed, return_counts=True)
    return len(values), 1.0 - counts.max() / len(packed)


def particle_pixels(png: bytes) -> int:
    """Pixels in the particles' reds (strong red, little green and blue: not the map's blues and
    whites, the scan's green or the S2M match's magenta)."""
    import io

    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int32)
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return int(((r > 100) & (r > 2 * g) & (r > 2 * b)).sum())


def magenta_pixels(png: bytes) -> int:
    """Pixels in the accepted S2M match's magenta (strong red and blue, little green)."""
    import io

    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int32)
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return int(((r > 170) & (b > 170) & (g < 120)).sum())


def scene_screenshot(page, canvas) -> bytes:
    """The canvas left of the panel, which floats over it (its overview draws particles too)."""
    box = canvas.bounding_box()
    panel_left = page.get_by_role("button", name="Reset globally").bounding_box()["x"] - 20
    clip = {"x": box["x"], "y": box["y"], "width": min(box["width"], panel_left - box["x"]), "height": box["height"]}
    return page.screenshot(clip=clip, timeout=LOAD_TIMEOUT)


def open_viewer(browser, url):
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    page.goto(url, timeout=LOAD_TIMEOUT)
    page.wait_for_selector("canvas", timeout=LOAD_TIMEOUT)
    page.wait_for_function(f"{JS_SCAN} >= 0", timeout=LOAD_TIMEOUT)
    return page


def test_tab_opened_while_playing_gets_the_history_and_live_plots(browser, playing):
    ARTIFACTS.mkdir(exist_ok=True)
    loc = playing.localizer
    wait_for(lambda: loc.k >= 8, what="playback before the tab opens")
    page = open_viewer(browser, playing.url)
    n_plots = len(playing.viewer.controls.plots.handles)
    page.wait_for_function(
        f"{JS_PLOTS}.length === {n_plots} && {JS_PLOTS}.every(p => p.n >= 8)", polling=250, timeout=STEP_TIMEOUT
    )
    first = page.evaluate(JS_PLOTS)
    # live updates: every chart grows, and the newest scan stays inside its x range (the whole run)
    page.wait_for_function(
        f"{JS_PLOTS}.every(p => p.n >= {max(p['n'] for p in first) + 6})", polling=250, timeout=STEP_TIMEOUT
    )
    for p in page.evaluate(JS_PLOTS):
        assert p["min"] == 0 and p["max"] == loc.n_scans - 1, p
        assert p["min"] <= p["last"] <= p["max"], p
    # the plots are nearly as tall as wide, each legend names its curves only (three at most),
    # and the dots every plot shares are named once, above them
    boxes = page.evaluate(JS_PLOT_BOXES)
    assert len(boxes) == n_plots, boxes
    for box in boxes:
        assert box["height"] >= 0.8 * box["width"] > 200, box
        assert 1 <= len(box["legend"]) <= 3 and not any("timeline" in e for e in box["legend"]), box
    assert page.get_by_text("Dots on the curves:").count() == 1

    # a message answers the tab that acted where it looks: a notification
    page.get_by_role("button", name="Reset globally").click()
    toast = page.locator(".mantine-Notification-root", has_text="particles reset globally")
    toast.first.wait_for(timeout=STEP_TIMEOUT)

    # the legend and the plots, for the eye
    viewer = playing.viewer
    assert not loc.done, f"the run finished (scan {loc.k} of {loc.n_scans}) before the test could pause it"
    press_and_wait(page, viewer, "Pause", "· paused", STEP_TIMEOUT)
    assert page.get_by_text("particles by log-weight rank").count() == 1
    page.get_by_text("particles by log-weight rank").scroll_into_view_if_needed()
    page.screenshot(path=str(ARTIFACTS / "viewer-legend.png"))
    page.locator(".uplot-container").last.scroll_into_view_if_needed()
    page.screenshot(path=str(ARTIFACTS / "viewer-plots.png"))
    page.close()


def test_viewer_in_chromium(browser, served):
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    ARTIFACTS.mkdir(exist_ok=True)
    page = open_viewer(browser, served.url)

    # playing: the counter moves by itself
    start = scan_counter(page)
    page.wait_for_function(f"{JS_SCAN} >= {start + 2}", timeout=STEP_TIMEOUT)

    # the canvas is drawn: many colours, and a good share of pixels that are not background
    canvas = page.locator("canvas").first
    page.wait_for_function(
        "(() => { const t = document.body.innerText; return t.includes('Scan') })()", timeout=STEP_TIMEOUT
    )
    colours, foreground = canvas_stats(canvas.screenshot(timeout=LOAD_TIMEOUT))
    assert colours > 50 and foreground > 0.02, (colours, foreground)

    # Pause: the status says paused and the counter stays put
    page.get_by_role("button", name="Pause").click()
    page.wait_for_function("document.body.innerText.includes('· paused')", timeout=STEP_TIMEOUT)
    paused_at = scan_counter(page)
    assert served.localizer.k == paused_at + 1
    with pytest.raises(PlaywrightTimeout):
        page.wait_for_function(f"{JS_SCAN} !== {paused_at}", timeout=2_500)

    # Step: exactly one more scan, then paused again
    page.get_by_role("button", name="Step").click()
    page.wait_for_function(f"{JS_SCAN} === {paused_at + 1}", timeout=STEP_TIMEOUT)
    page.wait_for_function("document.body.innerText.includes('· paused')", timeout=STEP_TIMEOUT)
    with pytest.raises(PlaywrightTimeout):
        page.wait_for_function(f"{JS_SCAN} !== {paused_at + 1}", timeout=2_500)
    assert served.localizer.k == paused_at + 2

    # Reset globally: the particles spread over the whole map at once, while paused. The page
    # with them drawn over the map is the README's picture (without the notifications).
    page.get_by_role("button", name="Reset globally").click()
    page.wait_for_function("document.body.innerText.includes('particles reset globally')", timeout=STEP_TIMEOUT)
    for close in page.locator(".mantine-Notification-closeButton").all():
        try:
            close.click(timeout=5_000)
        except PlaywrightTimeout:  # it closed by itself meanwhile
            pass
    wait_for(
        lambda: particle_pixels(scene_screenshot(page, canvas)) > 5_000,
        timeout=STEP_TIMEOUT / 1000,
        what="the re-drawn particles on the canvas",
    )
    page.screenshot(path=str(ARTIFACTS / "viewer.png"), full_page=True)

    # shift+click on the scene: particles reset around the clicked ground point
    box = canvas.bounding_box()
    cx, cy = box["x"] + box["width"] * 0.4, box["y"] + box["height"] * 0.55
    page.keyboard.down("Shift")
    page.mouse.click(cx, cy)
    page.keyboard.up("Shift")
    page.wait_for_function("document.body.innerText.includes('particles reset around')", timeout=STEP_TIMEOUT)

    # shift+drag: particles reset inside the rectangle
    page.keyboard.down("Shift")
    page.mouse.move(cx - 60, cy - 40)
    page.mouse.down()
    page.mouse.move(cx, cy, steps=5)
    page.mouse.move(cx + 60, cy + 40, steps=5)
    page.mouse.up()
    page.keyboard.up("Shift")
    page.wait_for_function("document.body.innerText.includes('particles reset in x')", timeout=STEP_TIMEOUT)
    text = page.evaluate("document.body.innerText")
    x0, x1, y0, y1 = map(float, re.search(r"reset in x (-?\d+)…(-?\d+), y (-?\d+)…(-?\d+)", text).groups())
    P = served.localizer.pf.states  # reset() re-draws the particles; snapshots show them from the next scan
    assert (P[:, 0] >= x0 - 1).all() and (P[:, 0] <= x1 + 1).all()
    assert (P[:, 1] >= y0 - 1).all() and (P[:, 1] <= y1 + 1).all()
    assert served.viewer.scene.node("reset_area").visible  # the reset area is outlined until the next scan
    page.get_by_role("button", name="Step").click()
    page.wait_for_function(f"{JS_SCAN} === {paused_at + 2}", timeout=STEP_TIMEOUT)
    page.screenshot(path=str(ARTIFACTS / "viewer-after-rect-reset.png"))
    paused_at += 1

    # a second tab: same run, same counter, its own camera folder
    page2 = open_viewer(browser, served.url)
    page2.wait_for_function(f"{JS_SCAN} === {paused_at + 1}", timeout=STEP_TIMEOUT)
    assert page2.get_by_text("Follow the vehicle").count() == 1
    page2.get_by_role("button", name="Step").click()
    for p in (page, page2):
        p.wait_for_function(f"{JS_SCAN} === {paused_at + 2}", timeout=STEP_TIMEOUT)
    page2.screenshot(path=str(ARTIFACTS / "viewer-second-tab.png"))
    page2.close()

    # a typed invalid value is refused in the page (and the server lives on); a valid one is applied
    # Each value is seen by the server before Apply is clicked, and the server's message is
    # checked before the page's, so a failure says which side went wrong. The page waits poll on
    # a timer, not on animation frames (a software-rendered page may draw few of them).
    page.get_by_text("Parameters", exact=True).click()
    sigma = page.get_by_label("σ (m)")
    sigma_on_server = served.viewer.controls.params["sigma"]
    # where a click went, should one be lost: the page's clicks and the server's Apply callbacks
    apply_clicks = watch_clicks(page, served.viewer.controls.apply)
    reconnects: list[int] = []  # a tab reconnecting meanwhile drops what its page sends until it is back
    served.viewer.server.on_client_connect(lambda client: reconnects.append(client.client_id))
    sigma.fill("0")
    wait_for(lambda: sigma_on_server.value == 0, what="σ = 0 on the server")
    page.get_by_role("button", name="Apply 1 change").click()
    refused = "refused: invalid configuration: pf.sigma must be > 0"
    try:
        wait_for(lambda: served.viewer.message == refused, what=repr(refused))
    except AssertionError as exc:
        page.screenshot(path=str(ARTIFACTS / "viewer-apply-lost.png"))
        raise AssertionError(
            f"{exc}; the server's message is {served.viewer.message!r}, it saw {len(apply_clicks)} Apply "
            f"click(s), changed {served.viewer.params.changed()!r}; the page's clicks: "
            f"{page.evaluate('window.__clicks')!r}; tabs connected meanwhile: {reconnects}"
        ) from None
    page.wait_for_function(f"document.body.innerText.includes({refused!r})", polling=250, timeout=STEP_TIMEOUT)
    assert served.localizer.cfg.pf.sigma == 0.5
    sigma.fill("0.7")
    wait_for(lambda: sigma_on_server.value == 0.7, what="σ = 0.7 on the server")
    page.get_by_role("button", name="Apply 1 change").click()
    page.wait_for_function(
        "document.body.innerText.includes('applied from the next scan: σ (m)')", polling=250, timeout=STEP_TIMEOUT
    )
    assert served.localizer.cfg.pf.sigma == 0.7 and served.localizer.pf.sigma == 0.7
    page.close()


@pytest.fixture
def waiting(tmp_path_factory):
    """A run that waits for its first tab (the demo's default): 100 scans at 5 scans/s, 20 s at
    least, so that its Pause, pressed once the page shows a scan, lands before the end on a quiet
    machine, and short enough to be played to the end later. Its S2M process runs at the PF's
    priority, as the other browser tests' (helpers.browser_localizer): the replay clock waits for
    every match, and a niced S2M beside busy processes let the run crawl past the time its end
    is waited for."""
    from helpers import StreetSequence
    from lidarloc.core.config import Config
    from lidarloc.core.localizer import Localizer

    cfg = Config()
    cfg.pf.n_particles = 300
    cfg.s2m.replay_process_nice = 0
    loc = Localizer(StreetSequence(n=100), cfg, tmp_path_factory.mktemp("waiting-cache"))
    with serving(loc, speed="5") as handle:
        yield handle


# the status table's S2M row (a table row's cells are tab-separated in innerText; "S2M enabled",
# the checkbox's label, is not it)
JS_S2M_ROW = "(() => { const m = document.body.innerText.match(/\\nS2M\\t([^\\n]*)/); return m ? m[1] : ''; })()"


def test_what_a_new_user_trips_over_is_fixed_in_the_page(browser, waiting):
    """In a real page: playback waits for the first tab; a kidnap while paused shows at once;
    Restart takes the last run's S2M match out of the scene; the S2M row is not "running" after
    the end and says "off" when S2M is off."""

    loc, viewer = waiting.localizer, waiting.viewer
    assert waiting.wait_ready(60)
    assert not viewer.player.playing and loc.k == 0  # nobody is watching yet: not playing
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    page.goto(waiting.url, timeout=LOAD_TIMEOUT)
    page.wait_for_selector("canvas", timeout=LOAD_TIMEOUT)
    page.wait_for_function(f"{JS_SCAN} >= 1", timeout=LOAD_TIMEOUT)  # the tab started it

    # pause, then step until an accepted S2M match has landed: its scan and search area are on
    # the canvas in magenta (a rejected one would be grey)
    page.get_by_role("button", name="Pause").click()
    page.wait_for_function("document.body.innerText.includes('· paused')", timeout=STEP_TIMEOUT)
    assert viewer.player.wait_idle(STEP_TIMEOUT / 1000)
    while not (loc.snapshot().s2m is not None and loc.snapshot().s2m.accepted):
        assert loc.k < loc.n_scans - 2, "no S2M match was accepted in the run"
        before = loc.k
        viewer.step_once()
        wait_for(lambda: loc.k == before + 1 and viewer.player.idle, timeout=LOAD_TIMEOUT / 1000, what="one step")
    canvas = page.locator("canvas").first
    wait_for(
        lambda: magenta_pixels(canvas.screenshot(timeout=LOAD_TIMEOUT)) > 500,
        timeout=LOAD_TIMEOUT / 1000,
        what="the accepted S2M match on the canvas",
    )

    # kidnap while paused: the status shows it at once, without another scan
    at = scan_counter(page)
    page.get_by_role("button", name="Kidnap").click()
    page.wait_for_function("document.body.innerText.includes('kidnap')", timeout=STEP_TIMEOUT)
    assert scan_counter(page) == at

    # restart (still paused): the old run's S2M match leaves the scene
    page.get_by_role("button", name="Restart from scan 0").click()
    page.wait_for_function("document.body.innerText.includes('restarted from scan 0')", timeout=STEP_TIMEOUT)
    wait_for(
        lambda: magenta_pixels(canvas.screenshot(timeout=LOAD_TIMEOUT)) < 50,
        timeout=STEP_TIMEOUT / 1000,
        what="no S2M match on the canvas after the restart",
    )

    # to the end: the S2M row does not say "running"; switched off, it says "off"
    press_and_wait(page, viewer, "Play", "· finished", LOAD_TIMEOUT)
    assert "running" not in page.evaluate(JS_S2M_ROW)
    page.get_by_text("Parameters", exact=True).click()
    # A click (it waits for the folder to open and the box to be still), then the localizer's word.
    # Not uncheck() alone: under load its click once left the box as it was ("Clicking the
    # checkbox did not change its state"; viser sets a box's value in the page at once, so the
    # click missed it: the panel moved under the pointer between Playwright's stability check and
    # its click). A click lost that way leaves the box checked and S2M on: made once more then.
    box = page.get_by_label("S2M enabled")
    box.click(timeout=STEP_TIMEOUT)
    try:
        wait_for(lambda: not loc.cfg.s2m.enabled, timeout=15.0, what="S2M switched off in the localizer")
    except AssertionError:
        if loc.cfg.s2m.enabled and box.is_checked():
            box.click(timeout=STEP_TIMEOUT)
        wait_for(lambda: not loc.cfg.s2m.enabled, timeout=STEP_TIMEOUT / 1000, what="S2M switched off in the localizer")
    page.wait_for_function(f"{JS_S2M_ROW}.startsWith('off')", timeout=STEP_TIMEOUT)
    page.close()
