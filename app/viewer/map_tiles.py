"""The prior map as the viewer sends it when it is too big to send whole at the display voxel (a
city): square tiles, a coarse layer of every tile always shown, and the tiles nearest the
followed pose at the display voxel, chosen nearest first while the points sent stay within the
budget.

Nothing here touches viser: :class:`~.scene_map.MapLayers` turns what this module decides into
scene nodes. The map's points are read where they are, never copied whole: a small index (which
chunks of the point array hold points of which tile) lets one tile be read without scanning the
whole map when the map is stored in spatial order, as a city's survey map is. What is held is
the coarse layer, the tiles shown at full density and, while one is read, that tile.

(core/maps/tiling.py buckets the index of every point by tile: 4 bytes a point, 1.7 GB for a
4 km city's map, which is why the display keeps only the per-chunk index.)
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

import numba as nb
import numpy as np

from ...core.maps.point_tiles import private_mapping
from ...core.maps.voxel_grid import voxel_centroids
from .ground import GroundHeight
from .style import (
    COARSE_MAX_POINTS,
    DISPLAY_BUDGET,
    DISPLAY_TILE_M,
    NEAR_TILE_HYSTERESIS_M,
    NEAR_TILE_RADIUS_M,
    NEAR_TILE_UPDATE_S,
    ROAD_REMOVED_MAX_POINTS,
)

CHUNK = 1 << 18  # points per chunk: the unit of the tile index
SAMPLE_ABOVE = 64  # a coarse layer is thinned from at most about this many times its points


@dataclass(frozen=True)
class TileSettings:
    """How a map too big to send whole is sent (the defaults are the viewer's)."""

    tile_m: float = DISPLAY_TILE_M  # side of a display tile (rounded to whole display voxels)
    budget: int = DISPLAY_BUDGET  # map points sent to a browser at most, every map layer together
    coarse_max: int = COARSE_MAX_POINTS  # the coarse layer of the whole map at most
    road_removed_max: int = ROAD_REMOVED_MAX_POINTS  # the road-removed layer at most (kept coarse)
    radius_m: float = NEAR_TILE_RADIUS_M  # tiles this close to the followed pose at full density …
    hysteresis_m: float = NEAR_TILE_HYSTERESIS_M  # … and those shown until this much farther
    interval_s: float = NEAR_TILE_UPDATE_S  # the choice of tiles is revisited at most this often


# ------------------------------------------------------------------------------------ the grid
@dataclass(frozen=True)
class TileGrid:
    """Square x-y tiles of side ``size`` from (x0, y0); tile ``t`` is column ``t // ny``, row
    ``t % ny``. Points outside the grid belong to the nearest border tile."""

    x0: float
    y0: float
    size: float
    nx: int
    ny: int

    @classmethod
    def covering(cls, lo, hi, size: float) -> TileGrid:
        """The grid over the box lo–hi, its origin on a multiple of ``size`` (so that a tile's
        edges are edges of the display voxels when ``size`` is a whole number of them)."""
        x0 = math.floor(float(lo[0]) / size) * size
        y0 = math.floor(float(lo[1]) / size) * size
        nx = max(1, math.floor((float(hi[0]) - x0) / size) + 1)
        ny = max(1, math.floor((float(hi[1]) - y0) / size) + 1)
        return cls(x0, y0, float(size), nx, ny)

    @property
    def n(self) -> int:
        return self.nx * self.ny

    def tiles_of(self, xy: np.ndarray) -> np.ndarray:
        """The tile of each (x, y) row."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        i = np.clip(np.floor((xy[:, 0] - self.x0) / self.size), 0, self.nx - 1).astype(np.int64)
        j = np.clip(np.floor((xy[:, 1] - self.y0) / self.size), 0, self.ny - 1).astype(np.int64)
        return i * self.ny + j

    def rect(self, t: int) -> tuple[float, float, float, float]:
        """(x0, y0, x1, y1) of tile ``t``."""
        i, j = divmod(int(t), self.ny)
        x, y = self.x0 + i * self.size, self.y0 + j * self.size
        return x, y, x + self.size, y + self.size

    def name(self, t: int) -> str:
        i, j = divmod(int(t), self.ny)
        return f"t{i}_{j}"

    def distances(self, x: float, y: float) -> np.ndarray:
        """Distance from (x, y) to every tile's square (0 inside it), by tile."""
        i = np.arange(self.nx)
        j = np.arange(self.ny)
        lo_x, lo_y = self.x0 + i * self.size, self.y0 + j * self.size
        dx = np.maximum(np.maximum(lo_x - x, x - (lo_x + self.size)), 0.0)
        dy = np.maximum(np.maximum(lo_y - y, y - (lo_y + self.size)), 0.0)
        return np.hypot(dx[:, None], dy[None, :]).ravel()


# ------------------------------------------------------------------------- which tiles, pure
def candidates(grid: TileGrid, x: float, y: float, shown: Iterable[int], radius: float, hysteresis: float) -> list:
    """The tiles that may be shown at full density for a pose at (x, y), nearest first: those
    within ``radius``, and those already shown within ``radius + hysteresis`` (a tile shown is
    ranked ``hysteresis`` nearer than it is, so that a vehicle going back and forth across a
    boundary does not swap tiles every time)."""
    d = grid.distances(float(x), float(y))
    shown = np.fromiter((int(t) for t in shown), np.int64)
    if len(shown):
        d[shown] -= hysteresis
    idx = np.flatnonzero(d <= radius)
    return idx[np.lexsort((idx, d[idx]))].tolist()


def fit(order: Iterable[int], counts: Mapping[int, int], budget: int) -> tuple[list, int | None]:
    """The tiles of ``order`` taken nearest first while their points (``counts``) fit in
    ``budget``; it stops at the first that does not fit. Returns (tiles, None), or (tiles so
    far, the first tile whose count is not known yet: read it and ask again)."""
    chosen, total = [], 0
    for t in order:
        n = counts.get(t)
        if n is None:
            return chosen, t
        if total + n > budget:
            break
        chosen.append(t)
        total += n
    return chosen, None


def thin(points: np.ndarray, max_points: int, voxel: float, map_voxel: float) -> tuple[np.ndarray, float]:
    """At most ``max_points`` centroids of ``points`` on a voxel of at least ``voxel``, grown
    until they fit. The first voxel tried is guessed from the count (surfaces sampled at
    ``map_voxel`` thin as the square of the voxel) so that one pass over a big map yields a few
    times ``max_points``; the centroids are then thinned again, on a voxel grown as the square
    root of the excess. Of a map more than ``SAMPLE_ABOVE`` times ``max_points`` only every k-th
    point is read (k keeps ~that many): a voxel of the result then still averages dozens of
    points, and a 4 km city's coarse layer takes seconds instead of a minute. Returns (points,
    voxel)."""
    if len(points) == 0:
        return np.zeros((0, 3), np.float32), voxel
    v = max(voxel, map_voxel * math.sqrt(len(points) / (4.0 * max_points)))
    points = points[:: max(1, len(points) // (SAMPLE_ABOVE * max_points))]
    while (c := voxel_centroids(points, v, cap=8 * max_points)) is None:
        v *= 2.0
    while len(c) > max_points:
        v *= max(1.25, 1.05 * math.sqrt(len(c) / max_points))
        c = voxel_centroids(c, v)
        assert c is not None
    return c, v


# ------------------------------------------------------------------------------ numba kernels
@nb.njit(nogil=True, cache=True)
def _tile_of(x, y, x0, y0, inv, nx, ny):
    i = min(max(np.int64(math.floor((x - x0) * inv)), 0), nx - 1)
    j = min(max(np.int64(math.floor((y - y0) * inv)), 0), ny - 1)
    return i * ny + j


@nb.njit(nogil=True, cache=True)
def _bounds(points):
    """(lo, hi) of the points, float64 (numpy's min over axis 0 of an (N, 3) array strides
    through memory: 20 s for a 4 km city's map, against half a second here)."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for k in range(points.shape[0]):
        for a in range(3):
            v = np.float64(points[k, a])
            if v < lo[a]:
                lo[a] = v
            if v > hi[a]:
                hi[a] = v
    return lo, hi


@nb.njit(nogil=True, cache=True)
def _index(points, x0, y0, inv, nx, ny, chunk, g_x0, g_y0, g_inv, g_nx, g_ny):
    """Which chunks hold points of which tile, each tile's count of points, and the lowest
    height in every ground cell (GroundHeight's grid), in one pass."""
    n = points.shape[0]
    chunk_tiles = np.zeros(((n + chunk - 1) // chunk, nx * ny), np.bool_)
    counts = np.zeros(nx * ny, np.int64)
    ground = np.full((g_nx, g_ny), np.inf, np.float32)
    for k in range(n):
        x, y, z = np.float64(points[k, 0]), np.float64(points[k, 1]), points[k, 2]
        t = _tile_of(x, y, x0, y0, inv, nx, ny)
        chunk_tiles[k // chunk, t] = True
        counts[t] += 1
        gi = min(max(np.int64((x - g_x0) * g_inv), 0), g_nx - 1)
        gj = min(max(np.int64((y - g_y0) * g_inv), 0), g_ny - 1)
        if z < ground[gi, gj]:
            ground[gi, gj] = z
    return chunk_tiles, counts, ground


@nb.njit(nogil=True, cache=True)
def _gather(points, start, stop, x0, y0, inv, nx, ny, t, out, k):
    """Copy the points of tile ``t`` among ``points[start:stop]`` to ``out[k:]``; the new k."""
    for p in range(start, stop):
        if _tile_of(np.float64(points[p, 0]), np.float64(points[p, 1]), x0, y0, inv, nx, ny) == t:
            out[k, 0] = points[p, 0]
            out[k, 1] = points[p, 1]
            out[k, 2] = points[p, 2]
            k += 1
    return k


# ------------------------------------------------------------------------------ the tiled map
class TiledMap:
    """A map too big to send whole, prepared for display: its grid of tiles, the coarse layer cut
    by tile, the ground under the pointer (GroundHeight), and one tile read at ``voxel`` on
    demand. Holds the map's array itself (not a copy) to read tiles from."""

    def __init__(self, map_points: np.ndarray, map_voxel: float, voxel: float, settings: TileSettings):
        self.points = map_points
        points = private_mapping(map_points)  # a map on disk: what is read here does not stay resident
        self.voxel = float(voxel)
        size = max(1, round(settings.tile_m / voxel)) * voxel
        self.lo, self.hi = _bounds(points)
        self.grid = g = TileGrid.covering(self.lo, self.hi, size)
        # the ground grid as GroundHeight builds it: 2 m cells, doubled until at most 4 M of them
        cell = 2.0
        while np.prod(np.ceil((self.hi[:2] - self.lo[:2]) / cell) + 1) > 4_000_000:
            cell *= 2
        shape = (np.ceil((self.hi[:2] - self.lo[:2]) / cell) + 1).astype(np.int64)
        self.chunk_tiles, self.counts, ground = _index(
            points, g.x0, g.y0, 1.0 / g.size, g.nx, g.ny, CHUNK, self.lo[0], self.lo[1], 1.0 / cell, shape[0], shape[1]
        )
        step = max(1, len(points) // 1_000_000)
        z_default = float(np.percentile(points[::step, 2], 5))
        self.ground = GroundHeight.from_grid(ground, self.lo[:2].copy(), cell, z_default)
        self.coarse, self.coarse_voxel = thin(points, settings.coarse_max, max(voxel, map_voxel), map_voxel)
        t = g.tiles_of(self.coarse[:, :2])
        order = np.argsort(t, kind="stable")
        tiles, starts = np.unique(t[order], return_index=True)
        self.coarse_tiles = {
            int(tile): part for tile, part in zip(tiles, np.split(self.coarse[order], starts[1:]), strict=True)
        }
        # the height ramp's span, the same for every tile (height_colors' 2nd–98th percentile)
        self.z_span = tuple(float(v) for v in np.percentile(self.coarse[:, 2], [2, 98])) if len(t) else (0.0, 1.0)

    def load(self, t: int) -> np.ndarray:
        """Tile ``t`` at the display voxel (float32 centroids), read from the chunks of the map
        that hold its points."""
        g = self.grid
        points = private_mapping(self.points)
        out = np.empty((int(self.counts[t]), 3), points.dtype)
        k = 0
        for c in np.flatnonzero(self.chunk_tiles[:, t]):
            start = int(c) * CHUNK
            stop = min(start + CHUNK, len(points))
            k = _gather(points, start, stop, g.x0, g.y0, 1.0 / g.size, g.nx, g.ny, int(t), out, k)
        pts = voxel_centroids(out[:k], self.voxel)
        assert pts is not None
        return pts


class NearTiles:
    """Which tiles are shown at full density, following a pose: :meth:`request` (at most every
    ``interval_s``) decides whether the choice changes and, if it does, reads the new tiles on a
    thread of its own (the display never waits for a read); :meth:`take` hands the finished
    change to the display thread. The tiles shown never hold more than ``budget`` points."""

    def __init__(
        self, tiled: TiledMap, budget: int, settings: TileSettings, on_ready: Callable[[], None] | None = None
    ):
        self.tiled, self.budget, self.settings = tiled, int(budget), settings
        self.shown: dict[int, np.ndarray] = {}  # tile → its points at full density
        self.counts: dict[int, int] = {}  # points of every tile read so far at full density
        self._on_ready = on_ready
        self._lock = threading.Lock()
        self._job: threading.Thread | None = None
        self._result: dict[int, np.ndarray] | BaseException | None = None
        self._last = -math.inf
        self.cancelled = False

    @property
    def points(self) -> int:
        """Points of the tiles shown."""
        return sum(len(p) for p in self.shown.values())

    def request(self, x: float, y: float, now: float) -> bool:
        """Follow the pose at (x, y): True when a change of tiles was started."""
        with self._lock:
            if now - self._last < self.settings.interval_s or self._job is not None or self._result is not None:
                return False
            self._last = now
            s = self.settings
            order = candidates(self.tiled.grid, x, y, self.shown, s.radius_m, s.hysteresis_m)
            chosen, unknown = fit(order, self.counts, self.budget)
            if unknown is None and set(chosen) == set(self.shown):
                return False
            self._job = threading.Thread(target=self._run, args=(order,), name="lidarloc-map-tiles", daemon=True)
            self._job.start()
            return True

    def _run(self, order: list) -> None:
        try:
            read: dict[int, np.ndarray] = dict(self.shown)
            while True:
                chosen, unknown = fit(order, self.counts, self.budget)
                if unknown is None or self.cancelled:
                    break
                read[unknown] = self.tiled.load(unknown)
                self.counts[unknown] = len(read[unknown])
            for t in chosen:  # counted once before, not held since: read again
                if t not in read:
                    read[t] = self.tiled.load(t)
            result: dict[int, np.ndarray] | BaseException = {t: read[t] for t in chosen}
        except BaseException as exc:  # handed to the display thread, which reports it
            result = exc
        with self._lock:
            self._result, self._job = result, None
        if self._on_ready is not None and not self.cancelled:
            self._on_ready()

    def wait(self, timeout: float | None = None) -> None:
        """Until the change in progress (if any) is read (tests; the display never waits)."""
        job = self._job
        if job is not None:
            job.join(timeout)

    def take(self) -> tuple[dict[int, np.ndarray], list] | None:
        """The finished change, as (tiles to add with their points, tiles to remove), now counted
        as shown; None when there is none. A failed read is raised here."""
        with self._lock:
            result, self._result = self._result, None
        if result is None:
            return None
        if isinstance(result, BaseException):
            raise result
        added = {t: p for t, p in result.items() if t not in self.shown}
        removed = [t for t in self.shown if t not in result]
        assert sum(len(p) for p in result.values()) <= self.budget
        self.shown = result
        return added, removed
