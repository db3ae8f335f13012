"""What the real-browser tests share: headless Chromium's place and flags, the page's time
limits, and reading the scan counter from the page.

WebGL is software-rendered here (no GPU), so waits are generous; every wait polls for a
condition, none sleeps for a fixed time."""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

from lidarloc.app.bench.chromium import CHROMIUM, CHROMIUM_ARGS  # the benchmarks' browser, as users run it
from lidarloc.app.bench.viewer import JS_SCAN  # the scan counter, read from the page as the benchmark reads it

__all__ = ["ARTIFACTS", "CHROMIUM", "CHROMIUM_ARGS", "JS_SCAN", "LOAD_TIMEOUT", "STEP_TIMEOUT", "serving"]

ARTIFACTS = Path(__file__).resolve().parents[1] / "test-artifacts"
LOAD_TIMEOUT = 90_000  # ms: first load compiles the viewer's shaders in software
STEP_TIMEOUT = 60_000


@contextmanager
def serving(loc, **options):
    """The viewer serving ``loc`` on a free port (``options``: serve()'s) while the block runs;
    then its server stops and the localizer closes, whatever the test did."""
    from lidarloc.app.viewer.serve import serve

    handle = serve(loc, port=0, **options)
    try:
        yield handle
    finally:
        handle.stop()
        loc.close()
