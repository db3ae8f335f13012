"""``lidarloc bench mapfile``: a large point-cloud map file, from reading it to the lookup table.

A town-like map (ground with gentle relief, building walls on a block grid, poles; 2 cm noise)
of ``--points`` float32 points is generated at benchmark time into a temporary binary .pcd,
chunk by chunk (never the whole cloud in memory). A fresh child process then does what the
localizer does before it can start on that map (the viewer's start: road removal follows in the
background): read the file and voxelize it (``load_or_build_map`` of a
:class:`~lidarloc.core.maps.map_source.MapFileSource`, into an empty cache), then build the lookup
table (``load_or_build_lookup`` at the default δ and d_max). Road removal is timed after it,
apart from the target. Peak memory is the child's own (``ru_maxrss``), and a sampling thread
gives the peak while reading, against the points' float32 size.

Targets: reading + voxelizing + lookup table ≤ 2 min and ≤ 6 GB peak for 50 M points; the read
alone ≤ 3× the points' float32 size.
"""

from __future__ import annotations

import multiprocessing as mp
import shutil
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from ...core.config import Config
from ...core.maps.mapfile import CHUNK_POINTS
from ...core.maps.mapfile_write import write_map_chunks
from ..console import peak_rss_mb
from .common import child_result, end_child, load_avg, machine, rss_mb

DEFAULT_POINTS = 50_000_000
#: the side of the generated square (m) for 50 M points: ~300 points/m² of ground, a SLAM map's
#: few-centimetre density; smaller maps shrink the square so the density stays
SIDE_AT_DEFAULT = 400.0
TARGET_S, TARGET_PEAK_MB = 120.0, 6000.0


def _terrain(x, y):
    return 1.5 * np.sin(x / 60.0) * np.cos(y / 45.0)


def town_buildings(side: float, seed: int = 0) -> np.ndarray:
    """Buildings (x0, y0, w, d, h) on a 50 m block grid, one per block, 3 of 10 blocks empty."""
    rng = np.random.default_rng(seed)
    rows = []
    for bx in np.arange(8.0, side - 20.0, 50.0):
        for by in np.arange(8.0, side - 20.0, 50.0):
            if rng.random() < 0.3:
                continue
            w, d = rng.uniform(10, min(30, side - bx - 2)), rng.uniform(10, min(30, side - by - 2))
            rows.append((bx + rng.uniform(0, 4), by + rng.uniform(0, 4), w, d, rng.uniform(5, 20)))
    if not rows:  # a tiny map: one building in the middle
        rows.append((side * 0.3, side * 0.3, side * 0.3, side * 0.3, 6.0))
    return np.array(rows)


