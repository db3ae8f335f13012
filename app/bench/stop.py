"""``lidarloc bench stop``: how fast Ctrl-C stops ``lidarloc run`` (target: within 2 s, results
still written), or with ``--viewer`` the live viewer (target: within 1 s, as docs/keeps-working.md promises).

A real ``lidarloc run`` in a child process, the way a user starts it, gets SIGINT a given delay
after it prints ``localizing`` (0 s: the first scans, when the S2M process may still be in its
set-up and the first whole-map match is running; later: mid-run). Timed from the signal to the
process's exit; each stop must exit with code 130 and leave a ``summary.json`` that says
``interrupted``. Both clocks; medians over the repeats.

``--viewer``: ``lidarloc demo --autoplay`` (``view`` on a source given), SIGINT the delay after it
prints ``ready:`` (playing); each stop must exit with code 0. ``--busy N`` starts N processes that
spin on a core each once the command is under way, as on a machine that runs other work beside it.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from ...core.errors import LidarlocError
from .common import load_avg, machine

TARGET_S = 2.0
VIEWER_TARGET_S = 1.0  # docs/keeps-working.md, "Stopping"


@contextmanager
def _busy(n: int):
    """``n`` processes spinning on a core each while the block runs."""
    spinners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        yield
    finally:
        for p in spinners:
            p.kill()
            p.wait()


def _stop_when_ready(
    cmd: list[str], merged: bool, ready: Callable[[str], bool], what: str, until: str, delay_s: float, busy: int
) -> tuple[float, int, str]:
    """Start ``cmd``, read its output (stdout with stderr when ``merged``, else stderr) until a
    line ``ready`` accepts, then, beside ``busy`` spinning processes, wait ``delay_s`` and send
    SIGINT. Returns the seconds from the signal to the exit, the exit code and the output."""
    out = subprocess.PIPE if merged else subprocess.DEVNULL
    err = subprocess.STDOUT if merged else subprocess.PIPE
    proc = subprocess.Popen(cmd, stdout=out, stderr=err, text=True)
    stream = proc.stdout if merged else proc.stderr
    try:
        seen = []
        for line in stream:
            seen.append(line)
            if ready(line):
                break
        else:
            raise LidarlocError(f"{what} ended before {until}: " + (seen[-1].strip() if seen else "no output"))
        tail: list[str] = []
        # the output is drained meanwhile: a command that prints must not block on a full pipe
        reader = threading.Thread(target=lambda: tail.extend(stream), daemon=True)
        reader.start()
        with _busy(busy):
            time.sleep(delay_s)  # the command goes on meanwhile; this is not synchronisation
            proc.send_signal(signal.SIGINT)
            t0 = time.perf_counter()
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                raise LidarlocError(f"Ctrl-C after {delay_s} s: {what} still running after 60 s") from None
            stop_s = time.perf_counter() - t0
        reader.join(timeout=5)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return stop_s, proc.returncode, "".join(tail or seen)


def _one_stop(out: Path, clock: str, delay_s: float, args: list[str], cache: str | None, busy: int = 0) -> float:
    cmd = [sys.executable, "-m", "lidarloc.app.cli", "run", "--out", str(out), *args, "--clock", clock] + (
        ["--cache", cache] if cache else []
    )
    stop_s, code, rest = _stop_when_ready(
        cmd, False, lambda line: "localizing" in line, "lidarloc run", "localizing", delay_s, busy
    )
    summary_file = out / "summary.json"
    summary = json.loads(summary_file.read_text()) if summary_file.is_file() else {}
    if code != 130 or not summary.get("interrupted"):
        last = rest.strip().splitlines()[-1:]
        raise LidarlocError(
            f"Ctrl-C after {delay_s} s: exit code {code}, summary.json "
            f"{'interrupted' if summary.get('interrupted') else 'missing or not interrupted'}: {last}"
        )
    return stop_s


def _one_viewer_stop(command: list[str], delay_s: float, cache: str | None, busy: int) -> float:
    cmd = [sys.executable, "-m", "lidarloc.app.cli", *command, "--autoplay", "--port", "0", "--no-record"]
    cmd += ["--cache", cache] if cache else []
    what = f"lidarloc {command[0]}"
    stop_s, code, rest = _stop_when_ready(
        cmd, True, lambda line: line.startswith("ready:"), what, "it played", delay_s, busy
    )
    if code != 0:
        last = rest.strip().splitlines()[-1:]
        raise LidarlocError(f"Ctrl-C after {delay_s} s: {what} exit code {code}: {last}")
    return stop_s


def run(
    run_args: list[str],
    delays_s: tuple[float, ...] = (0.0, 1.0, 3.0),
    repeats: int = 3,
    cache: str | None = None,
    busy: int = 0,
    viewer: list[str] | None = None,
) -> dict:
    """Stop ``lidarloc run <run_args>`` (source and configuration options) ``repeats`` times per
    clock and delay; with ``viewer`` (``["demo", …]`` or ``["view", …]``), that viewer instead,
    ``repeats`` times per delay. ``busy``: processes spinning beside it once it is under way."""
    results = {}
    if viewer is not None:
        for delay in delays_s:
            times = [_one_viewer_stop(viewer, delay, cache, busy) for _ in range(repeats)]
            results[f"viewer, Ctrl-C {delay:g} s after playing"] = _figures(times)
        target = VIEWER_TARGET_S
    else:
        with tempfile.TemporaryDirectory(prefix="lidarloc-stop-") as tmp:
            for clock in ("replay", "realtime"):
                for delay in delays_s:
                    times = [
                        _one_stop(Path(tmp) / f"{clock}-{delay}-{i}", clock, delay, run_args, cache, busy)
                        for i in range(repeats)
                    ]
                    results[f"{clock}, Ctrl-C {delay:g} s after start"] = _figures(times)
        target = TARGET_S
    worst = max(r["stop_s_max"] for r in results.values())
    return {
        "stops": results,
        "repeats": repeats,
        "busy": busy,
        "worst_s": worst,
        "target_s": target,
        "met": worst <= target,
        "load_average_1min": round(load_avg(), 2),
        "machine": machine(),
    }


def _figures(times: list[float]) -> dict:
    return {"stop_s_median": round(float(np.median(times)), 2), "stop_s_max": round(max(times), 2)}
