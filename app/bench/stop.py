"""``lidarloc bench stop``: how fast Ctrl-C stops ``lidarloc run`` (target: within 2 s, results
still written).

A real ``lidarloc run`` in a child process, the way a user starts it, gets SIGINT a given delay
after it prints ``localizing`` (0 s: the first scans, when the S2M process may still be in its
set-up and the first whole-map match is running; later: mid-run). Timed from the signal to the
process's exit; each stop must exit with code 130 and leave a ``summary.json`` that says
``interrupted``. Both clocks; medians over the repeats.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ...core.errors import LidarlocError
from .common import load_avg, machine

TARGET_S = 2.0


def _one_stop(out: Path, clock: str, delay_s: float, args: list[str], cache: str | None) -> float:
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


def run(
    run_args: list[str], delays_s: tuple[float, ...] = (0.0, 1.0, 3.0), repeats: int = 3, cache: str | None = None
) -> dict:
    """Stop ``lidarloc run <run_args>`` (source and configuration options) ``repeats`` times per
    clock and delay."""
    results = {}
    with tempfile.TemporaryDirectory(prefix="lidarloc-stop-") as tmp:
        for clock in ("replay", "realtime"):
            for delay in delays_s:
                times = [
                    _one_stop(Path(tmp) / f"{clock}-{delay}-{i}", clock, delay, run_args, cache) for i in range(repeats)
                ]
                results[f"{clock}, Ctrl-C {delay:g} s after start"] = {
                    "stop_s_median": round(float(np.median(times)), 2),
                    "stop_s_max": round(max(times), 2),
                }
    worst = max(r["stop_s_max"] for r in results.values())
    return {
        "stops": results,
        "repeats": repeats,
        "worst_s": worst,
        "target_s": TARGET_S,
        "met": worst <= TARGET_S,
        "load_average_1min": round(load_avg(), 2),
        "machine": machine(),
    }
