"""The headless Chromium the benchmarks and the browser tests launch: where it is, the flags it
runs with, and the CPU priority its tabs run at (``idle``: only the CPU the viewer leaves; the
websocket tabs' process of :mod:`.socket_tabs` runs at the same priorities)."""

from __future__ import annotations

import contextlib
import shutil
import tempfile
from pathlib import Path

CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--headless",
]
CHROMIUM = Path("/usr/bin/chromium")
TAB_PRIORITIES = ("idle", "normal")


def check_tab_priority(priority: str) -> None:
    """Refuse a tab priority the benchmark does not know, naming those it does."""
    if priority not in TAB_PRIORITIES:
        raise ValueError(f"tab priority must be one of {', '.join(TAB_PRIORITIES)}; got {priority!r}")


@contextlib.contextmanager
def chromium_at(priority: str):
    """The Chromium executable to launch at ``priority``: ``normal`` is Chromium itself; ``idle``
    a wrapper that starts it under ``chrt --idle 0`` (every process it starts inherits the
    policy: a scheduling policy, unlike a nice value, is not undone by Chromium raising its GPU
    process's priority)."""
    check_tab_priority(priority)
    if priority == "normal":
        yield CHROMIUM
        return
    chrt = shutil.which("chrt")
    if chrt is None:
        raise RuntimeError("idle-priority tabs need chrt (util-linux); use --tab-priority normal")
    with tempfile.TemporaryDirectory(prefix="lidarloc-chromium-") as tmp:
        wrapper = Path(tmp) / "chromium-idle"
        wrapper.write_text(f'#!/bin/sh\nexec {chrt} --idle 0 {CHROMIUM} "$@"\n')
        wrapper.chmod(0o755)
        yield wrapper
