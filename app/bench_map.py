"""``lidarloc bench map``: prior-map build and cache-load cost, each in a fresh process so that
peak memory and timings are those of a first start (and of a second start for the load)."""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path


def _map_build(args: list[str], cache: Path) -> dict:
    import os

    env = dict(os.environ, LIDARLOC_CACHE=str(cache))
    r = subprocess.run([sys.executable, "-m", "lidarloc.app.cli", "map", "build", "--json", *args],
                       capture_output=True, text=True, env=env)
    if r.returncode != 0:
        raise RuntimeError(r.stderr.strip().splitlines()[-1] if r.stderr.strip() else "map build failed")
    return json.loads(r.stdout)


def run(data_dir: Path = Path("../shared/data")) -> dict:
    out = {}
    sources = {"town": []}
    raw = Path(data_dir) / "kitti_raw"
    if raw.is_dir():
        sources["kitti_raw"] = ["--kitti-raw", str(raw), "--date", "2011_09_26", "--drive", "0013"]
    for name, args in sources.items():
        with tempfile.TemporaryDirectory(prefix="lidarloc-bench-map-") as cache:
            build = _map_build(args, Path(cache))
            load = _map_build(args, Path(cache))
        out[name] = {"scans": build["scans"], "points": build["points"],
                     "points_road_removed": build["points_road_removed"],
                     "build_s": build["seconds"], "build_peak_rss_mb": build["peak_rss_mb"],
                     "load_s": load["seconds"], "load_peak_rss_mb": load["peak_rss_mb"]}
    return out
