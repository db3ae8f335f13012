"""``lidarloc bench city``'s fresh process: a later start on the city's cached tiles and the
memory a drive through the city keeps resident, measured where nothing else was loaded before.

It opens the tiled lookup table and BEV pyramid from their cache (no map points), assembles the
likelihood's window around a tracking particle cloud at the first pose (the start) with the
particle filter's own :class:`~lidarloc.core.maps.follow.TileFollower`, then moves the cloud
along the drive's poses (a new window whenever the tiles under the cloud and the scan's reach
change) with a scan-sized read of the window at every pose (the particle filter's reads), plus
the tiled global search of one scan. Prints one JSON line: start_s, rss_peak_mb, windows.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from ...core.maps.follow import TileFollower
from ...core.maps.tile_cache import read_index
from ...core.maps.tiled_bev import TiledBEV
from ...core.maps.tiled_lookup import TiledLookup
from ...core.matching.tiled_search import match_global_tiled

SCAN_REACH_M = 80.0  # the scan's reach from its particle (the HDL-64E's range)
SPREAD_M = 5.0  # the tracking cloud's standard deviation per axis (m)
PARTICLES = 1000


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
    follower = TileFollower(lookup)
    spread = np.random.default_rng(1).normal(0.0, SPREAD_M, (PARTICLES, 2))  # a tracking particle cloud
    window = follower.follow(poses[0, :2] + spread, SCAN_REACH_M)
    start_s = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    offsets = np.c_[rng.uniform(-80, 80, (20_000, 2)), rng.uniform(-2, 10, 20_000)]
    for p in poses:
        window = None  # as the particle filter holds it: only between its reads
        window = follower.follow(p[:2] + spread, SCAN_REACH_M)
        window.query(offsets + p)
    t = time.perf_counter()
    match_global_tiled(bev, scan, args["angle_step"])
    return {
        "start_s": start_s,
        "rss_peak_mb": peak_rss_mb(),
        "windows": follower.windows,
        "window_mb": window.nbytes / 1e6,
        "global_ms": (time.perf_counter() - t) * 1e3,
        "bev_tiles_loaded": bev.loaded,
    }


if __name__ == "__main__":
    print(json.dumps(probe(json.loads(sys.argv[1]))))
