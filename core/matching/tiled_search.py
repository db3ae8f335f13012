"""The exact global search over a whole city: M3RSM's branch and bound on a tiled BEV pyramid
(:class:`~lidarloc.core.maps.tiled_bev.TiledBEV`), with only the coarse levels in memory.

The search space is :func:`~lidarloc.core.matching.m3rsm.match_global`'s: every L0 cell centre of
the map as sensor position, every lattice angle. Its translations are cut along the pyramid's
tiles (2^k × 2^k lattice positions each). For a tile and an angle, a scan point placed at the
tile's translations visits a 2^k-cell run of L0 per axis, which lies in at most 2 × 2 cells of
level k (the coarse level held in memory, one cell per tile); the largest of those cells bounds
the point, and the sum over the scan's points bounds every pose in the tile (the strided bound of
:mod:`.m3rsm` at level k).

Inside a tile the search is M3RSM's own best-first branch and bound, on the tile's L0 mapped in
from its file with the neighbouring tiles' cells a scan can reach. To expand the blocks the
whole-map search expands, and not each tile's own runners-up, the tiles' searches are run as one
best-first search: every tile keeps its heap between visits, and the search goes in sweeps, each
of which takes the tiles whose best bound lies within 1 % of the highest one left and expands
their blocks down to that threshold (a block below it stays on its tile's heap for a later
sweep). A tile is mapped in at its first visit and let go once nothing on its heap can beat the
best score found; the search stops when no tile's bound beats it. Only the order in which blocks are
expanded differs from the whole-map search, never what is pruned: no block is dropped whose
bound beats the best score found, so the optimum is the whole-map search's
(tests/test_tiles_search.py compares them).

Every tile of a sweep is told the best score found before the sweep, and the sweep's finds are
taken in its order (highest bound first, then tile index), a strictly higher score replacing the
best. So the tiles of a sweep can be searched in any order, at once, on threads or on other
machines (:mod:`.shards`), and the pose, score and candidates are the same whatever searched
them, even where two poses tie: nothing depends on which search finished first. What it could cost:
a tile that finds a better leaf does not prune the other tiles of its sweep, which may expand
blocks between the old and the new best score, within the sweep's 1 %; on 8 scans of the 1 km²
city it expanded exactly the blocks of a search that told each tile the newest best score.
"""

from __future__ import annotations

import math
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Protocol

import numba as nb
import numpy as np

from ..errors import LidarlocError
from ..maps.tiled_bev import TiledBEV
from ..maps.tiling import usable_cores
from .bnb_kernels import _angle_cells, _bnb_expand, _bnb_roots, level_entries
from .m3rsm import DENSE_UPTO, N_CANDIDATES, MatchResult, _prepared, _top_level, _wrap, angle_lattice, scan_cells

#: A sweep takes the tiles whose best bound lies within this share of the highest one left.
SWEEP_SHARE = 0.01


@nb.njit(cache=True, nogil=True, parallel=True)
def _tile_bounds(Lk, cx, cy, level, ntx, nty):
    """(ntx · nty, R) upper bound of the L0 score over every translation of each tile, per angle."""
    R, K = cx.shape
    nkx, nky = Lk.shape
    t = np.int64(1) << level
    out = np.zeros((ntx * nty, R), np.float64)
    for i in nb.prange(ntx * nty):
        tx = i // nty
        ty = i % nty
        for r in range(R):
            s = 0.0
            for j in range(K):
                ax = cx[r, j] + tx * t
                ay = cy[r, j] + ty * t
                m = 0.0
                for X in ((ax >> level), ((ax + t - 1) >> level)):
                    if X < 0 or X >= nkx:
                        continue
                    for Y in ((ay >> level), ((ay + t - 1) >> level)):
                        if Y >= 0 and Y < nky and Lk[X, Y] > m:
                            m = Lk[X, Y]
                s += m
            out[i, r] = s
    return out


