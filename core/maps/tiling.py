"""A point cloud cut into square x-y build tiles on a cell grid: each point's cell, and the points
of each tile with a margin around it (one counting sort), so that tiles are built independently
and in parallel (the lookup table's distance transform)."""

from __future__ import annotations

import math
import os

import numba as nb
import numpy as np


def usable_cores(requested: int | None = None) -> int:
    """Threads to build or search tiles on: ``requested`` if given, else the cores this process
    may run on (its CPU affinity, which a container or ``taskset`` narrows below the machine's)."""
    if requested:
        return int(requested)
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)


@nb.njit(nogil=True, cache=True)
def point_cells(pts, lo, res, shape):
    """int32 cell index of every point (clamped into the grid)."""
    out = np.empty((pts.shape[0], 3), np.int32)
    for i in range(pts.shape[0]):
        for a in range(3):
            c = np.int64(math.floor((np.float64(pts[i, a]) - lo[a]) / res))
            out[i, a] = min(max(c, 0), shape[a] - 1)
    return out


@nb.njit(nogil=True, cache=True)
def tile_range(c, pad, tile, nt):
    return max((c - pad) // tile, 0), min((c + pad) // tile, nt - 1)


@nb.njit(nogil=True, cache=True)
def bucket_points(cells, tile, pad, ntx, nty):
    """Indices of the points each tile needs (its own and those within ``pad`` cells of it),
    as CSR (offsets over tiles, flat index list). A point reaches at most 2×2 tiles."""
    n = cells.shape[0]
    offsets = np.zeros(ntx * nty + 1, np.int64)
    for i in range(n):
        tx0, tx1 = tile_range(cells[i, 0], pad, tile, ntx)
        ty0, ty1 = tile_range(cells[i, 1], pad, tile, nty)
        for tx in range(tx0, tx1 + 1):
            for ty in range(ty0, ty1 + 1):
                offsets[tx * nty + ty + 1] += 1
    for t in range(ntx * nty):
        offsets[t + 1] += offsets[t]
    flat = np.empty(offsets[ntx * nty], np.int32)
    fill = offsets[:-1].copy()
    for i in range(n):
        tx0, tx1 = tile_range(cells[i, 0], pad, tile, ntx)
        ty0, ty1 = tile_range(cells[i, 1], pad, tile, nty)
        for tx in range(tx0, tx1 + 1):
            for ty in range(ty0, ty1 + 1):
                t = tx * nty + ty
                flat[fill[t]] = i
                fill[t] += 1
    return offsets, flat
