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

The first start is then watched on until S2M has confirmed the estimate: the demo records what
it plays, and its recording is read as it grows (every ``POLL_S``). ``s2m_confirmed_s`` is the
time from launch to the first recorded step that is localized (the rule needs S2M's word) or has
an S2M confirmation; ``first_start_false_fire`` says whether any step until then was localized
more than 5 m from the truth (its truth alarm) or a ``false_fire`` event was recorded.
Targets: first start playing ≤ 30 s, later starts ≤ 5 s, no false fire.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np

from ...core.errors import LidarlocError
from ..viewer.token_gate import TOKEN_ENV
from .common import load_avg, machine

_URL = re.compile(r"(http://[0-9a-z.\-]+:\d+)")
_RECORDING = re.compile(r"recording into (\S+) \(")
POLL_S = 0.25
CONFIRM_TIMEOUT_S = 300.0


def first_steps(run_dir: Path | None, t0: float, timeout_s: float, proc) -> dict:
    """Watch a demo's recording until a step is localized or S2M-confirmed (or ``timeout_s`` from
    ``t0``, or the demo ends): when that was, and whether any step until then fired falsely."""
    from ...core.rules.truth import truth_alarm
    from ...core.runs import recording

    confirmed_s, false_fire, seen = None, False, 0
    while run_dir is not None and time.perf_counter() - t0 < timeout_s and proc.poll() is None:
        try:
            rec = recording.open(run_dir)
        except LidarlocError:  # not written yet
            time.sleep(POLL_S)
            continue
        now = time.perf_counter() - t0
        n = rec.n
        if n > seen:
            localized = rec.field("localized", n).astype(bool)
            err = rec.field("error_m", n).astype(float)
            confirmed = rec.field("confirmed_at", n) >= 0 if "confirmed_at" in rec.field_names else localized
            hit = (localized | confirmed).nonzero()[0]
            upto = int(hit[0]) + 1 if hit.size else n
            false_fire |= any(truth_alarm(bool(localized[i]), float(err[i])) for i in range(seen, upto))
            false_fire |= any(e.kind == "false_fire" and s < upto for s, e in rec.events)
            seen = upto
            if hit.size:
                confirmed_s = now
                break
        time.sleep(POLL_S)
    return {
        "s2m_confirmed_s": None if confirmed_s is None else round(confirmed_s, 2),
        "false_fire": bool(false_fire),
        "steps_watched": seen,
    }


def _one_start(args: list[str], cache: str, timeout_s: float, watch: bool = False) -> dict:
    """One start of the demo; with ``watch`` it runs on until S2M confirmed (``first_steps``)."""
    cmd = [sys.executable, "-m", "lidarloc.app.cli", *args, "--autoplay", "--port", "0", "--cache", cache]
    env = dict(os.environ, COLUMNS="200")
    env.pop(TOKEN_ENV, None)  # the bench's own loopback viewer: its client brings no token
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1, env=env)
    # a demo that neither prints "ready:" nor exits would block the read below forever: past the
    # timeout it is killed, which ends its output and the read
    watchdog = threading.Timer(timeout_s + (CONFIRM_TIMEOUT_S if watch else 0.0), proc.kill)
    watchdog.daemon = True
    watchdog.start()
    url_s = ready_s = None
    http_status = None
    run_dir = None
    watched = {}
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
            rec = _RECORDING.search(line)
            if rec:
                run_dir = Path(rec.group(1)) / "run"
            if line.startswith("ready:"):
                ready_s = now
                break
            if now > timeout_s:
                break
        if watch and ready_s is not None:
            # the pipe is drained meanwhile: a demo that prints must not block on it
            threading.Thread(target=lambda: [None for _ in proc.stdout], daemon=True).start()
            watched = first_steps(run_dir, t0, CONFIRM_TIMEOUT_S, proc)
    finally:
        watchdog.cancel()
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    if ready_s is None:
        raise LidarlocError(f"lidarloc {args[0]} did not become ready: " + " | ".join(tail))
    return {"url_s": round(url_s, 2), "ready_s": round(ready_s, 2), "http_status": http_status, **watched}


def run(command: list[str], repeats: int = 3, timeout_s: float = 600.0) -> dict:
    """Time ``lidarloc <command>`` (``demo`` or ``view`` and their options) once into an empty
    cache, then ``repeats`` times from it."""
    with tempfile.TemporaryDirectory(prefix="lidarloc-startup-") as cache:
        first = _one_start(command, cache, timeout_s, watch=True)
        cached = [_one_start(command, cache, timeout_s) for _ in range(repeats)]
    ready = np.array([c["ready_s"] for c in cached])
    return {
        "first_start_ready_s": first["ready_s"],
        # the first scan processed and drawn: what "ready:" waits for with --autoplay
        "first_start_scan_drawn_s": first["ready_s"],
        "s2m_confirmed_s": first.get("s2m_confirmed_s"),
        "first_start_false_fire": first.get("false_fire"),
        # steps of the first start read while waiting for the confirmation (null: not within
        # CONFIRM_TIMEOUT_S after launch)
        "first_start_steps_watched": first.get("steps_watched"),
        "confirm_timeout_s": CONFIRM_TIMEOUT_S,
        "first_start_url_s": first["url_s"],
        "cached_ready_s_median": round(float(np.median(ready)), 2),
        "cached_ready_s_max": round(float(ready.max()), 2),
        "cached_url_s_median": round(float(np.median([c["url_s"] for c in cached])), 2),
        "http_status": first["http_status"],
        "targets_s": {"first_start": 30.0, "cached": 5.0},
        "targets": {"first_start_false_fire": False},
        "load_average_1min": round(load_avg(), 2),
        "machine": machine(),
    }
