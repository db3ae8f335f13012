"""The lookup table a run reads from a tiled map: the tiles around its particles, assembled into one
table and moved along with them.

The window covers the particles' bounding box grown by the scan's reach (its farthest point from
the sensor, plus one cell), so every read of the likelihood falls inside it and gives the value
one table over the whole map gives. It is reassembled only when the set of tiles under
that box changes (about once per tile crossed, once localized), so most scans reuse it. The
window is a copy of its tiles: they are unmapped once copied, and the old window goes before the
new one is assembled, so a run holds one window and one tile being copied, never more.
"""

from __future__ import annotations

import numpy as np

from .lookup import LookupTable
from .tiled_lookup import TiledLookup


class TileFollower:
    """One :class:`LookupTable` over the tiles of ``tiled`` around the particles (see the module)."""

    def __init__(self, tiled: TiledLookup):
        self.tiled = tiled
        self.table: LookupTable | None = None
        self.tiles: frozenset = frozenset()
        self.windows = 0  # windows assembled so far

    def follow(self, xy: np.ndarray, reach_m: float) -> LookupTable:
        """The table for particles at ``xy`` (N, ≥2) reading scan points up to ``reach_m`` from
        them: the current one while its tiles are still the ones under them."""
        xy = np.asarray(xy)[:, :2]
        reach = float(reach_m) + self.tiled.resolution
        (x0, y0), (x1, y1) = xy.min(axis=0) - reach, xy.max(axis=0) + reach
        tiles = frozenset(self.tiled.tiles_over(x0, y0, x1, y1))
        if self.table is None or tiles != self.tiles:
            self.tiled.drop_except(())  # the window is a copy: no tile needs to stay mapped
            self.table = None  # the old window goes before the new one is assembled: never two resident
            self.table = self.tiled.window(x0, y0, x1, y1)
            self.tiles = tiles
            self.windows += 1
        return self.table
