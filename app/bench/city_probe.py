"""``lidarloc bench city``'s fresh process: a later start on the city's cached tiles and the
memory a drive through the city keeps resident, measured where nothing else was loaded before.

It opens the tiled lookup table and BEV pyramid from their cache (no map points), assembles the
likelihood's window around the first pose (the start), then follows the drive's poses: a new
window whenever the vehicle moved a quarter tile, tiles left behind unmapped, and a scan-sized
read of the window at every pose (the particle filter's reads), plus the tiled global search of
one scan. Prints one JSON line: start_s, rss_peak_mb, tiles mapped.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from ...core.maps.tile_cache import read_index
from ...core.maps.tiled_bev import TiledBEV
from ...core.maps.tiled_lookup import TiledLookup
from ...core.matching.tiled_search import match_global_tiled

REACH_M = 100.0  # the window's half side: scan range (80 m) plus the particles' spread


def peak_rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) / 1024.0
    return float("nan")


def probe(args: dict) -> dict:
    poses = np.load(args["poses"])  # (n, 3): x, y, z of the drive
    scan = np.load(args["scan"])  # one road-removed scan, sensor frame
    t0 = time.perf_counter()
    index = read_index(Path(args["lookup_dir"]), args["lookup_key"])
    if index is None:
        raise SystemExit("tiled lookup cache missing")
    lookup = TiledLookup(Path(args["lookup_dir"]), index, points=None)
    bev = TiledBEV.load_or_build(
        np.zeros((0, 2)), Path(args["bev_dir"]), args["bev_key"], args["bev_res"], args["bev_tile_m"]
    )
    x, y = poses[0, :2]
    window = lookup.window(x - REACH_M, y - REACH_M, x + REACH_M, y + REACH_M)
    start_s = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    offsets = np.c_[rng.uniform(-80, 80, (20_000, 2)), rng.uniform(-2, 10, 20_000)]
    centre = poses[0, :2]
    windows = 1
    for p in poses:
        if np.hypot(*(p[:2] - centre)) > lookup.tile_m / 4:
            centre = p[:2]
            x, y = centre
            lookup.drop_except(lookup.tiles_over(x - REACH_M, y - REACH_M, x + REACH_M, y + REACH_M))
            window = lookup.window(x - REACH_M, y - REACH_M, x + REACH_M, y + REACH_M)
            windows += 1
        window.query(offsets + p)
    t = time.perf_counter()
    match_global_tiled(bev, scan, args["angle_step"])
    return {
        "start_s": start_s,
        "rss_peak_mb": peak_rss_mb(),
        "windows": windows,
        "window_mb": window.nbytes / 1e6,
        "global_ms": (time.perf_counter() - t) * 1e3,
        "bev_tiles_loaded": bev.loaded,
    }


if __name__ == "__main__":
    print(json.dumps(probe(json.loads(sys.argv[1]))))
