"""The map's ground height under a position, for the z of a match whose start gives none (a
whole-map match, or a start whose attitude is not trusted): from the map's points in memory
(:class:`GroundGrid`) or from a map held as point tiles (:class:`TiledGround`)."""

from __future__ import annotations

import math

import numpy as np


class GroundGrid:
    """Lowest map z per d_m cell, for a z guess in global mode (no start pose to take it from)."""

    def __init__(self, points: np.ndarray, resolution: float):
        xy = np.asarray(points[:, :2], np.float64)
        self.res = float(resolution)
        idx = np.floor(xy / self.res).astype(np.int64)
        self.lo = idx.min(axis=0)
        idx -= self.lo
        shape = tuple((idx.max(axis=0) + 1).tolist())
        self.zmin = np.full(shape, np.inf, np.float32)
        np.minimum.at(self.zmin, (idx[:, 0], idx[:, 1]), np.asarray(points[:, 2], np.float32))

    def height(self, x: float, y: float, radius_cells: int = 2) -> float:
        """Median of the per-cell minima around (x, y); a median shrugs off the odd point below the
        road (reflections) and cells whose lowest point is a car roof."""
        i = int(math.floor(x / self.res)) - int(self.lo[0])
        j = int(math.floor(y / self.res)) - int(self.lo[1])
        # clipped at 0 on both ends: a negative stop would count from the grid's far end
        win = self.zmin[
            max(i - radius_cells, 0) : max(i + radius_cells + 1, 0),
            max(j - radius_cells, 0) : max(j + radius_cells + 1, 0),
        ]
        vals = win[np.isfinite(win)]
        return float(np.median(vals)) if len(vals) else math.nan


class TiledGround:
    """:class:`GroundGrid`'s heights from a map held as point tiles: the cells around (x, y)
    from the points under them, read when asked (a global match asks once)."""

    def __init__(self, tiles, resolution: float):
        self.tiles = tiles
        self.res = float(resolution)

    def height(self, x: float, y: float, radius_cells: int = 2) -> float:
        r = self.res
        i, j = math.floor(x / r), math.floor(y / r)
        x0, y0 = (i - radius_cells) * r, (j - radius_cells) * r
        side = (2 * radius_cells + 1) * r
        pts = self.tiles.points_in(x0, y0, x0 + side, y0 + side)
        ci = np.floor(pts[:, 0].astype(np.float64) / r).astype(np.int64) - (i - radius_cells)
        cj = np.floor(pts[:, 1].astype(np.float64) / r).astype(np.int64) - (j - radius_cells)
        n = 2 * radius_cells + 1
        inside = (ci >= 0) & (ci < n) & (cj >= 0) & (cj < n)  # the rectangle's far edges are closed
        zmin = np.full((n, n), np.inf, np.float32)
        np.minimum.at(zmin, (ci[inside], cj[inside]), pts[inside, 2])
        vals = zmin[np.isfinite(zmin)]
        return float(np.median(vals)) if len(vals) else math.nan
