"""Where the map has points (the ``map_support`` start, ``pf.init_mode``): a 2-D grid of the
occupied cells with a ground height in each, to draw particles only where a vehicle can be."""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from ..errors import LidarlocError


@dataclass
class SupportGrid:
    """Where the map has points, on a 2-D grid, with a ground height per occupied cell."""

    cell: float
    origin: np.ndarray  # (2,) x, y of cell (0, 0)'s corner
    cells: np.ndarray  # (K, 2) int64 occupied cell indices
    ground_z: np.ndarray  # (K,) low percentile of the map's z in each cell

    @classmethod
    def from_points(cls, points: np.ndarray, cell: float = 2.0, ground_percentile: float = 5.0) -> SupportGrid:
        pts = np.asarray(points)[:, :3].astype(np.float64)
        if len(pts) == 0:
            raise LidarlocError("map_support init needs a non-empty map")
        origin = pts[:, :2].min(axis=0)
        ij = np.floor((pts[:, :2] - origin) / cell).astype(np.int64)
        key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
        order = np.lexsort((pts[:, 2], key))  # by cell, then by z inside the cell
        key_sorted = key[order]
        starts = np.flatnonzero(np.r_[True, key_sorted[1:] != key_sorted[:-1]])
        counts = np.diff(np.r_[starts, len(key_sorted)])
        pick = starts + np.floor(ground_percentile / 100.0 * (counts - 1)).astype(np.int64)
        return cls(cell=float(cell), origin=origin, cells=ij[order[starts]], ground_z=pts[order[pick], 2])

    def sample(self, rng: np.random.Generator, n: int, region=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x, y uniform over occupied cells (optionally those meeting the rectangle
        (x0, y0, x1, y1), then drawn inside cell ∩ rectangle); z = the cell's ground height.
        Returns None if no occupied cell meets the region."""
        lo = self.origin + self.cells * self.cell
        hi = lo + self.cell
        if region is not None:
            x0, y0, x1, y1 = region
            lo = np.maximum(lo, [x0, y0])
            hi = np.minimum(hi, [x1, y1])
            keep = np.all(hi > lo, axis=1)
            if not keep.any():
                return None
            idx_pool = np.flatnonzero(keep)
        else:
            idx_pool = np.arange(len(self.cells))
        pick = idx_pool[rng.integers(0, len(idx_pool), n)]
        xy = lo[pick] + rng.random((n, 2)) * (hi[pick] - lo[pick])
        return xy[:, 0], xy[:, 1], self.ground_z[pick]


_CACHE: dict[int, tuple] = {}


def support_for(points: np.ndarray) -> SupportGrid:
    """SupportGrid.from_points, remembered per map array: the localizer makes a new filter on
    every restart, and sorting a large map by cell takes seconds."""
    key = id(points)
    hit = _CACHE.get(key)
    if hit is not None and hit[0]() is points:
        return hit[1]
    grid = SupportGrid.from_points(points)
    for k in [k for k, (ref, _) in _CACHE.items() if ref() is None]:
        del _CACHE[k]
    try:
        _CACHE[key] = (weakref.ref(points), grid)
    except TypeError:  # not weak-referenceable (e.g. a list): just don't cache
        pass
    return grid
