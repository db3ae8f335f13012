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


def _one_stop(out: Path, clock: str, delay_s: float, args: list[str], cache: str | None, busy: int = 0) -> float:
    cmd = [sys.executable, "-m", "lidarloc.app.cli", "run", "--out", str(out), *args, "--clock", clock] + (
        ["--cache", cache] if cache else []
    )
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        seen = []
        for line in proc.stderr:
            seen.append(line)
            if "localizing" in line:
                break
        else:
            raise LidarlocError("lidarloc run ended before localizing: " + (seen[-1].strip() if seen else "no output"))
        with _busy(busy):
            time.sleep(delay_s)  # the run goes on meanwhile; this is not synchronisation
            proc.send_signal(signal.SIGINT)
            t0 = time.perf_counter()
            try:
                _, rest = proc.communicate(timeout=60)
            except subprocess.TimeoutExpired:
                raise LidarlocError(f"Ctrl-C after {delay_s} s: lidarloc run still running after 60 s") from None
            stop_s = time.perf_counter() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    summary_file = out / "summary.json"
    summary = json.loads(summary_file.read_text()) if summary_file.is_file() else {}
    if proc.returncode != 130 or not summary.get("interrupted"):
        last = (rest or "".join(seen)).strip().splitlines()[-1:]
        raise LidarlocError(
            f"Ctrl-C after {delay_s} s: exit code {proc.returncode}, summary.json "
            f"{'interrupted' if summary.get('interrupted') else 'missing or not interrupted'}: {last}"
        )
    return stop_s


def _one_viewer_stop(command: list[str], delay_s: float, cache: str | None, busy: int) -> float:
    cmd = [sys.executable, "-m", "lidarloc.app.cli", *command, "--autoplay", "--port", "0", "--no-record"]
    cmd += ["--cache", cache] if cache else []
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        seen = []
        for line in proc.stdout:
            seen.append(line)
            if line.startswith("ready:"):
                break
        else:
            raise LidarlocError(
                f"lidarloc {command[0]} ended before it played: " + (seen[-1].strip() if seen else "no output")
            )
        tail: list[str] = []
        # the output is drained meanwhile: a viewer that prints must not block on a full pipe
        reader = threading.Thread(target=lambda: tail.extend(proc.stdout), daemon=True)
        reader.start()
        with _busy(busy):
            time.sleep(delay_s)  # the viewer plays on meanwhile; this is not synchronisation
            proc.send_signal(signal.SIGINT)
            t0 = time.perf_counter()
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                raise LidarlocError(
                    f"Ctrl-C after {delay_s} s: lidarloc {command[0]} still running after 60 s"
                ) from None
            stop_s = time.perf_counter() - t0
        reader.join(timeout=5)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    if proc.returncode != 0:
        last = "".join(tail or seen).strip().splitlines()[-1:]
        raise LidarlocError(f"Ctrl-C after {delay_s} s: lidarloc {command[0]} exit code {proc.returncode}: {last}")
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
