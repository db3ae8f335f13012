"""What the real-browser tests share: headless Chromium's place and flags, the page's time
limits, and reading the scan counter from the page.

WebGL is software-rendered here (no GPU), so waits are generous; every wait polls for a
condition, none sleeps for a fixed time."""

from __future__ import annotations

from pathlib import Path

from lidarloc.app.bench.clients import CHROMIUM, CHROMIUM_ARGS  # the benchmarks' browser, as users run it

__all__ = ["ARTIFACTS", "CHROMIUM", "CHROMIUM_ARGS", "JS_SCAN", "LOAD_TIMEOUT", "STEP_TIMEOUT"]

ARTIFACTS = Path(__file__).resolve().parents[1] / "test-artifacts"
LOAD_TIMEOUT = 90_000  # ms: first load compiles the viewer's shaders in software
STEP_TIMEOUT = 60_000

JS_SCAN = "(() => { const m = document.body.innerText.match(/Scan (\\d+) of \\d+/); return m ? +m[1] : -1; })()"
