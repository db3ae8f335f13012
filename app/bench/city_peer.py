"""``lidarloc bench city``'s FPFH + RANSAC, in a process of its own: on a city the feature map
alone can outgrow the machine or take hours, and the bench must be able to stop it at its budget
and still report every other figure (see :func:`lidarloc.app.bench.city.peers`).

Reads the cached map (memory-mapped) and the prepared scans with their truth, builds open3d's
FPFH feature map (or reads it from the map's cache directory, where the first run keeps it),
registers each scan to it with RANSAC and prints one JSON line per step as it goes (so that a stop
at the budget still tells how far it got): ``{"features_s", "features_cached", "features_load_s",
"index_s", "feature_points", "rss_peak_mb"}`` once the map's features and their index are there,
then ``{"scan", "ms", "ok", "err_m", "rss_peak_mb"}`` per scan. Each scan's RANSAC is seeded with the run's seed plus the
scan's number, so a resumed run registers a scan as a whole one would.
"""

from __future__ import annotations

import json
import math
import sys
import time

import numpy as np

from .city_probe import peak_rss_mb


def say(line: dict) -> None:
    print(json.dumps(line), flush=True)


def register(args: dict) -> None:
    from .city_rows import judge
    from .peers_global import FeatureMap

    scans = np.load(args["scans"])
    ends = scans["ends"]
    starts = np.r_[0, ends[:-1]]
    points = np.load(args["map"], mmap_mode="r")  # the city's map stays on disk, paged in chunk by chunk
    features = FeatureMap(points, cache_dir=args.get("features_dir"))
    features.index()  # the map's feature index, built once before the first scan's clock starts
    say(
        {
            "features_s": features.build_s,
            "features_cached": features.cached,
            "features_load_s": features.load_s,
            "index_s": features.index_s,
            "feature_points": len(features.cloud.points),
            "rss_peak_mb": peak_rss_mb(),
        }
    )
    for j, (a, b) in enumerate(zip(starts, ends)):
        truth = scans["truth"][j]
        k = int(scans["scan"][j])
        t = time.perf_counter()
        T = features.ransac(scans["points"][a:b], args["seed"] + k)
        ms = (time.perf_counter() - t) * 1e3
        ok, err = (
            judge(T[0, 3], T[1, 3], math.atan2(T[1, 0], T[0, 0]), truth) if np.isfinite(T).all() else (False, math.inf)
        )
        say({"scan": k, "ms": ms, "ok": bool(ok), "err_m": err, "rss_peak_mb": peak_rss_mb()})


if __name__ == "__main__":
    register(json.loads(sys.argv[1]))
