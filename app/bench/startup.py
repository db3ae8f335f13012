"""``lidarloc bench startup``: start-up time of ``lidarloc demo`` (``lidarloc view`` when a source
is given): first start with nothing cached, then cached starts.

What is timed, from launching the process (a real ``lidarloc demo`` in a child process, the
way a user starts it): the moment the console prints the URL (the server answers HTTP from
then on, with a progress bar in the page) and the moment it prints ``ready:``. The demo is
started with ``--autoplay`` (it would otherwise wait for a browser tab), so ``ready:`` comes once
the first scan has been processed and drawn: it is playing. On a first start S2M's own tables
(road-removed map, BEV pyramid) may still be building in the background then; the filter plays
meanwhile. The first run uses an empty temporary cache directory, so it builds everything; the
later runs reuse it.
Targets: first start playing ≤ 30 s, later starts ≤ 5 s.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request

import numpy as np

from ...core.errors import LidarlocError

from .common import load_avg, machine

_URL = re.compile(r"(http://[0-9a-z.\-]+:\d+)")


def _one_start(args: list[str], cache: str, timeout_s: float) -> dict:
    cmd = [sys.executable, "-m", "lidarloc.app.cli", *args, "--autoplay", "--port", "0", "--cache", cache]
    env = dict(os.environ, COLUMNS="200")
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1, env=env)
    url_s = ready_s = None
    http_status = None
    tail: list[str] = []
    try:
        for line in proc.stdout:
            now = time.perf_counter() - t0
            tail = (tail + [line.rstrip()])[-5:]
            match = _URL.search(line)
            if url_s is None and match:
                url_s = now
                with urllib.request.urlopen(match.group(1), timeout=10) as resp:
                    http_status = resp.status
            if line.startswith("ready:"):
                ready_s = now
                break
            if now > timeout_s:
                break
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    if ready_s is None:
        raise LidarlocError(f"lidarloc {args[0]} did not become ready: " + " | ".join(tail))
    return {"url_s": round(url_s, 2), "ready_s": round(ready_s, 2), "http_status": http_status}


def run(command: list[str], repeats: int = 3, timeout_s: float = 600.0) -> dict:
    """Time ``lidarloc <command>`` (``demo`` or ``view`` and their options) once into an empty
    cache, then ``repeats`` times from it."""
    with tempfile.TemporaryDirectory(prefix="lidarloc-startup-") as cache:
        first = _one_start(command, cache, timeout_s)
        cached = [_one_start(command, cache, timeout_s) for _ in range(repeats)]
    ready = np.array([c["ready_s"] for c in cached])
    return {
        "first_start_ready_s": first["ready_s"],
        "first_start_url_s": first["url_s"],
        "cached_ready_s_median": round(float(np.median(ready)), 2),
        "cached_ready_s_max": round(float(ready.max()), 2),
        "cached_url_s_median": round(float(np.median([c["url_s"] for c in cached])), 2),
        "http_status": first["http_status"],
        "targets_s": {"first_start": 30.0, "cached": 5.0},
        "load_average_1min": round(load_avg(), 2),
        "machine": machine(),
    }