def town_chunk(i: int, m: int, side: float, buildings: np.ndarray) -> np.ndarray:
    """Chunk ``i`` (m points, float32) of the generated map: 55 % ground, 40 % walls, 5 % poles.
    Each chunk has its own random stream, so the file is the same for the same size."""
    rng = np.random.default_rng([1, i])
    n_ground, n_wall = int(m * 0.55), int(m * 0.40)
    n_pole = m - n_ground - n_wall
    gx, gy = rng.random(n_ground) * side, rng.random(n_ground) * side
    ground = np.stack([gx, gy, _terrain(gx, gy)], axis=1)
    b = buildings[rng.integers(0, len(buildings), n_wall)]
    x0, y0, w, d, h = b.T
    perimeter = 2 * (w + d)
    s = rng.random(n_wall) * perimeter
    x = np.where(s < w, x0 + s, np.where(s < w + d, x0 + w, np.where(s < 2 * w + d, x0 + (s - w - d), x0)))
    y = np.where(s < w, y0, np.where(s < w + d, y0 + (s - w), np.where(s < 2 * w + d, y0 + d, y0 + (s - 2 * w - d))))
    walls = np.stack([x, y, _terrain(x0, y0) - 0.5 + rng.random(n_wall) * h], axis=1)
    # poles on a 25 m grid along the blocks' edges
    k = max(int(side // 25.0), 1)
    px = (rng.integers(0, k, n_pole) + 0.5) * 25.0
    py = (rng.integers(0, k, n_pole) + 0.1) * 25.0
    angle = rng.random(n_pole) * 2 * np.pi
    poles = np.stack(
        [px + 0.1 * np.cos(angle), py + 0.1 * np.sin(angle), _terrain(px, py) + rng.random(n_pole) * 6.0], axis=1
    )
    pts = np.concatenate([ground, walls, poles])
    pts += rng.normal(0.0, 0.02, pts.shape)
    return pts.astype(np.float32)


def write_town_map(path: Path, n_points: int) -> float:
    """Write the generated map of ``n_points`` to ``path`` (binary .pcd); returns its side (m)."""
    side = max(30.0, SIDE_AT_DEFAULT * (n_points / DEFAULT_POINTS) ** 0.5)
    buildings = town_buildings(side)
    sizes = [min(CHUNK_POINTS, n_points - s) for s in range(0, n_points, CHUNK_POINTS)]
    write_map_chunks(path, n_points, (town_chunk(i, m, side, buildings) for i, m in enumerate(sizes)), np.float32)
    return side


class _PeakSampler(threading.Thread):
    """Resident memory sampled every 20 ms: the peak within a phase (ru_maxrss only knows the
    process's whole life)."""

    def __init__(self):
        super().__init__(daemon=True, name="lidarloc-rss")
        self.peak, self._halt = 0.0, threading.Event()

    def run(self):
        while not self._halt.wait(0.02):
            self.peak = max(self.peak, rss_mb())

    def take(self) -> float:
        peak, self.peak = max(self.peak, rss_mb()), 0.0
        return peak

    def stop(self):
        self._halt.set()
        self.join()


def _child(path: str, cache: str, queue) -> None:
    try:
        queue.put(_measure(path, cache))
    except Exception as exc:  # reported by the parent as one line
        queue.put({"error": f"{type(exc).__name__}: {exc}".splitlines()[0]})


def _measure(path: str, cache: str) -> dict:
    from ...core.maps.lookup import LookupTable, load_or_build_lookup
    from ...core.maps.map_source import MapFileSource
    from ...core.maps.mapping import load_or_build_map, remove_road
    from ...core.maps.voxel_grid import VoxelAccumulator

    cfg = Config()
    # compile the numba kernels first (cached on disk after a first run): the figures are the work's
    VoxelAccumulator(cfg.map.voxel_size).add(np.random.default_rng(0).random((100, 3)))
    LookupTable.build(np.random.default_rng(0).random((2000, 3)).astype(np.float32) * 10, 0.25, 5.0)
    rss_before = rss_mb()
    sampler = _PeakSampler()
    sampler.start()
    marks = {}

    def progress(i, n):
        if i >= 0.75 * n and "read" not in marks:  # build_prior_map_from_file: reading is 3/4 of the scale
            marks["read"] = time.perf_counter()
            marks["read_peak"] = sampler.take()

    t0 = time.perf_counter()
    prior, map_dir, _ = load_or_build_map(
        MapFileSource(path), cfg.map, Path(cache), progress=progress, road_removal=False
    )
    t1 = time.perf_counter()
    map_peak = sampler.take()
    lookup = load_or_build_lookup(prior, map_dir, cfg.pf.lookup_resolution, cfg.pf.d_max).value
    t2 = time.perf_counter()
    lookup_peak = sampler.take()
    peak_to_lookup = peak_rss_mb()
    road = remove_road(prior, cfg.map)
    t3 = time.perf_counter()
    sampler.stop()
    return {
        "read_s": marks["read"] - t0,
        "voxelize_s": t1 - marks["read"],
        "lookup_s": t2 - t1,
        "total_s": t2 - t0,
        "road_removal_s": t3 - t2,
        "map_points": int(len(prior.points)),
        "map_points_road_removed": int(len(road.points_bev)),
        "lookup_mb": lookup.nbytes / 1e6,
        "rss_before_mb": rss_before,
        "read_peak_rss_mb": marks["read_peak"],
        "map_peak_rss_mb": max(marks["read_peak"], map_peak),
        "lookup_peak_rss_mb": lookup_peak,
        "peak_rss_mb": peak_to_lookup,
        "peak_rss_with_road_removal_mb": peak_rss_mb(),
        "origin_m": [float(v) for v in prior.origin],
    }


def run(n_points: int = DEFAULT_POINTS) -> dict:
    """Generate the map file, then read, voxelize and build the lookup table in a fresh process."""
    work = Path(tempfile.mkdtemp(prefix="lidarloc-bench-mapfile-"))
    try:
        path = work / "map.pcd"
        t0 = time.perf_counter()
        side = write_town_map(path, n_points)
        write_s = time.perf_counter() - t0
        ctx = mp.get_context("spawn")
        queue = ctx.Queue()
        proc = ctx.Process(target=_child, args=(str(path), str(work / "cache"), queue), daemon=True)
        proc.start()
        try:
            res = child_result(queue, proc, "mapfile")
            if "error" in res:
                from ...core.errors import LidarlocError

                raise LidarlocError(f"bench mapfile: {res['error']}")
        finally:
            end_child(proc)
        float32_mb = n_points * 12 / 1e6
        return {
            "points": n_points,
            "side_m": round(side, 1),
            "file_mb": round(path.stat().st_size / 1e6, 1),
            "write_s": round(write_s, 2),
            **{k: (round(v, 2) if isinstance(v, float) else v) for k, v in res.items()},
            "points_float32_mb": round(float32_mb, 1),
            "read_peak_over_float32": round(res["read_peak_rss_mb"] / float32_mb, 2),
            "read_increase_over_float32": round((res["read_peak_rss_mb"] - res["rss_before_mb"]) / float32_mb, 2),
            "targets": {"total_s": TARGET_S, "peak_rss_mb": TARGET_PEAK_MB, "read_peak_over_float32": 3.0},
            "meets_targets": bool(res["total_s"] <= TARGET_S and res["peak_rss_mb"] <= TARGET_PEAK_MB),
            "load_avg_1min": round(load_avg(), 2),
            "machine": machine(),
        }
    finally:
        shutil.rmtree(work, ignore_errors=True)
