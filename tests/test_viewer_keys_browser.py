"""Keyboard shortcuts in a real (headless) Chromium: space plays and pauses, → steps one scan
(or one recorded step while the timeline shows one), ← goes one recorded step back, keys typed
into a number field do nothing of the sort, and the arrows do not turn the camera.

WebGL is software-rendered here (no GPU), so waits are generous; every wait polls for a
condition, none sleeps for a fixed time."""

from __future__ import annotations

import numpy as np
import pytest
from browser import JS_SCAN, LOAD_TIMEOUT
from helpers import MAPPING_SCANS, wait_for

pytestmark = [pytest.mark.browser, pytest.mark.slow]

WAIT_S = 60


@pytest.fixture(scope="module")
def served(cache_root, tmp_path_factory):
    """A paused viewer on the short town that records what it plays (the timeline needs it)."""
    from lidarloc.app.viewer.serve import serve
    from lidarloc.core.config import Config
    from lidarloc.core.localizer import Localizer
    from lidarloc.core.sequences.factory import SourceSpec, open_sequence

    cfg = Config()
    cfg.town.n_scans = MAPPING_SCANS
    cfg.pf.n_particles = 300
    spec = SourceSpec(scans=40)
    loc = Localizer(open_sequence(spec, cfg), cfg, cache_root)
    handle = serve(
        loc,
        port=0,
        autoplay=False,
        speed="5",
        record_to=tmp_path_factory.mktemp("keys-runs"),
        spec=spec,
        cache_root=cache_root,
    )
    yield handle
    handle.stop()
    loc.close()


def test_space_and_arrows_drive_playback_and_the_timeline(browser, served):
    v, loc = served.viewer, served.localizer
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    page.goto(served.url, timeout=LOAD_TIMEOUT)
    page.wait_for_selector("canvas", timeout=LOAD_TIMEOUT)
    page.wait_for_function(f"{JS_SCAN} >= -1 && document.body.innerText.includes('Scan ')", timeout=LOAD_TIMEOUT)
    wait_for(lambda: len(served.server.get_clients()) == 1, WAIT_S, "the tab's connection")
    # → while live and paused: one more scan
    page.keyboard.press("ArrowRight")
    wait_for(lambda: loc.k == 1 and v.player.idle, WAIT_S, "one scan stepped by →")
    # (one press at a time: the page merges quick presses of one button into one message)
    page.keyboard.press("ArrowRight")
    wait_for(lambda: loc.k == 2 and v.player.idle, WAIT_S, "another scan")
    page.keyboard.press("ArrowRight")
    wait_for(lambda: loc.k == 3 and v.player.idle and v.travel.recorder.n == 3, WAIT_S, "a third scan")
    # space: play, space again: pause
    page.keyboard.press("Space")
    wait_for(lambda: v.player.playing, WAIT_S, "playing after space")
    wait_for(lambda: loc.k >= 5, WAIT_S, "scans played")
    page.keyboard.press("Space")
    wait_for(lambda: not v.player.playing and v.player.idle, WAIT_S, "paused after space")
    # ← one recorded step back (the timeline shows it), → forward again; the camera stays put
    tl = v.travel.timeline
    wait_for(lambda: v.travel.recorder.n == loc.steps and tl.n == loc.steps, WAIT_S, "every step on the timeline")
    newest = tl.current()
    camera = next(iter(served.server.get_clients().values())).camera
    wxyz = np.asarray(camera.wxyz)
    page.keyboard.press("ArrowLeft")
    wait_for(lambda: tl.step == newest - 1, WAIT_S, "one recorded step back after ←")
    page.keyboard.press("ArrowLeft")
    wait_for(lambda: tl.step == newest - 2, WAIT_S, "two back")
    page.keyboard.press("ArrowRight")
    wait_for(lambda: tl.step == newest - 1, WAIT_S, "one forward after →")
    # the same rotation (q and −q are one: the camera following the vehicle may flip the sign)
    q = np.asarray(camera.wxyz)
    assert min(np.abs(q - wxyz).max(), np.abs(q + wxyz).max()) < 1e-6, (q, wxyz)
    k = loc.k
    assert not v.player.playing and loc.k == k  # → on the timeline moves it, it processes nothing
    # typing into a number field is typing: no shortcut fires (had ← gone through, the → after it
    # would land one step short)
    seed = page.get_by_label("Seed")
    seed.click()
    seed.press("ArrowLeft")
    seed.press(" ")
    page.evaluate("document.activeElement.blur()")
    page.keyboard.press("ArrowRight")
    wait_for(lambda: tl.step == newest, WAIT_S, "forward to the newest recorded step")
    assert not v.player.playing
    page.close()
