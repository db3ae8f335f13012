"""``lidarloc bench map``: prior-map build and cache-load cost, each in a fresh process so that
peak memory and timings are those of a first start (and of a second start for the load)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from ...core.errors import LidarlocError
from ...core.sequences.factory import SourceSpec
from .common import real_drive, source_args


def source_name(spec: SourceSpec) -> str:
    return spec.kind


def default_sources(town: SourceSpec) -> dict[str, SourceSpec]:
    """No source chosen: the town, and the reference real drive where the data is present."""
    sources = {"town": town}
    drive = real_drive(town.scans)
    if drive is not None:
        sources["kitti_raw"] = drive
    return sources


def _map_build(args: list[str], cache: Path) -> dict:
    env = dict(os.environ, LIDARLOC_CACHE=str(cache))
    r = subprocess.run(
        [sys.executable, "-m", "lidarloc.app.cli", "map", "build", "--json", *args],
        capture_output=True,
        text=True,
        env=env,
    )
    if r.returncode != 0:
        last = r.stderr.strip().splitlines()[-1] if r.stderr.strip() else "map build failed"
        raise LidarlocError(f"bench map: {last.removeprefix('lidarloc: error: ')}")
    return json.loads(r.stdout)


def run(sources: dict[str, SourceSpec], config_args: list[str] = ()) -> dict:
    """Build each source's map into an empty cache, then load it from there (``lidarloc map build``
    twice, each in a fresh process)."""
    out = {}
    for name, spec in sources.items():
        args = source_args(spec) + list(config_args)
        with tempfile.TemporaryDirectory(prefix="lidarloc-bench-map-") as cache:
            build = _map_build(args, Path(cache))
            load = _map_build(args, Path(cache))
        out[name] = {
            "scans": build["scans"],
            "points": build["points"],
            "points_road_removed": build["points_road_removed"],
            "build_s": build["seconds"],
            "build_peak_rss_mb": build["peak_rss_mb"],
            "load_s": load["seconds"],
            "load_peak_rss_mb": load["peak_rss_mb"],
        }
    return out
