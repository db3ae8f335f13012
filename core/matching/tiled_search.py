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
(tests/test_tiles_search.py compares them). A sweep's tiles are visited a few at once, one per
core, each told the best score found before its batch, and their finds are taken in the sweep's
order, so that the result does not depend on which thread finished first.
"""

from __future__ import annotations

import math
import time
from concurrent.futures import ThreadPoolExecutor

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


def match_global_tiled(
    bev: TiledBEV,
    scan_xy: np.ndarray,
    angle_step: float = 2.5 * math.pi / 180.0,
    keep_candidates: int = N_CANDIDATES,
    workers: int | None = None,
) -> MatchResult:
    """Global search over the whole tiled map (see the module docstring): the pose and score
    :func:`~lidarloc.core.matching.m3rsm.match_global` finds on the same map, mapping in only
    the tiles whose bound can beat the best score found. ``workers`` tiles are searched at once
    on as many threads (default: one per core; the branch and bound releases the GIL)."""
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
    shifted: dict = {}

    def cells(dx: int, dy: int, top: int):
        key = (dx, dy, top)
        if key not in shifted:
            sx, sy = cx + dx, cy + dy
            shifted[key] = (sx, sy, level_entries(sx, sy, DENSE_UPTO + 1, top))
        return shifted[key]

    # The best bound left per tile: its coarse bound until it is first visited, then its heap's.
    left = bounds.max(axis=1) if bounds.size else np.full(len(bounds), -math.inf)
    tiles: dict[int, _TileSearch] = {}  # the tiles mapped in
    kept = []
    best, found, nodes, visited = -1.0, None, 0, 0
    workers = usable_cores(workers)
    pool = ThreadPoolExecutor(workers, thread_name_prefix="lidarloc-tiles") if workers > 1 else None

    def visit(i: int, beat: float, above: float):
        return tiles[i].visit(beat, above)

    try:
        while True:
            live = np.flatnonzero(left > best)
            if len(live) == 0:
                break
            highest = float(left[live].max())
            above = (1.0 - SWEEP_SHARE) * highest
            if not above > best or not above < highest:
                above = best  # a last sweep to the end (or scores too small to step through)
            sweep = live[left[live] > above]
            sweep = sweep[np.lexsort((sweep, -left[sweep]))]  # highest bound first, then tile index
            for pos in range(0, len(sweep), workers):
                batch = [int(i) for i in sweep[pos : pos + workers]]
                beat = best
                # tiles not yet mapped in are created here, in the sweep's order, not on the threads
                for i in batch:
                    if i not in tiles:
                        tiles[i] = _TileSearch(bev, i, cells, reach, keep)
                        visited += 1
                if pool is None or len(batch) == 1:
                    results = [visit(i, beat, above) for i in batch]
                else:
                    results = list(pool.map(visit, batch, [beat] * len(batch), [above] * len(batch)))
                for i, (leaf, expanded, rest) in zip(batch, results):
                    nodes += expanded
                    left[i] = rest
                    if leaf is not None and leaf[0] > best:
                        best, found = leaf[0], leaf
                    if rest <= best:  # nothing left in this tile can beat the best: let it go
                        kept.append(tiles.pop(i).kept())
    finally:
        if pool is not None:
            pool.shutdown()
    kept += [s.kept() for s in tiles.values()]
    ts = np.concatenate([k[0] for k in kept]) if kept else np.zeros(0)
    order = np.argsort(-ts, kind="stable")[:keep]
    tr, tx, ty = (np.concatenate([k[j] for k in kept])[order] if kept else np.zeros(0, np.int64) for j in (1, 2, 3))
    # the same arithmetic as match_global's candidates and optimum, so the first equals it exactly
    candidates = np.column_stack(
        [anchor[0] + tx * d, anchor[1] + ty * d, _wrap(angles[tr.astype(np.int64)]), ts[order]]
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
