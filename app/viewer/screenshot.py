"""The README's picture of the viewer, taken from the viewer as it is now:
``python -m lidarloc.app.viewer.screenshot [OUT.png]`` (default ``assets/viewer.png``).

It plays the short town (the default town's first scans, mapped from a short drive) in the live
viewer until the filter is localized (or the scans run out), opens one tab in Debian's headless
Chromium (``/usr/bin/chromium``, through Playwright, as the browser tests do), waits for the
status to say so, and saves the whole page at 1400 × 900. The picture is made by the viewer's
own code each time, so it shows its status, panel and colours as they are.
"""

from __future__ import annotations

import contextlib
import shutil
import sys
import tempfile
import time
from pathlib import Path

SIZE = {"width": 1400, "height": 900}
SCANS = 120  # the drive played: long enough to localize and draw a trajectory
MAPPING_SCANS = 150  # the drive the map is fused from (shorter than the town's: seconds to build)
TIMEOUT_MS = 300_000


def take(out: Path, cache_root: Path | None = None) -> Path:
    """Play the short town in the viewer and save the page as ``out`` (PNG)."""
    from playwright.sync_api import sync_playwright

    from ...core.config import Config
    from ...core.errors import LidarlocError
    from ...core.localizer import Localizer
    from ...core.sequences.factory import SourceSpec, open_sequence
    from ..bench.chromium import CHROMIUM, CHROMIUM_ARGS
    from .serve import serve

    if not CHROMIUM.exists():
        raise LidarlocError(f"{CHROMIUM} not found (apt-get install -y chromium)")
    cfg = Config()
    cfg.town.n_scans = MAPPING_SCANS
    spec = SourceSpec(scans=SCANS)
    seq = open_sequence(spec, cfg)
    loc = Localizer(seq, cfg, cache_root)
    # recorded (into a folder removed afterwards), so that the timeline shows the steps played
    records = Path(tempfile.mkdtemp(prefix="lidarloc-screenshot-"))
    handle = serve(loc, port=0, autoplay=True, speed="10", spec=spec, record_to=records, cache_root=cache_root)
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
            page = browser.new_page(viewport=SIZE)
            page.goto(handle.url, timeout=TIMEOUT_MS)
            page.wait_for_selector("canvas", timeout=TIMEOUT_MS)
            # localized (green), or the drive's end: the picture shows the run as it stands
            page.wait_for_function(
                "document.body.innerText.includes('localized since') || document.body.innerText.includes('finished')",
                timeout=TIMEOUT_MS,
            )
            k = loc.k
            deadline = time.monotonic() + TIMEOUT_MS / 1000
            while loc.k < min(k + 20, SCANS) and not loc.done and time.monotonic() < deadline:
                time.sleep(0.1)  # a stretch of trajectory after the localization
            handle.viewer.player.pause()
            page.wait_for_function(
                "document.body.innerText.includes('· paused') || document.body.innerText.includes('· finished')",
                timeout=TIMEOUT_MS,
            )
            # the browser's own notice about software WebGL (no GPU here) is not the viewer's
            page.add_style_tag(content=".mantine-Notifications-root { display: none !important; }")
            out.parent.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(out))
            browser.close()
    finally:
        handle.stop()
        loc.close()
        shutil.rmtree(records, ignore_errors=True)
    return out


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    out = Path(args[0]) if args else Path(__file__).resolve().parents[2] / "assets" / "viewer.png"
    with contextlib.redirect_stdout(sys.stderr):  # viser's banner
        path = take(out)
    print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
