"""Headless Chromium clients of the viewer, as the soak and the many-clients benchmark open them.

Debian's Chromium through Playwright; WebGL is software-rendered (no GPU), so a tab costs CPU of
its own: on a 2-core machine the clients compete with the viewer they measure."""

from __future__ import annotations

CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--headless",
]
