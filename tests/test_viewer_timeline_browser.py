"""``lidarloc view --run`` in a real (headless) Chromium: a recorded run is served, the timeline
slider moved in the page shows the chosen scan (the status's scan counter says so) and the scene
changes with it. Screenshots go to test-artifacts/.

WebGL is software-rendered here (no GPU), so waits are generous; every wait polls for a
condition, none sleeps for a fixed time."""

from __future__ import annotations

import io

import numpy as np
import pytest
from browser import ARTIFACTS, JS_SCAN, LOAD_TIMEOUT, STEP_TIMEOUT
from helpers import MAPPING_SCANS, wait_for

pytestmark = [pytest.mark.browser, pytest.mark.slow]

SCANS = 20


@pytest.fixture(scope="module")
def recorded_run(cache_root, tmp_path_factory):
    """A finished 20-scan run of the short town, recorded as ``lidarloc run`` records."""
    from lidarloc.app.bench.common import record_run
    from lidarloc.core.config import Config
    from lidarloc.core.sequences.factory import SourceSpec, open_sequence

    cfg = Config()
    cfg.town.n_scans = MAPPING_SCANS
    cfg.pf.n_particles = 500
    spec = SourceSpec(scans=SCANS)
    return record_run(spec, open_sequence(spec, cfg), cfg, tmp_path_factory.mktemp("browser-run"), cache_root)


@pytest.fixture(scope="module")
def served_run(recorded_run, cache_root):
    from lidarloc.app.viewer.runs import open_runs

    handle = open_runs([recorded_run], port=0, cache_root=cache_root)
    yield handle
    handle.stop()


def pixels(png: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int16)


def test_moving_the_slider_shows_the_chosen_scan(browser, served_run):
    ARTIFACTS.mkdir(exist_ok=True)
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    try:
        page.goto(served_run.url, timeout=LOAD_TIMEOUT)
        page.wait_for_selector("canvas", timeout=LOAD_TIMEOUT)
        page.wait_for_function(f"{JS_SCAN} == 0", timeout=LOAD_TIMEOUT)
        canvas = page.locator("canvas").first
        # the scene has drawn scan 0's particles: wait until two screenshots agree
        shots = [pixels(canvas.screenshot(timeout=LOAD_TIMEOUT))]

        def settled() -> bool:
            shots.append(pixels(canvas.screenshot(timeout=LOAD_TIMEOUT)))
            return np.array_equal(shots[-1], shots[-2])

        wait_for(settled, timeout=LOAD_TIMEOUT / 1000, what="the first scene to settle")
        before = shots[-1]
        page.screenshot(path=str(ARTIFACTS / "timeline-scan-0.png"))
        # the timeline's slider (its thumb has role=slider): to its end with the keyboard
        thumb = page.locator(f"[role=slider][aria-valuemax='{SCANS - 1}']").first
        thumb.focus(timeout=LOAD_TIMEOUT)
        thumb.press("End")
        page.wait_for_function(f"{JS_SCAN} == {SCANS - 1}", timeout=STEP_TIMEOUT)
        tl = served_run.viewer.travel.timeline
        assert tl.step == SCANS - 1
        # and back by three with the arrow keys: each press is a move
        for _ in range(3):
            thumb.press("ArrowLeft")
        page.wait_for_function(f"{JS_SCAN} == {SCANS - 4}", timeout=STEP_TIMEOUT)
        assert page.evaluate("document.body.innerText").count(f"Scan {SCANS - 4}") >= 2  # status and timeline

        def changed() -> bool:
            diff = np.abs(pixels(canvas.screenshot(timeout=LOAD_TIMEOUT)) - before).max(axis=2)
            return int((diff > 40).sum()) > 500

        wait_for(changed, timeout=STEP_TIMEOUT / 1000, what="the scene to show the chosen scan")
        page.screenshot(path=str(ARTIFACTS / f"timeline-scan-{SCANS - 4}.png"))
    finally:
        page.close()