class _TileSearch:
    """One tile's branch and bound, kept between visits: the kernels' view of its window (the
    tile's L0 and the cells around it a scan can reach) and its heap."""

    def __init__(self, bev: TiledBEV, i: int, cells, reach, keep: int):
        t = bev.tile_cells
        nx, ny = bev.shape
        tx, ty = divmod(int(i), bev.nty)
        self.kx0, self.ky0 = tx * t, ty * t
        self.kx1, self.ky1 = min(self.kx0 + t, nx) - 1 - self.kx0, min(self.ky0 + t, ny) - 1 - self.ky0
        (lo_x, hi_x), (lo_y, hi_y) = reach
        # the L0 cells this tile's translations can reach, clipped to the grid (beyond it: empty)
        wx0, wy0 = max(self.kx0 + lo_x, 0), max(self.ky0 + lo_y, 0)
        wx1 = max(min(self.kx0 + self.kx1 + hi_x + 1, nx), wx0 + 1)
        wy1 = max(min(self.ky0 + self.ky1 + hi_y + 1, ny), wy0 + 1)
        pyramid = bev.window(wx0, wy0, wx1, wy1)
        self.prep = _prepared(pyramid, DENSE_UPTO)
        self.top = _top_level(self.prep.n_levels, self.kx1 + 1, self.ky1 + 1)
        # the scan's cells on the window's grid: tiles at the same offset share them
        self.cx, self.cy, self.entries = cells(self.kx0 - wx0, self.ky0 - wy0, self.top)
        self.keep = keep
        self.state = None  # (heap arrays, size, kept leaves, their count, nodes per level)

    def _kernel_args(self):
        p = self.prep
        return (p.L0, p.G, p.gnx, p.gny, p.goff, p.S, p.snx, p.sny, p.soff, DENSE_UPTO, self.cx, self.cy, *self.entries)

    def visit(self, best: float, above: float):
        """Expand this tile's blocks whose bound beats ``best`` and ``above``: (its best leaf if
        strictly better than ``best`` as (score, r, kx, ky) on the city's lattice, else None;
        nodes expanded; the best bound left on its heap, −inf if none)."""
        found = None
        region = (0, self.kx1, 0, self.ky1)
        if self.state is None:
            out = _bnb_roots(*self._kernel_args(), self.top, *region, best, self.keep)
            if out[1] >= 0:
                best, found = out[0], (out[0], out[1], out[2], out[3])
            self.state = out[4:]
        hs, hl, hr, hx, hy, n, ts, tr, tx, ty, m, per_level = self.state
        out = _bnb_expand(
            *self._kernel_args(), *region, best, hs, hl, hr, hx, hy, n, ts, tr, tx, ty, m, per_level, above
        )
        if out[1] >= 0:
            found = (out[0], out[1], out[2], out[3])
        hs, hl, hr, hx, hy, n, m = *out[4:10], out[10]
        self.state = (hs, hl, hr, hx, hy, n, ts, tr, tx, ty, m, per_level)
        if found is not None:
            found = (found[0], found[1], found[2] + self.kx0, found[3] + self.ky0)
        return found, int(out[11]), (float(hs[0]) if n > 0 else -math.inf)

    def kept(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The best leaves this tile scored: (scores, r, kx, ky) on the city's lattice."""
        if self.state is None:
            return np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
        ts, tr, tx, ty, m = self.state[6:11]
        return ts[:m], tr[:m], tx[:m] + self.kx0, ty[:m] + self.ky0


class TileShard:
    """Some of a city's tiles searched for one scan (its cells ``cx``, ``cy`` on the city's grid
    at translation 0, per angle): each tile's search made at its first visit and kept between
    sweeps, and the best leaves of the tiles let go. One holds every tile on one machine; a
    sharded search (:mod:`.shards`) gives each shard one."""

    def __init__(self, bev: TiledBEV, cx: np.ndarray, cy: np.ndarray, reach, keep: int):
        self.bev, self.cx, self.cy, self.reach, self.keep = bev, cx, cy, reach, int(keep)
        self._shifted: dict = {}
        self.tiles: dict[int, _TileSearch] = {}  # the tiles mapped in
        self.released: dict[int, tuple] = {}  # the best leaves of the tiles let go

    def _cells(self, dx: int, dy: int, top: int):
        """The scan's cells shifted onto a window's grid: tiles at the same offset share them."""
        key = (dx, dy, top)
        if key not in self._shifted:
            sx, sy = self.cx + dx, self.cy + dy
            self._shifted[key] = (sx, sy, level_entries(sx, sy, DENSE_UPTO + 1, top))
        return self._shifted[key]

    def open(self, tiles) -> None:
        """Map in the tiles not yet visited, in the order given."""
        for i in tiles:
            if i not in self.tiles and i not in self.released:
                self.tiles[i] = _TileSearch(self.bev, i, self._cells, self.reach, self.keep)

    def visit(self, i: int, beat: float, above: float):
        return self.tiles[i].visit(beat, above)

    def release(self, tiles) -> None:
        """Let go of tiles nothing on whose heap can beat the best score: keep their best leaves."""
        for i in tiles:
            if i in self.tiles:
                self.released[i] = self.tiles.pop(i).kept()

    def sweep(self, tiles, beat: float, above: float, release=()) -> list:
        """Let go of ``release``, then visit ``tiles`` one after another, each told ``beat``: per
        tile (its best leaf if strictly better than ``beat``, nodes expanded, best bound left)."""
        self.release(release)
        self.open(tiles)
        return [self.visit(i, beat, above) for i in tiles]

    def kept(self) -> tuple[dict[int, tuple], int]:
        """Every tile's best leaves (scores, r, kx, ky on the city's lattice) by tile, and how many
        tiles were mapped in."""
        out = dict(self.released)
        out.update((i, s.kept()) for i, s in self.tiles.items())
        return out, len(out)


class TileVisits(Protocol):
    """Who searches the tiles: :class:`_LocalTiles` on this machine's threads, or
    :class:`~lidarloc.core.matching.shards.ShardedTiles` over shards anywhere."""

    def start(self, cx: np.ndarray, cy: np.ndarray, reach, keep: int) -> None: ...

    def sweep(self, tiles: list[int], beat: float, above: float, release: list[int]) -> list: ...

    def kept(self) -> tuple[dict[int, tuple], int]: ...


class _LocalTiles:
    """Every tile in this process, a sweep's tiles visited ``workers`` at once on threads (the
    branch and bound releases the GIL); tiles are mapped in on the calling thread, in the sweep's
    order."""

    def __init__(self, bev: TiledBEV, workers: int):
        self.bev, self.workers = bev, workers
        self.shard: TileShard | None = None

    def start(self, cx, cy, reach, keep: int) -> None:
        self.shard = TileShard(self.bev, cx, cy, reach, keep)

    def sweep(self, tiles, beat, above, release) -> list:
        shard = self.shard
        assert shard is not None
        shard.release(release)
        shard.open(tiles)
        if self.workers <= 1 or len(tiles) == 1:
            return [shard.visit(i, beat, above) for i in tiles]
        with ThreadPoolExecutor(min(self.workers, len(tiles)), thread_name_prefix="lidarloc-tiles") as pool:
            return list(pool.map(lambda i: shard.visit(i, beat, above), tiles))

    def kept(self):
        assert self.shard is not None
        out, self.shard = self.shard.kept(), None
        return out


def match_global_tiled(
    bev: TiledBEV,
    scan_xy: np.ndarray,
    angle_step: float = 2.5 * math.pi / 180.0,
    keep_candidates: int = N_CANDIDATES,
    workers: int | None = None,
    shards: TileVisits | None = None,
) -> MatchResult:
    """Global search over the whole tiled map (see the module docstring): the pose and score
    :func:`~lidarloc.core.matching.m3rsm.match_global` finds on the same map, mapping in only
    the tiles whose bound can beat the best score found. ``workers`` tiles are searched at once
    on as many threads (default: one per core; the branch and bound releases the GIL);
    ``shards``: the tiles are searched there instead (:class:`~.shards.ShardedTiles`), with the
    same result."""
    if angle_step <= 0:
        raise LidarlocError(f"angle_step must be > 0, got {angle_step}")
    t0 = time.perf_counter()
    d = bev.resolution
    nx, ny = bev.shape
    anchor = (float(bev.origin[0]) + 0.5 * d, float(bev.origin[1]) + 0.5 * d)
    angles = angle_lattice(angle_step)
    B = scan_cells(scan_xy, d)
    # the cells of match_global's angle_cells: anchor minus origin, the same arithmetic
    ax, ay = anchor[0] - float(bev.origin[0]), anchor[1] - float(bev.origin[1])
    cx, cy = _angle_cells(np.ascontiguousarray(B, np.float64), np.cos(angles), np.sin(angles), ax, ay, 1.0 / d)
    keep = int(keep_candidates)
    if keep < 0:
        raise LidarlocError(f"keep_candidates must be ≥ 0, got {keep}")
    bounds = _tile_bounds(bev.coarse[0], cx, cy, bev.tile_level, bev.ntx, bev.nty)
    reach = ((int(cx.min()), int(cx.max())), (int(cy.min()), int(cy.max()))) if cx.size else ((0, 0), (0, 0))
    visits = _LocalTiles(bev, usable_cores(workers)) if shards is None else shards
    # The best bound left per tile: its coarse bound until it is first visited, then its heap's.
    left = bounds.max(axis=1) if bounds.size else np.full(len(bounds), -math.inf)
    visits.start(cx, cy, reach, keep)
    best, found, nodes, release = -1.0, None, 0, []
    opened: set[int] = set()  # tiles mapped in and not let go
    while True:
        live = np.flatnonzero(left > best)
        if len(live) == 0:
            break
        highest = float(left[live].max())
        above = (1.0 - SWEEP_SHARE) * highest
        if not above > best or not above < highest:
            above = best  # a last sweep to the end (or scores too small to step through)
        sweep = live[left[live] > above]
        sweep = [int(i) for i in sweep[np.lexsort((sweep, -left[sweep]))]]  # highest bound first, then index
        results = visits.sweep(sweep, best, above, release)
        opened.update(sweep)
        for i, (leaf, expanded, rest) in zip(sweep, results):
            nodes += expanded
            left[i] = rest
            if leaf is not None and leaf[0] > best:
                best, found = leaf[0], leaf
        release = sorted(i for i in opened if left[i] <= best)  # nothing left there can beat the best
        opened.difference_update(release)
    kept_by_tile, visited = visits.kept()
    kept = [kept_by_tile[i] for i in sorted(kept_by_tile)]
    ts, tr, tx, ty = (
        np.concatenate([k[j] for k in kept]) if kept else np.zeros(0, np.float64 if j == 0 else np.int64)
        for j in range(4)
    )
    # best first; among equal scores the optimum first, then by tile and as the tile kept them
    is_found = np.zeros(len(ts), bool) if found is None else (tr == found[1]) & (tx == found[2]) & (ty == found[3])
    order = np.lexsort((np.arange(len(ts)), ~is_found, -ts))[:keep]
    ts, tr, tx, ty = ts[order], tr[order], tx[order], ty[order]
    # the same arithmetic as match_global's candidates and optimum, so the first equals it exactly
    candidates = np.column_stack(
        [anchor[0] + tx * d, anchor[1] + ty * d, _wrap(angles[tr.astype(np.int64)]), ts]
    ).reshape(-1, 4)
    common = dict(
        nodes_expanded=int(nodes),
        ms=(time.perf_counter() - t0) * 1e3,
        n_points=len(B),
        region=(anchor[0], anchor[1], anchor[0] + (nx - 1) * d, anchor[1] + (ny - 1) * d),
        n_angles=len(angles),
        candidates=candidates,
        nodes_per_level=(visited,),
    )
    if found is None:
        return MatchResult(x=math.nan, y=math.nan, yaw=math.nan, score=float(best), **common)
    _, r, kx, ky = found
    return MatchResult(
        x=float(anchor[0] + kx * d),
        y=float(anchor[1] + ky * d),
        yaw=float(_wrap(angles[r])),
        score=float(best),
        **common,
    )
