"""``lidarloc bench town``: how long the built-in town takes to generate and to scan.

Wall-clock times are what a user waits for, but on a shared machine they include whatever else
runs; the CPU time of this process (all its threads) and the load average are reported beside
them so that a slow number can be told apart from a busy machine.
"""

from __future__ import annotations

import os
import time

import numpy as np


def run(seed: int = 0, n_scans_timed: int = 30) -> dict:
    """Build the default town (``TownConfig`` defaults) and time ``n_scans_timed`` scans spread
    over its drive; medians over the scans."""
    from lidarloc.core.config import TownConfig
    from lidarloc.core.o3d import open3d
    from lidarloc.core.sequences.town import TownSequence

    open3d()  # the import itself is not town building
    load_before = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), time.process_time()
    seq = TownSequence.from_config(TownConfig(), seed=seed)
    build_s, build_cpu_s = time.perf_counter() - t0, time.process_time() - c0

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
        "triangles": int(seq.stats["triangles"]),
        "cpu_count": os.cpu_count(),
        "load_avg_1min_before": round(load_before, 2),
        "load_avg_1min_after": round(os.getloadavg()[0], 2),
    }


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=2))
