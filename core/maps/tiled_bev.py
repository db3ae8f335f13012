"""The BEV pyramid of a city cut into square tiles of 2^k L0 cells: each tile's L0 in its own
memory-mapped file (:mod:`.tile_cache`), the coarse levels (k and above, one cell per tile and
coarser) held in memory. The exact tiled global search (:mod:`lidarloc.core.matching.tiled_search`)
bounds whole tiles on the coarse levels and maps in a tile's L0 only when it searches inside it.

The grid is the one :meth:`BEVPyramid.build <lidarloc.core.maps.bev.BEVPyramid.build>` lays over
the same points (origin a multiple of d_m at the lowest occupied cell), so a tile's L0 is the
monolithic L0's block and the coarse levels are the monolithic pyramid's levels k, k + 1, …: a
level-l cell is the maximum over its aligned 2^l × 2^l block of L0 (zeros beyond the grid), and
a tile is such a block at level k.
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..cache import atomic_write_file, cache_rebuilt
from ..errors import LidarlocError
from .bev import DEFAULT_CELL_VALUE, BEVPyramid, _cell_values, max_pool2
from .tile_cache import cache_bytes, open_or_rebuild, read_index, remember, tile_name, write_index, write_tile

_FORMAT = 1
_CHUNK = 1 << 24


def tile_level_for(tile_m: float, resolution: float) -> int:
    """log2 of the L0 cells per tile side for a requested tile size (≥ 16 cells)."""
    if not (tile_m > 0 and math.isfinite(tile_m)):
        raise LidarlocError(f"tile size must be > 0 m, got {tile_m}")
    return max(4, round(math.log2(tile_m / resolution)))


class TiledBEV:
    """A BEV pyramid stored as L0 tiles in ``directory`` with its coarse levels in memory."""

    def __init__(
        self, directory: Path, index: dict, coarse: list[np.ndarray], max_open: int = 64, xy: np.ndarray | None = None
    ):
        self.directory = Path(directory)
        self.index = index
        self.resolution = float(index["resolution"])
        self.origin = np.asarray(index["origin"], np.float64)
        self.shape = tuple(int(s) for s in index["shape"])
        self.tile_level = int(index["tile_level"])
        self.tile_cells = 1 << self.tile_level
        self.ntx, self.nty = (int(v) for v in index["tiles_xy"])
        self.cell_value = str(index["cell_value"])
        self.coarse = coarse  # levels tile_level, tile_level + 1, … of the whole pyramid
        self.max_open = int(max_open)
        self.loaded = 0  # tiles mapped in since opening (what a search descended into)
        self.xy = xy  # the road-removed map's points, kept to rebuild a tile whose file is damaged
        self.rebuilt: list[tuple[int, int]] = []  # tiles rebuilt since opening (damaged files)
        self._open: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()
        self._lock = threading.Lock()  # the global search reads tiles from several threads

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of L0 in world metres, as :attr:`BEVPyramid.extent`."""
        x0, y0 = self.origin
        d = self.resolution
        return float(x0), float(y0), float(x0 + self.shape[0] * d), float(y0 + self.shape[1] * d)

    @property
    def cache_bytes(self) -> int:
        return cache_bytes(self.directory)

    def tile(self, tx: int, ty: int) -> np.ndarray:
        """L0 of tile (tx, ty) (zeros for a tile with no map points), mapped in on first use."""
        with self._lock:
            return self._tile(tx, ty)

    def _tile(self, tx: int, ty: int) -> np.ndarray:
        key = (tx, ty)
        if key in self._open:
            self._open.move_to_end(key)
            return self._open[key]
        name = tile_name(tx, ty)
        entry = self.index["tiles"].get(name)
        if entry is None:
            l0 = np.zeros(self._tile_shape(tx, ty), np.float32)
        else:
            l0 = open_or_rebuild(
                self.directory,
                name,
                entry,
                lambda arrays: arrays["L0"],
                None if self.xy is None else lambda: self._rebuild(tx, ty),
                f"delete {self.directory} to rebuild the city's pyramid",
            )
        self.loaded += 1
        return remember(self._open, key, l0, self.max_open)

    def _rebuild(self, tx: int, ty: int) -> np.ndarray:
        """L0 of tile (tx, ty) counted again from the map's points, written back in place."""
        assert self.xy is not None
        t = self.tile_cells
        lo_i = np.round(self.origin / self.resolution).astype(np.int64)
        shape = self._tile_shape(tx, ty)
        counts = _count_cells(self.xy, self.resolution, lo_i + np.array([tx * t, ty * t]), shape)
        l0 = np.ascontiguousarray(_cell_values(counts, self.cell_value))
        name = tile_name(tx, ty)
        self.index["tiles"][name] = write_tile(self.directory, name, {"L0": l0})
        write_index(self.directory, self.index)
        self.rebuilt.append((tx, ty))
        return l0

    def _tile_shape(self, tx: int, ty: int) -> tuple[int, int]:
        t = self.tile_cells
        return min(t, self.shape[0] - tx * t), min(t, self.shape[1] - ty * t)

    def window(self, cx0: int, cy0: int, cx1: int, cy1: int) -> BEVPyramid:
        """A :class:`BEVPyramid` over L0 cells [cx0, cx1) × [cy0, cy1) (clipped to the grid; its
        cells beyond the grid are empty), assembled from the tiles it meets."""
        cx0, cy0 = max(cx0, 0), max(cy0, 0)
        cx1, cy1 = max(min(cx1, self.shape[0]), cx0 + 1), max(min(cy1, self.shape[1]), cy0 + 1)
        l0 = np.zeros((cx1 - cx0, cy1 - cy0), np.float32)
        t = self.tile_cells
        for tx in range(cx0 // t, (cx1 - 1) // t + 1):
            for ty in range(cy0 // t, (cy1 - 1) // t + 1):
                if tx >= self.ntx or ty >= self.nty:
                    continue
                tile = self.tile(tx, ty)
                x0, y0 = tx * t, ty * t
                ax0, ay0 = max(cx0, x0), max(cy0, y0)
                ax1, ay1 = min(cx1, x0 + tile.shape[0]), min(cy1, y0 + tile.shape[1])
                if ax1 > ax0 and ay1 > ay0:
                    l0[ax0 - cx0 : ax1 - cx0, ay0 - cy0 : ay1 - cy0] = tile[ax0 - x0 : ax1 - x0, ay0 - y0 : ay1 - y0]
        levels = [l0]
        while levels[-1].size > 9:
            levels.append(max_pool2(levels[-1]))
        origin = self.origin + np.array([cx0, cy0], np.float64) * self.resolution
        return BEVPyramid(self.resolution, origin, levels, self.cell_value)

    # ------------------------------------------------------------------------------ building
    @classmethod
    def load_or_build(
        cls,
        xy: np.ndarray,
        directory: Path,
        key: str,
        resolution: float,
        tile_m: float,
        cell_value: str | None = None,
        progress: Callable[[float], None] | None = None,
    ) -> TiledBEV:
        """The tiled pyramid of the road-removed map's ``xy`` cached in ``directory`` for ``key``,
        or built there. A tile whose file is found damaged when it is first read is counted again
        from ``xy`` and rewritten (the user is told)."""
        cell_value = cell_value or DEFAULT_CELL_VALUE
        level = tile_level_for(tile_m, resolution)
        full_key = f"{key}|bev|d{resolution:.6g}|{cell_value}|t{level}|v{_FORMAT}"
        directory = Path(directory)
        index = read_index(directory, full_key)
        if index is not None:
            try:
                with np.load(directory / "coarse.npz") as data:
                    coarse = [np.asarray(data[f"L{i}"], np.float32) for i in range(index["n_coarse"])]
                return cls(directory, index, coarse, xy=xy)
            except (OSError, ValueError, KeyError) as exc:
                cache_rebuilt(directory, f"{type(exc).__name__}: {exc}")  # rebuilt below
        t0 = time.perf_counter()
        index, coarse = _build(xy, directory, full_key, float(resolution), level, cell_value, progress)
        index["build_seconds"] = time.perf_counter() - t0
        write_index(directory, index)
        return cls(directory, index, coarse, xy=xy)


def _count_cells(xy, resolution: float, first_cell: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Points of ``xy`` per cell of the block of ``shape`` cells starting at cell ``first_cell``
    (cells floor(xy / resolution), as BEVPyramid.build's lattice); points outside it are left
    out. One pass in chunks: a city's road-removed map does not fit twice in memory."""
    counts = np.zeros(shape, np.int64)
    for a in range(0, len(xy), _CHUNK):
        idx = np.floor(np.asarray(xy[a : a + _CHUNK, :2], np.float64) / resolution).astype(np.int64) - first_cell
        inside = (idx[:, 0] >= 0) & (idx[:, 0] < shape[0]) & (idx[:, 1] >= 0) & (idx[:, 1] < shape[1])
        np.add.at(counts, (idx[inside, 0], idx[inside, 1]), 1)
    return counts


def _build(xy, directory: Path, key: str, resolution: float, level: int, cell_value: str, progress):
    n = len(xy)
    if n == 0:
        raise LidarlocError("cannot build a BEV pyramid from an empty map (no road-removed points)")
    # the same lattice as BEVPyramid.build: cells floor(xy / d_m) from the lowest occupied one
    lo = np.array([np.inf, np.inf])
    hi = -lo
    for a in range(0, n, _CHUNK):
        idx = np.floor(np.asarray(xy[a : a + _CHUNK, :2], np.float64) / resolution)
        lo, hi = np.minimum(lo, idx.min(axis=0)), np.maximum(hi, idx.max(axis=0))
    lo_i = lo.astype(np.int64)
    nx, ny = (hi.astype(np.int64) - lo_i + 1).tolist()
    counts = _count_cells(xy, resolution, lo_i, (nx, ny))
    l0 = _cell_values(counts, cell_value)
    del counts
    t = 1 << level
    ntx, nty = (nx + t - 1) // t, (ny + t - 1) // t
    directory.mkdir(parents=True, exist_ok=True)
    for old in directory.glob("t*_*.*.npy"):
        old.unlink(missing_ok=True)
    tiles = {}
    tile_max = np.zeros((ntx, nty), np.float32)
    for tx in range(ntx):
        for ty in range(nty):
            block = np.ascontiguousarray(l0[tx * t : (tx + 1) * t, ty * t : (ty + 1) * t])
            tile_max[tx, ty] = block.max()
            if tile_max[tx, ty] > 0:  # empty tiles are not stored: they read as zeros
                tiles[tile_name(tx, ty)] = write_tile(directory, tile_name(tx, ty), {"L0": block})
        if progress is not None:
            progress((tx + 1) / ntx)
    coarse = [tile_max]
    while coarse[-1].size > 9:
        coarse.append(max_pool2(coarse[-1]))
    atomic_write_file(
        directory / "coarse.npz", lambda tmp: np.savez(tmp, **{f"L{i}": lv for i, lv in enumerate(coarse)})
    )
    index = {"format": _FORMAT, "key": key, "resolution": resolution, "origin": (lo_i * resolution).tolist(),
             "shape": [nx, ny], "tile_level": level, "tiles_xy": [ntx, nty], "cell_value": cell_value,
             "n_coarse": len(coarse), "map_points": int(n), "tiles": tiles}  # fmt: skip
    return index, coarse
