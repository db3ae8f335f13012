"""An exported run in a real (headless) Chromium, opened from file:// with no server running:
the scene renders (a non-blank canvas), the overlay shows the step's figures, playback advances,
and the player's time slider scrubs to the step asked for. Screenshots go to test-artifacts/.

WebGL is software-rendered here (no GPU), so waits are generous; every wait polls a condition."""

from __future__ import annotations

import io
import re
from pathlib import Path

import numpy as np
import pytest
from browser import ARTIFACTS, LOAD_TIMEOUT
from helpers import record_run, wait_for
from rich.console import Console

# ~30 s (software WebGL): the slow lane
pytestmark = [pytest.mark.browser, pytest.mark.slow]

SCANS = 14
JS_HUD = "(() => { const d = document.getElementById('lidarloc-hud'); return d ? d.innerText : ''; })()"


@pytest.fixture(scope="module")
def exported(cache_root, tmp_path_factory):
    from lidarloc.app.export import export_run

    root = tmp_path_factory.mktemp("export-browser")
    record_run(root / "run", cache_root, scans=SCANS)
    return export_run(root / "run", root / "shared", console=Console(file=io.StringIO()), cache_root=cache_root)


def canvas_stats(png: bytes) -> tuple[int, float]:
    """(distinct colours, fraction of pixels unlike the most common one = the background)."""
    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).reshape(-1, 3)
    packed = (img[:, 0].astype(np.int64) << 16) | (img[:, 1].astype(np.int64) << 8) | img[:, 2]
    values, counts = np.unique(packed, return_counts=True)
    return len(values), 1.0 - counts.max() / len(packed)


def hud_step(page) -> int:
    m = re.search(r"\(step (\d+) of (\d+)\)", page.evaluate(JS_HUD))
    return int(m.group(1)) if m else -1


def test_the_exported_folder_plays_from_file_with_no_server(browser, exported):
    page = browser.new_page(viewport={"width": 1100, "height": 750})
    requests: list[str] = []
    page.on("request", lambda r: requests.append(r.url))
    try:
        page.goto(Path(exported["page"]).resolve().as_uri())
        page.wait_for_selector("canvas", timeout=LOAD_TIMEOUT)
        assert page.title().startswith("lidarloc · ")
        page.wait_for_function(f"() => /step \\d+ of {SCANS}/.test({JS_HUD})", timeout=LOAD_TIMEOUT)
        assert re.search(
            r"scan \d+ \(step \d+ of 14\) · (not )?localized\nstd \d+\.\d\d m · error \d+\.\d\d m · "
            r"N_eff \d+\.\d % of \d+",
            page.evaluate(JS_HUD),
        )
        # the scene renders: many colours, most of the canvas not background
        canvas = page.locator("canvas").first
        shots = {}

        def drawn():
            shots["png"] = canvas.screenshot()
            colours, share = canvas_stats(shots["png"])
            return colours > 200 and share > 0.15

        wait_for(drawn, timeout=LOAD_TIMEOUT / 1000, what="the exported scene on the canvas")
        ARTIFACTS.mkdir(exist_ok=True)
        (ARTIFACTS / "export_file_url.png").write_bytes(shots["png"])
        # playback runs by itself (and loops): the overlay's step changes
        first = hud_step(page)
        wait_for(lambda: hud_step(page) not in (-1, first), timeout=60, what="playback to advance")
        # the time slider scrubs: a click pauses, a second one lands on the step at that time
        bar = page.locator(".mantine-Slider-root").first
        box = bar.bounding_box()
        for frac in (0.9, 0.5):
            target = round(frac * SCANS)  # the step shown at time frac × duration (± one at the edge)
            page.mouse.click(box["x"] + frac * box["width"], box["y"] + box["height"] / 2)
            page.mouse.click(box["x"] + frac * box["width"], box["y"] + box["height"] / 2)
            wait_for(lambda: abs(hud_step(page) - target) <= 1, timeout=30, what=f"the step at {frac:.0%}")
        page.screenshot(path=str(ARTIFACTS / "export_scrubbed.png"))
        # everything came from the folder itself: no server, no network
        assert requests and all(u.startswith(("file:", "data:", "blob:")) for u in requests), requests
    finally:
        page.close()
    print(
        f"\n.viser {exported['viser_bytes'] / 1e6:.2f} MB, folder {exported['folder_bytes'] / 1e6:.2f} MB "
        f"for {exported['steps']} steps"
    )
