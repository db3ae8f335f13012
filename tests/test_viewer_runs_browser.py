"""``lidarloc view --run A --run B`` of two runs of unequal lengths, in a real (headless) Chromium:
the timeline reaches the longer run's last step, the shorter one says where it ended, and a step
past the end is refused instead of landing somewhere else.

WebGL is software-rendered here (no GPU), so waits are generous; every wait polls for a
condition, none sleeps for a fixed time."""

from __future__ import annotations

import numpy as np
import pytest
from browser import LOAD_TIMEOUT, STEP_TIMEOUT
from helpers import MAPPING_SCANS
from lidarloc.core.errors import LidarlocError

pytestmark = [pytest.mark.browser, pytest.mark.slow]

SCANS, SHORT = 20, 8


@pytest.fixture(scope="module")
def two_runs(cache_root, tmp_path_factory):
    """Two recorded runs of the short town's first 20 scans: one to the end, one stopped after
    8 scans (as a run stopped with Ctrl-C is recorded): (short, long)."""
    from lidarloc.app.bench.common import record_run
    from lidarloc.core.config import Config
    from lidarloc.core.localizer import Localizer
    from lidarloc.core.runs import recording
    from lidarloc.core.sequences.factory import SourceSpec, open_sequence

    cfg = Config()
    cfg.town.n_scans = MAPPING_SCANS
    cfg.pf.n_particles = 300
    spec = SourceSpec(scans=SCANS)
    long = record_run(spec, open_sequence(spec, cfg), cfg, tmp_path_factory.mktemp("long-run"), cache_root)
    short = tmp_path_factory.mktemp("short-run")
    seq = open_sequence(spec, cfg)
    loc = Localizer(seq, cfg, cache_root)
    try:
        writer = recording.RecordingWriter(short, spec, cfg, seq)
        for _ in range(SHORT):
            writer.on_scan(loc, loc.step())
        writer.close(None)
    finally:
        loc.close()
    return short, long


@pytest.fixture(scope="module")
def served_runs(two_runs, cache_root):
    from lidarloc.app.viewer.runs import open_runs

    handle = open_runs(list(two_runs), port=0, cache_root=cache_root)
    yield handle
    handle.stop()


def test_the_timeline_reaches_the_longer_runs_last_step(browser, served_runs, two_runs):
    from lidarloc.core.runs import recording

    w = served_runs.viewer
    tl = w.travel.timeline
    long = recording.open(two_runs[1])
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    try:
        page.goto(served_runs.url, timeout=LOAD_TIMEOUT)
        page.wait_for_selector("canvas", timeout=LOAD_TIMEOUT)
        # the slider ends at the longer run's last step (it ended at the shorter one's)
        thumb = page.locator(f"[role=slider][aria-valuemax='{SCANS - 1}']").first
        thumb.focus(timeout=LOAD_TIMEOUT)
        thumb.press("End")
        page.wait_for_function(
            f"document.body.innerText.includes('step {SCANS - 1} of 0…{SCANS - 1}')", timeout=STEP_TIMEOUT
        )
        assert tl.step == SCANS - 1
        # the status and the timeline say that the first run ended, and where
        page.wait_for_function(
            f"document.body.innerText.includes('this run ended at step {SHORT - 1}')", timeout=STEP_TIMEOUT
        )
        # the blue run is drawn at that step, the first run at its last one
        w.update_display()
        ref = w.travel.reference_node("particles")
        np.testing.assert_allclose(ref.points, long.particles(SCANS - 1)[:, :3], atol=1e-5)
        assert w.drawn is not None and w.drawn.scan_index == SHORT - 1
        # the Compare table names its rows in words a user reads (what A counts, not "(sum)")
        page.wait_for_function(
            "document.body.innerText.includes('A: scans spent not localized (every try)')", timeout=STEP_TIMEOUT
        )
        assert "(sum)" not in page.evaluate("document.body.innerText")
        # a step past the end is refused, not moved somewhere else
        with pytest.raises(LidarlocError, match="past the end"):
            tl.go(SCANS + 5)
        assert tl.step == SCANS - 1
    finally:
        page.close()
