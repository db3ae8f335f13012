"""The exact tiled global search (:mod:`.tiled_search`) with its tiles spread over shards: other
processes or other machines, each holding some of the city's tiles and searching them.

A shard is a :class:`ShardHost`: the city's tiled pyramid opened from its cache directory (every
shard reads the tiles it searches from there, memory-mapped; nothing of the map is shipped), and
for the scan being matched a :class:`~.tiled_search.TileShard`. :class:`ShardedTiles` is the
search's side: it splits each sweep's tiles among the shards, has every shard search its own at
once, and hands the finds back in the sweep's order. How a call reaches a shard is the caller's
``run``, a plain function, so this module knows nothing of threads, process pools or Ray
(``lidarloc.app.bench.shards`` runs the shards on Ray; :func:`in_process` here, for tests and as
the reference).

Why the result is the one-machine search's, pose, score and candidates alike, even where two
poses tie: the tiled search tells every tile of a sweep the best score found before the sweep
and takes the sweep's finds in its own order, never in the order the tiles finished; a tile's
search depends only on the scores it is told. Splitting a sweep among shards changes who
searches a tile, not what it is told or the order its find is taken in.

Why a tile stays on one shard: its search keeps its heap between sweeps (the blocks below the
sweep's threshold), up to tens of MB, so the tile is pinned to the shard that first searched it
and later sweeps send it there. A tile met for the first time goes to the shard with the least
work in this sweep so far, counting for a tile already pinned the nodes it expanded in its last
visit; the busiest tiles are not known before they are searched, so the balance is good, not
perfect: on 8 scans of the 1 km² city (25 tiles, 7–50 sweeps a scan) the nodes of the busiest of
2 shards, summed over the sweeps, allow a speed-up of 1.87–1.93× over one shard.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..maps.tiled_bev import TiledBEV
from .tiled_search import TileShard

#: run(calls) → results: every call (shard index, method name, arguments) made on that shard's
#: :class:`ShardHost`, the calls at once, the results in the calls' order.
Run = Callable[[list[tuple[int, str, tuple]]], list]


def cache_spec(bev: TiledBEV) -> tuple:
    """What a shard needs to open ``bev`` from its cache directory: (directory, index, coarse
    levels), a few kB to hundreds of kB (the tiles' checksums and one cell a tile)."""
    return (str(bev.directory), bev.index, bev.coarse)


class ShardHost:
    """One shard: the tiled pyramid (a :class:`TiledBEV` or its :func:`cache_spec`) and the tiles
    of the scan being matched that this shard searches."""

    def __init__(self, bev: TiledBEV | tuple):
        if not isinstance(bev, TiledBEV):
            directory, index, coarse = bev
            bev = TiledBEV(directory, index, [np.asarray(c, np.float32) for c in coarse])
        self.bev = bev
        self.shard: TileShard | None = None

    def start(self, cx: np.ndarray, cy: np.ndarray, reach, keep: int) -> None:
        """A new scan: its cells on the city's grid at translation 0, per angle."""
        self.shard = TileShard(self.bev, cx, cy, reach, keep)

    def sweep(self, tiles: list[int], beat: float, above: float, release: list[int]) -> list:
        assert self.shard is not None, "start() first"
        return self.shard.sweep(tiles, beat, above, release)

    def kept(self) -> tuple[dict[int, tuple], int]:
        """The scan's kept leaves by tile and the tiles mapped in; the scan's tiles let go."""
        assert self.shard is not None, "start() first"
        out, self.shard = self.shard.kept(), None
        return out


def split_sweep(tiles: Sequence[int], owner: dict[int, int], work: dict[int, int], n_shards: int) -> list[list[int]]:
    """Each shard's tiles of a sweep, in the sweep's order. A tile already in ``owner`` goes to
    its shard; a new one to the shard with the least work so far in this sweep (``work``: nodes
    a pinned tile expanded last time; a new tile counts as the largest of those, or 1), the
    lowest index on a tie, and is entered in ``owner``."""
    per: list[list[int]] = [[] for _ in range(n_shards)]
    load = [0] * n_shards
    new_cost = max(max(work.values(), default=0), 1)
    for i in tiles:
        if i in owner:
            load[owner[i]] += work.get(i, new_cost)
    for i in tiles:
        if i not in owner:
            s = min(range(n_shards), key=lambda j: (load[j], j))
            owner[i] = s
            load[s] += new_cost
        per[owner[i]].append(i)
    return per


class ShardedTiles:
    """The tiled search's tile visits (:class:`~.tiled_search.TileVisits`) spread over
    ``n_shards`` shards that ``run`` reaches (see :data:`Run`). Pass it as
    ``match_global_tiled(..., shards=…)``; one instance serves one search at a time."""

    def __init__(self, n_shards: int, run: Run):
        if n_shards < 1:
            raise ValueError(f"n_shards must be ≥ 1, got {n_shards}")
        self.n_shards, self.run = int(n_shards), run
        self.owner: dict[int, int] = {}
        self.work: dict[int, int] = {}
        self.calls = 0  # calls made during the last search (one per shard per sweep and at its ends)

    def start(self, cx, cy, reach, keep: int) -> None:
        self.owner, self.work, self.calls = {}, {}, self.n_shards
        self.run([(s, "start", (cx, cy, reach, keep)) for s in range(self.n_shards)])

    def sweep(self, tiles, beat, above, release) -> list:
        per = split_sweep(tiles, self.owner, self.work, self.n_shards)
        gone: list[list[int]] = [[] for _ in range(self.n_shards)]
        for i in release:
            gone[self.owner[i]].append(i)
        calls = [(s, "sweep", (per[s], beat, above, gone[s])) for s in range(self.n_shards) if per[s] or gone[s]]
        self.calls += len(calls)
        found = {}
        for (_, _, args), results in zip(calls, self.run(calls)):
            found.update(zip(args[0], results))
        for i in tiles:
            self.work[i] = int(found[i][1])
        return [found[i] for i in tiles]

    def kept(self) -> tuple[dict[int, tuple], int]:
        self.calls += self.n_shards
        out: dict[int, tuple] = {}
        visited = 0
        for kept, n in self.run([(s, "kept", ()) for s in range(self.n_shards)]):
            out.update(kept)
            visited += n
        return out, visited


def in_process(bev: TiledBEV, n_shards: int, threads: int = 1) -> ShardedTiles:
    """``n_shards`` shards in this process, called on ``threads`` threads at once (1: one after
    another): the sharded search without another process, for tests and as a reference."""
    hosts = [ShardHost(bev) for _ in range(n_shards)]

    def run(calls):
        def call(c):
            s, name, args = c
            return getattr(hosts[s], name)(*args)

        if threads <= 1 or len(calls) <= 1:
            return [call(c) for c in calls]
        with ThreadPoolExecutor(min(threads, len(calls)), thread_name_prefix="lidarloc-shards") as pool:
            return list(pool.map(call, calls))

    return ShardedTiles(n_shards, run)
