"""The exact whole-city search sharded over Ray (``--ray local|auto|ADDRESS``), and ``lidarloc
bench shards``: its time with 1 and more workers beside the one-machine search, and whether every
answer is the same.

Each worker is a Ray actor holding one shard (:class:`~lidarloc.core.matching.shards.ShardHost`):
it opens the city's tiled pyramid from the cache directory, so on a cluster every node needs the
cache at the same path (a shared file system), as ``lidarloc sweep --ray`` needs the map's. An
actor, not a task per tile: a tile's search keeps its heap between the search's sweeps, so it
stays where it started. What crosses Ray per scan is the scan's cells (a few MB, once per actor)
and per sweep a list of tiles and each tile's find (bytes).
"""

from __future__ import annotations

import os
import time

from ...core.config import Config
from ...core.errors import LidarlocError
from ...core.maps.mapping import load_or_build_map
from ...core.maps.tiled_bev import TiledBEV
from ...core.matching.shards import ShardedTiles, ShardHost, cache_spec
from ...core.matching.tiled_search import match_global_tiled
from ...core.sequences.factory import SourceSpec
from .city_rows import prepare, scan_order
from .common import load_avg, machine, median, open_source

#: Side of the city pyramid's L0 tiles (m), as ``bench city`` builds them.
BEV_TILE_M = 256.0


class RayShards:
    """``workers`` Ray actors, one shard each, over one city's tiled pyramid: :attr:`tiles` is what
    ``match_global_tiled(..., shards=…)`` takes; :meth:`using` the first n of them alone.
    :meth:`close` ends the actors."""

    def __init__(self, bev: TiledBEV, workers: int, address: str | None = "local"):
        from ..sweep.cluster import connect, import_ray

        if workers < 1:
            raise LidarlocError(f"--workers must be ≥ 1, got {workers}")
        if address in (None, "local"):
            # Ray starts its workers at nice 15, to leave the driver its core; here the workers are
            # the search the driver waits for, and at nice 15 beside any other work on the machine
            # they get a sliver of a core (only a local instance started here reads this)
            os.environ.setdefault("RAY_worker_niceness", "0")
        connect(address or "local", workers)
        self.ray = ray = import_ray()
        host = ray.remote(num_cpus=1)(ShardHost)
        spec = ray.put(cache_spec(bev))
        self.actors = [host.remote(spec) for _ in range(workers)]
        self.tiles = self.using(workers)

    def using(self, n: int) -> ShardedTiles:
        """The search over the first ``n`` actors only."""
        actors, ray = self.actors[:n], self.ray

        def run(calls):
            cells: list = []  # the scan's cells, the same for every shard: put in the object store once

            def args_of(name: str, args: tuple) -> tuple:
                if name != "start":
                    return args
                if not cells:
                    cells.extend((ray.put(args[0]), ray.put(args[1])))
                return (*cells, *args[2:])

            return ray.get([getattr(actors[s], name).remote(*args_of(name, args)) for s, name, args in calls])

        return ShardedTiles(len(actors), run)

    def close(self) -> None:
        for actor in self.actors:
            self.ray.kill(actor)
        self.actors = []


def run(
    spec: SourceSpec,
    cfg: Config,
    cache_root=None,
    scans: int = 5,
    workers: tuple[int, ...] = (1, 2),
    address: str | None = "local",
    progress=None,
) -> dict:
    """The exact tiled search over the whole city on ``scans`` of its drive's scans (the bench
    city's seeded order): on this machine (threads, one per core) and over Ray with each count of
    ``workers``, one after the other on the same scan, each search's answer compared with this
    machine's. Numba's kernels are loaded in every worker off the clock (one search first)."""
    report = progress or (lambda what, f: None)
    seq = open_source(spec, cfg, "shards", need_poses=True)
    prior, map_dir, _ = load_or_build_map(seq.map_source, cfg.map, cache_root, memory_map=True)
    bev = TiledBEV.load_or_build(
        prior.points_bev, map_dir / "tiles-bev", map_dir.name, cfg.s2m.match_resolution, BEV_TILE_M,
        "binary" if cfg.s2m.binary_cells else None, progress=lambda f: report("pyramid tiles", f),
    )  # fmt: skip
    step = cfg.s2m.angle_step
    idx = scan_order(len(seq), scans, cfg.seed)
    out: dict = {"source": seq.name, "machine": machine(), "load_avg_start": load_avg(), "tiles": bev.ntx * bev.nty}
    t0 = time.perf_counter()
    shards = RayShards(bev, max(workers), address)
    by_count = {n: shards.using(n) for n in workers}
    try:
        first = prepare(seq.scan(idx[0]), cfg)[:, :2]
        for tiles in by_count.values():  # every worker's kernels loaded, its first tiles read
            match_global_tiled(bev, first, step, shards=tiles)
        out["ray_start_s"] = time.perf_counter() - t0
        match_global_tiled(bev, first, step)
        rows = []
        for j, k in enumerate(idx):
            scan = prepare(seq.scan(k), cfg)[:, :2]
            here = match_global_tiled(bev, scan, step)
            row = {"scan": k, "load_avg": load_avg(), "one_machine_ms": here.ms, "nodes": here.nodes_expanded}
            row["same"] = True
            for n, tiles in by_count.items():
                res = match_global_tiled(bev, scan, step, shards=tiles)
                row[f"ray_{n}_ms"] = res.ms
                row["same"] &= _answer(res) == _answer(here)
            rows.append(row)
            report("global searches", (j + 1) / len(idx))
    finally:
        shards.close()
    out["scans"] = len(rows)
    out["one_machine_ms_median"] = median(r["one_machine_ms"] for r in rows)
    for n in workers:
        out[f"ray_{n}_ms_median"] = median(r[f"ray_{n}_ms"] for r in rows)
    lo, hi = min(workers), max(workers)
    # per scan, then the median: the machine's load drifts between scans more than within one
    out[f"speedup_{hi}_over_{lo}"] = median(r[f"ray_{lo}_ms"] / r[f"ray_{hi}_ms"] for r in rows)
    out["sharded_equals_one_machine"] = sum(r["same"] for r in rows) / len(rows)
    out["nodes_median"] = median(r["nodes"] for r in rows)
    out["load_avg_end"] = load_avg()
    out["rows"] = rows
    return out


def _answer(res) -> tuple:
    """What must be the same wherever the search ran: pose, score, candidates, the work done."""
    return (res.score, res.x, res.y, res.yaw, res.nodes_expanded, res.candidates.tobytes())
