"""How fast a run notices a killed child process and goes on (target: within 1 s).

``lidarloc bench faults [--scans N] [--repeats R] [--json]``: the built-in town's
first ``scans`` scans in the real-time clock (a sensor's pace: a step every scan interval); after
a third of them the S2M or the KISS-ICP child is killed with SIGKILL, and the time from the kill
to the start of its replacement is taken (the ``restarted`` event is recorded then). The run must then finish every scan.
Medians over ``repeats`` kills per block, with the 1-minute load average.
"""

from __future__ import annotations

import os
import signal
import time

import numpy as np

from ...core.config import Config
from ...core.errors import LidarlocError
from ...core.localizer import Localizer
from ...core.sequences.factory import SourceSpec, open_sequence
from .common import load_avg, machine

TARGET_S = 1.0


def _one_kill(seq, cfg: Config, which: str, cache_root) -> float:
    with Localizer(seq, cfg, cache_root) as loc:
        loc.wait_ready()
        loc.run(len(seq) // 3)
        proxy = loc.s2m.matcher if which == "S2M" else loc.odometry.process
        seen = len(loc.events)
        t_kill = time.monotonic()
        os.kill(proxy.pid, signal.SIGKILL)
        period = float(np.median(np.diff(seq.timestamps)))
        while not loc.done:
            t0 = time.perf_counter()
            loc.step()
            time.sleep(max(0.0, period - (time.perf_counter() - t0)))  # the sensor's pace
        restarts = [e for e in loc.events[seen:] if e.kind == "restarted"]
        if not restarts or proxy.restarted_at is None:
            raise LidarlocError(f"{which}: the killed child was never restarted")
        return proxy.restarted_at - t_kill  # the new child started: the death was noticed


def run(scans: int = 45, repeats: int = 3, cache_root=None) -> dict:
    cfg = Config()
    cfg.localize.clock = "realtime"
    seq = open_sequence(SourceSpec(scans=scans), cfg)
    load_start = load_avg()
    out = {}
    for which in ("S2M", "RPE"):
        times = [_one_kill(seq, cfg, which, cache_root) for _ in range(repeats)]
        out[which] = {
            "notice_s_median": round(float(np.median(times)), 3),
            "notice_s_max": round(max(times), 3),
            "met": max(times) <= TARGET_S,
        }
    out["scans"], out["repeats"] = scans, repeats
    out["load_avg"] = [round(load_start, 1), round(load_avg(), 1)]
    out["machine"] = machine()
    return out
