"""The exact global search over a whole city: M3RSM's branch and bound on a tiled BEV pyramid
(:class:`~lidarloc.core.maps.tiled_bev.TiledBEV`), with only the coarse levels in memory.

The search space is :func:`~lidarloc.core.matching.m3rsm.match_global`'s: every L0 cell centre of
the map as sensor position, every lattice angle. Its translations are cut along the pyramid's
tiles (2^k × 2^k lattice positions each). For a tile and an angle, a scan point placed at the
tile's translations visits a 2^k-cell run of L0 per axis, which lies in at most 2 × 2 cells of
level k (the coarse level held in memory, one cell per tile); the largest of those cells bounds
the point, and the sum over the scan's points bounds every pose in the tile (the strided bound of
:mod:`.m3rsm` at level k). Tiles are then searched best bound first, each with M3RSM's own
branch and bound on its L0 (mapped in from its file, with the neighbouring tiles' cells a scan
can reach) and told the best score so far, so it prunes against it; the search stops at the
first tile whose bound cannot beat that score. Tiles are searched a few at once, one per core,
each batch told the best score of the batches before it and merged in tile order, so that the
result does not depend on which thread finished first. No pose is pruned whose score could be
higher than the one returned, so the optimum is the whole-map search's
(tests/test_tiles_search.py compares them).
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
from .bnb_kernels import _angle_cells
from .m3rsm import N_CANDIDATES, MatchResult, _wrap, angle_lattice, scan_cells, search_cells


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
    t = bev.tile_cells
    bounds = _tile_bounds(bev.coarse[0], cx, cy, bev.tile_level, bev.ntx, bev.nty)
    tile_bound = bounds.max(axis=1) if bounds.size else np.zeros(len(bounds))
    order = np.argsort(-tile_bound, kind="stable")
    lo_x, hi_x = (int(cx.min()), int(cx.max())) if cx.size else (0, 0)
    lo_y, hi_y = (int(cy.min()), int(cy.max())) if cy.size else (0, 0)

    def search_tile(i: int, beat: float):
        """Tile i's own branch and bound over the angles whose bound can beat ``beat``: its best
        pose strictly above ``beat`` (on the city's grid), or None, and its result."""
        sel = np.flatnonzero(bounds[i] > beat)
        tx, ty = divmod(int(i), bev.nty)
        kx0, ky0 = tx * t, ty * t
        kx1, ky1 = min(kx0 + t, nx) - 1, min(ky0 + t, ny) - 1
        # the L0 cells this tile's translations can reach, clipped to the grid (beyond it: empty)
        wx0, wy0 = max(kx0 + lo_x, 0), max(ky0 + lo_y, 0)
        wx1, wy1 = max(min(kx1 + hi_x + 1, nx), wx0 + 1), max(min(ky1 + hi_y + 1, ny), wy0 + 1)
        pyr = bev.window(wx0, wy0, wx1, wy1)
        local_anchor = (anchor[0] + kx0 * d, anchor[1] + ky0 * d)
        res = search_cells(
            pyr, cx[sel] + (kx0 - wx0), cy[sel] + (ky0 - wy0), local_anchor, angles[sel], (0, 0), (kx1 - kx0, ky1 - ky0),
            beat=beat, keep=keep_candidates,
        )  # fmt: skip
        c = res.candidates.copy()
        if len(c):
            k = np.rint((c[:, :2] - np.array(local_anchor)) / d) + np.array([kx0, ky0])
            c[:, 0], c[:, 1] = anchor[0] + k[:, 0] * d, anchor[1] + k[:, 1] * d
        pose = None
        if not math.isnan(res.x) and res.score > beat:
            kx = int(round((res.x - local_anchor[0]) / d)) + kx0
            ky = int(round((res.y - local_anchor[1]) / d)) + ky0
            pose = (anchor[0] + kx * d, anchor[1] + ky * d, res.yaw)
        return pose, res, c

    # Tiles in batches of `workers`, best bound first, every tile of a batch told the best score
    # of the batches before it; a batch's results are merged in tile order, so the outcome does not
    # depend on which thread finished first.
    best, found, nodes, searched = -1.0, None, 0, 0
    cands = []
    workers = usable_cores(workers)
    pool = ThreadPoolExecutor(workers, thread_name_prefix="lidarloc-tiles") if workers > 1 else None
    try:
        pos = 0
        while pos < len(order) and tile_bound[order[pos]] > best:
            batch = [int(i) for i in order[pos : pos + workers] if tile_bound[i] > best]
            pos += workers
            beat = best
            if pool is None:
                results = [search_tile(i, beat) for i in batch]
            else:
                results = list(pool.map(search_tile, batch, [beat] * len(batch)))
            for pose, res, c in results:
                searched += 1
                nodes += res.nodes_expanded
                if len(c):
                    cands.append(c)
                if pose is not None and res.score > best:
                    best, found = res.score, pose
    finally:
        if pool is not None:
            pool.shutdown()
    candidates = np.concatenate(cands) if cands else np.zeros((0, 4))
    candidates = candidates[np.argsort(-candidates[:, 3], kind="stable")][:keep_candidates]
    common = dict(
        nodes_expanded=int(nodes),
        ms=(time.perf_counter() - t0) * 1e3,
        n_points=len(B),
        region=(anchor[0], anchor[1], anchor[0] + (nx - 1) * d, anchor[1] + (ny - 1) * d),
        n_angles=len(angles),
        candidates=candidates,
        nodes_per_level=(searched,),
    )
    if found is None:
        return MatchResult(x=math.nan, y=math.nan, yaw=math.nan, score=float(best), **common)
    return MatchResult(x=float(found[0]), y=float(found[1]), yaw=float(_wrap(found[2])), score=float(best), **common)
