"""``lidarloc bench town``: how long the built-in town takes to generate and to scan.

Wall-clock times are what a user waits for, but on a shared machine they include whatever else
runs; the CPU time of this process (all its threads) and the load average are reported beside
them so that a slow number can be told apart from a busy machine.
"""

from __future__ import annotations

import os
import time
from dataclasses import replace

import numpy as np

from ...core.config import Config
from ...core.sequences.base import Limited
from ...core.sequences.factory import SourceSpec, open_sequence
from .common import load_avg, require_town


def run(spec: SourceSpec, cfg: Config, n_scans_timed: int = 30) -> dict:
    """Build the town of ``spec`` (``cfg.town``) and time ``n_scans_timed`` scans spread over its
    drive (over its first ``spec.scans`` scans if given); medians over the scans."""
    from ...core.o3d import open3d
    from ...core.sim.town import TownSequence  # noqa: F401  (imported off the clock)

    require_town(spec, "town", "the built-in town's generation")
    open3d()  # the import itself is not town building
    load_before = load_avg()
    t0, c0 = time.perf_counter(), time.process_time()
    town = open_sequence(replace(spec, scans=None), cfg)  # the whole town's drive
    build_s, build_cpu_s = time.perf_counter() - t0, time.process_time() - c0
    seq = town if spec.scans is None else Limited(town, spec.scans)

    wall, cpu, points = [], [], []
    for i in np.linspace(0, len(seq) - 1, n_scans_timed).astype(int):
        t0, c0 = time.perf_counter(), time.process_time()
        scan = seq.scan(int(i))
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        points.append(len(scan))
    return {
        "town_build_s": round(build_s, 3),
        "scan_ms_median": round(1e3 * float(np.median(wall)), 2),
        "scan_points_median": int(np.median(points)),
        "scans_timed": len(wall),
        "town_build_cpu_s": round(build_cpu_s, 3),
        "scan_cpu_ms_median": round(1e3 * float(np.median(cpu)), 2),
        "scans_in_drive": len(seq),
        "triangles": int(town.stats["triangles"]),
        "cpu_count": os.cpu_count(),
        "load_avg_1min_before": round(load_before, 2),
        "load_avg_1min_after": round(load_avg(), 2),
    }
