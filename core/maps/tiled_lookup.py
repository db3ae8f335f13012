"""The nearest-distance lookup table L cut into square x-y tiles, built per tile in parallel, cached
one file per tile (:mod:`.tile_cache`) and mapped in only where it is read — the city's table.

The same table, cell for cell
    The tiles partition the grid :meth:`LookupTable.build <lidarloc.core.maps.lookup.LookupTable.build>`
    lays over the same points (the same origin, resolution and shape), and every tile is computed by
    the same kernel from the same points: the distance transform already works in build tiles of
    192 × 192 cells with a margin of d_max + 2 cells (:mod:`.distance_transform`), and a map tile is
    a whole number of build tiles, fed every point within that margin of it, in the same order. So
    a tile's codes are the monolithic table's codes bit for bit, border cells included: a node
    near a tile's border sees its nearest map point in the next tile (tests/test_tiles_lookup.py
    compares every cell). Tile sizes are therefore rounded to whole build tiles: 96 m or 384 m
    for a requested 100 m or 400 m at δ = 0.25 m.

Reading
    :meth:`TiledLookup.query` reads any points, tile by tile, with the monolithic read's arithmetic
    (the cell from the grid's origin), so it answers exactly as one table. :meth:`TiledLookup.window`
    assembles the tiles over a rectangle into an ordinary :class:`LookupTable` (its origin the
    window's corner) for the particle filter's kernels. Opened tiles are memory-mapped and kept
    in least-recently-used order; :meth:`TiledLookup.drop_except` unmaps the others.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numba as nb
import numpy as np

from ..errors import DataError, LidarlocError
from .bricks import BRICK, BRICK_CELLS, BRICK_MASK, BRICK_SHIFT, MAX_CODE, MISS_CODE
from .distance_transform import _TILE, _tile_bricks
from .lookup import LookupTable, grid_over
from .point_tiles import private_mapping
from .tile_cache import cache_bytes, open_or_rebuild, read_index, remember, tile_name, write_index, write_tile
from .tiling import bucket_points, point_cells, usable_cores

_FORMAT = 1
BUCKET_CHUNK = 1 << 24  # map points bucketed at a time while building (16 M: 192 MB of float32)


def tile_cells_for(tile_m: float, resolution: float) -> int:
    """Cells per tile side for a requested tile size: a whole number (≥ 1) of build tiles."""
    if not (tile_m > 0 and math.isfinite(tile_m)):
        raise LidarlocError(f"tile size must be > 0 m, got {tile_m}")
    return max(1, round(tile_m / resolution / _TILE)) * _TILE


@nb.njit(nogil=True, cache=True, fastmath=True)
def _tile_ids(points, origin, inv_res, tile_cells, ntx, nty, out):
    """Linear tile index (tx · nty + ty) of each point's cell, −1 outside the grid's tiles; the
    cell is computed as :func:`~lidarloc.core.maps.lookup.lookup_code` computes it."""
    for i in range(points.shape[0]):
        fx = (np.float64(points[i, 0]) - origin[0]) * inv_res
        fy = (np.float64(points[i, 1]) - origin[1]) * inv_res
        fz = (np.float64(points[i, 2]) - origin[2]) * inv_res
        if fx < 0.0 or fy < 0.0 or fz < 0.0:
            out[i] = -1
            continue
        tx = np.int64(fx) // tile_cells
        ty = np.int64(fy) // tile_cells
        out[i] = tx * nty + ty if tx < ntx and ty < nty else -1


@nb.njit(nogil=True, cache=True, fastmath=True)
def _read_tile(points, sel, origin, inv_res, step, cap, bx0, by0, brick_index, bricks, out):
    """:func:`~lidarloc.core.maps.lookup.lookup_code` for the points ``sel`` of one tile, whose
    local brick (0, 0) is the grid's brick (bx0, by0)."""
    for n in range(sel.shape[0]):
        i = sel[n]
        ix = np.int64((np.float64(points[i, 0]) - origin[0]) * inv_res)
        iy = np.int64((np.float64(points[i, 1]) - origin[1]) * inv_res)
        iz = np.int64((np.float64(points[i, 2]) - origin[2]) * inv_res)
        bx = (ix >> BRICK_SHIFT) - bx0
        by = (iy >> BRICK_SHIFT) - by0
        bz = iz >> BRICK_SHIFT
        code = MISS_CODE
        if bx < brick_index.shape[0] and by < brick_index.shape[1] and bz < brick_index.shape[2]:
            cell = ((ix & BRICK_MASK) << 6) | ((iy & BRICK_MASK) << 3) | (iz & BRICK_MASK)
            code = np.int64(bricks[brick_index[bx, by, bz], cell])
        out[i] = min(np.float32(code * step), np.float32(cap))


class TiledLookup:
    """A lookup table stored as tiles in ``directory`` (see the module docstring)."""

    def __init__(self, directory: Path, index: dict, points: np.ndarray | None = None, max_open: int = 16):
        self.directory = Path(directory)
        self.index = index
        self.origin = np.asarray(index["origin"], np.float64)
        self.resolution = float(index["resolution"])
        self.d_max_built = float(index["d_max_built"])
        self.shape = tuple(int(s) for s in index["shape"])
        self.tile_cells = int(index["tile_cells"])
        self.ntx, self.nty = (int(v) for v in index["tiles_xy"])
        self.nbz = (self.shape[2] + BRICK - 1) // BRICK
        self.step = self.d_max_built / MAX_CODE
        self.inv_res = 1.0 / self.resolution
        self.points = points  # kept to rebuild a tile whose file is damaged
        self.max_open = int(max_open)
        self.rebuilt: list[tuple[int, int]] = []  # tiles rebuilt since opening (damaged files)
        self._open: OrderedDict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = OrderedDict()

    # ------------------------------------------------------------------------------ grid
    @property
    def tile_m(self) -> float:
        return self.tile_cells * self.resolution

    @property
    def cache_bytes(self) -> int:
        return cache_bytes(self.directory)

    @property
    def open_tiles(self) -> list[tuple[int, int]]:
        return list(self._open)

    def tiles_over(self, x0: float, y0: float, x1: float, y1: float) -> list[tuple[int, int]]:
        """The tiles meeting the world rectangle [x0, x1] × [y0, y1] (clipped to the grid)."""
        t = self.tile_m
        ox, oy = self.origin[:2]
        tx0, tx1 = max(int((x0 - ox) // t), 0), min(int((x1 - ox) // t), self.ntx - 1)
        ty0, ty1 = max(int((y0 - oy) // t), 0), min(int((y1 - oy) // t), self.nty - 1)
        return [(tx, ty) for tx in range(tx0, tx1 + 1) for ty in range(ty0, ty1 + 1)]

    # ------------------------------------------------------------------------------ tiles
    def tile(self, tx: int, ty: int) -> tuple[np.ndarray, np.ndarray]:
        """(brick_index, bricks) of tile (tx, ty), mapped in from its files (or rebuilt when
        they are damaged and the points are at hand); most recently used last."""
        key = (tx, ty)
        if key in self._open:
            self._open.move_to_end(key)
            return self._open[key]
        name = tile_name(tx, ty)
        arrays = open_or_rebuild(
            self.directory,
            name,
            self.index["tiles"][name],
            lambda files: (files["index"], files["bricks"]),
            None if self.points is None else lambda: self._rebuild(tx, ty),
            "rebuild the map's tables (the map points are needed)",
        )
        return remember(self._open, key, arrays, self.max_open)

    def drop_except(self, keep) -> None:
        """Unmap every open tile not in ``keep`` (tiles the run left behind)."""
        for key in [k for k in self._open if k not in set(keep)]:
            del self._open[key]

    def _rebuild(self, tx: int, ty: int) -> tuple[np.ndarray, np.ndarray]:
        assert self.points is not None
        grid = self.grid_args()
        source = self.points  # a memory-mapped map is read a chunk at a time (see build_tiles)
        reach = int(math.ceil(grid["d_max"] / grid["resolution"])) + 2
        idx = _bucket_in_chunks(source, grid, reach, self.ntx, self.nty, BUCKET_CHUNK, only=tx * self.nty + ty)
        index, bricks = _build_tile(private_mapping(source), grid, tx, ty, idx=idx)
        name = tile_name(tx, ty)
        self.index["tiles"][name] = write_tile(self.directory, name, {"index": index, "bricks": bricks})
        write_index(self.directory, self.index)
        self.rebuilt.append((tx, ty))
        return index, bricks

    def grid_args(self) -> dict:
        return dict(
            origin=self.origin,
            resolution=self.resolution,
            d_max=self.d_max_built,
            shape=self.shape,
            tile_cells=self.tile_cells,
            nty=self.nty,
        )

    # ------------------------------------------------------------------------------ reading
    def capped(self, d_max: float) -> float:
        return min(float(d_max), self.d_max_built)

    def query(self, points: np.ndarray, d_max: float | None = None) -> np.ndarray:
        """Distances (float32, metres) of (M, ≥3) points to the map, capped at ``d_max``: the
        values one :class:`LookupTable` over the whole map reads."""
        cap = self.d_max_built if d_max is None else self.capped(d_max)
        pts = np.ascontiguousarray(np.asarray(points)[:, :3], dtype=np.float64)
        out = np.full(len(pts), np.float32(min(MISS_CODE * self.step, cap)), np.float32)
        ids = np.empty(len(pts), np.int64)
        _tile_ids(pts, self.origin, self.inv_res, self.tile_cells, self.ntx, self.nty, ids)
        order = np.argsort(ids, kind="stable")
        sorted_ids = ids[order]
        starts = np.flatnonzero(np.r_[True, sorted_ids[1:] != sorted_ids[:-1]]) if len(ids) else []
        bounds = list(starts) + [len(ids)]
        bricks_per_tile = self.tile_cells // BRICK
        for a, b in zip(bounds[:-1], bounds[1:], strict=False):
            tid = int(sorted_ids[a])
            if tid < 0:
                continue
            tx, ty = divmod(tid, self.nty)
            brick_index, bricks = self.tile(tx, ty)
            _read_tile(
                pts,
                order[a:b],
                self.origin,
                self.inv_res,
                self.step,
                cap,
                tx * bricks_per_tile,
                ty * bricks_per_tile,
                brick_index,
                bricks,
                out,
            )
        return out

    def window(self, x0: float, y0: float, x1: float, y1: float) -> LookupTable:
        """One :class:`LookupTable` over the tiles meeting [x0, x1] × [y0, y1] (copied out of the
        mapped tiles; outside them it reads d_max)."""
        tiles = self.tiles_over(x0, y0, x1, y1)
        if not tiles:
            raise LidarlocError(f"window [{x0:.0f}, {x1:.0f}] × [{y0:.0f}, {y1:.0f}] m is outside the map")
        txs, tys = sorted({t[0] for t in tiles}), sorted({t[1] for t in tiles})
        bpt = self.tile_cells // BRICK
        cx0, cy0 = txs[0] * self.tile_cells, tys[0] * self.tile_cells
        cx1 = min((txs[-1] + 1) * self.tile_cells, self.shape[0])
        cy1 = min((tys[-1] + 1) * self.tile_cells, self.shape[1])
        nb_x, nb_y = (cx1 - cx0 + BRICK - 1) // BRICK, (cy1 - cy0 + BRICK - 1) // BRICK
        # the window holds a copy: a tile mapped in only to be copied is unmapped right after its
        # copy, so that the copy is not resident twice (its pages and the mapped file's)
        was_open = set(self._open)
        sizes = [len(self.tile(tx, ty)[1]) for tx, ty in tiles]  # mapped, not read yet: nothing resident
        pool = np.empty((1 + sum(n - 1 for n in sizes), BRICK_CELLS), np.uint8)
        pool[0] = MISS_CODE
        brick_index = np.zeros((nb_x, nb_y, self.nbz), np.int32)
        slot = 1
        for tx, ty in tiles:
            index, bricks = self.tile(tx, ty)
            k = len(bricks) - 1
            pool[slot : slot + k] = bricks[1:]
            local = np.asarray(index)
            bx, by = (tx - txs[0]) * bpt, (ty - tys[0]) * bpt
            brick_index[bx : bx + local.shape[0], by : by + local.shape[1]] = np.where(local > 0, local + slot - 1, 0)
            slot += k
            del index, bricks, local
            if (tx, ty) not in was_open:
                self._open.pop((tx, ty), None)
        origin = self.origin + np.array([cx0 * self.resolution, cy0 * self.resolution, 0.0])
        return LookupTable(
            origin, self.resolution, self.d_max_built, (cx1 - cx0, cy1 - cy0, self.shape[2]), brick_index, pool
        )

    # ------------------------------------------------------------------------------ building
    @classmethod
    def load_or_build(
        cls,
        points: np.ndarray,
        directory: Path,
        key: str,
        resolution: float,
        d_max: float,
        tile_m: float,
        *,
        threads: int | None = None,
        progress: Callable[[float], None] | None = None,
    ) -> TiledLookup:
        """The tiled table of ``points`` cached in ``directory`` for ``key`` (the map's identity),
        or built there tile by tile. A cache made for another key, resolution, d_max or tile size
        is rebuilt; a damaged tile is rebuilt when it is first read."""
        directory = Path(directory)
        resolution, d_max = float(resolution), float(d_max)
        tile_cells = tile_cells_for(tile_m, resolution)
        full_key = f"{key}|lookup|r{resolution:.6g}|d{d_max:.6g}|t{tile_cells}|v{_FORMAT}"
        index = read_index(directory, full_key)
        if index is not None:
            return cls(directory, index, points)
        t0 = time.perf_counter()
        index = build_tiles(points, directory, full_key, resolution, d_max, tile_cells, threads, progress)
        index["build_seconds"] = time.perf_counter() - t0
        write_index(directory, index)
        return cls(directory, index, points)


def _checked_points(points: np.ndarray) -> np.ndarray:
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3 or len(pts) == 0:
        raise DataError(f"map points must be a non-empty (N, 3) array; got shape {pts.shape}")
    return np.ascontiguousarray(pts[:, :3], dtype=pts.dtype if pts.dtype in (np.float32, np.float64) else np.float64)


def _build_tile(points: np.ndarray, grid: dict, tx: int, ty: int, cells=None, idx=None):
    """(local brick_index, bricks) of map tile (tx, ty), from every point within reach of it
    (``idx``: their indices in ascending order, when the caller has bucketed them already; then
    only their cells are computed, unless ``cells`` has every point's)."""
    pts = _checked_points(points)
    lo, res, d_max = grid["origin"], grid["resolution"], grid["d_max"]
    shape = np.asarray(grid["shape"], np.int64)
    tc = grid["tile_cells"]
    reach = int(math.ceil(d_max / res)) + 2
    x0, y0 = tx * tc, ty * tc
    x1, y1 = min(x0 + tc, int(shape[0])), min(y0 + tc, int(shape[1]))
    if idx is None:
        if cells is None:
            cells = point_cells(pts, lo, res, shape)
        cx, cy = cells[:, 0], cells[:, 1]
        idx = np.flatnonzero((cx >= x0 - reach) & (cx < x1 + reach) & (cy >= y0 - reach) & (cy < y1 + reach))
    nbz = (int(shape[2]) + BRICK - 1) // BRICK
    nb_x, nb_y = (x1 - x0 + BRICK - 1) // BRICK, (y1 - y0 + BRICK - 1) // BRICK
    brick_index = np.zeros((nb_x, nb_y, nbz), np.int32)
    datas = []
    if len(idx):
        sub_pts = np.ascontiguousarray(pts[idx])
        sub_cells = cells[idx] if cells is not None else point_cells(sub_pts, lo, res, shape)
        ntx_b = (int(shape[0]) + _TILE - 1) // _TILE
        nty_b = (int(shape[1]) + _TILE - 1) // _TILE
        offsets, flat = bucket_points(sub_cells, _TILE, reach, ntx_b, nty_b)
        slot = 1
        for bxt in range(x0 // _TILE, (x1 + _TILE - 1) // _TILE):
            for byt in range(y0 // _TILE, (y1 + _TILE - 1) // _TILE):
                got = _tile_bricks(
                    bxt * nty_b + byt,
                    pts=sub_pts,
                    cells=sub_cells,
                    offsets=offsets,
                    flat=flat,
                    shape=shape,
                    reach=reach,
                    nz8=nbz * BRICK,
                    lo=lo,
                    resolution=res,
                    d_max=d_max,
                    step=d_max / MAX_CODE,
                )
                if got is None or not len(got[0]):
                    continue
                coords, data = got
                k = len(coords)
                brick_index[coords[:, 0] - x0 // BRICK, coords[:, 1] - y0 // BRICK, coords[:, 2]] = np.arange(
                    slot, slot + k, dtype=np.int32
                )
                datas.append(data)
                slot += k
    bricks = np.empty((1 + sum(len(d) for d in datas), BRICK_CELLS), np.uint8)
    bricks[0] = MISS_CODE
    if datas:
        bricks[1:] = np.concatenate(datas)
    return brick_index, bricks


def build_tiles(
    points, directory, key, resolution, d_max, tile_cells, threads=None, progress=None, chunk: int = BUCKET_CHUNK
) -> dict:
    """Build every tile of ``points``'s table into ``directory`` (map tiles in parallel; each
    tile's files written as soon as it is done) and return the index (also written).

    The points may be a memory-mapped map larger than memory: they are bucketed into tiles
    ``chunk`` points at a time (only each tile's list of point indices is held, ~4 bytes a point),
    and each tile reads its own points from the map, each read through a mapping of its own so
    that the pages read do not stay resident (:func:`~.point_tiles.private_mapping`). Every tile
    gets the same points in the same (ascending) order as from one pass over the whole map, so the
    tables are the same bit for bit (the 4 × 4 km city's 121 tiles at δ = 0.5 m: the same CRCs).
    Measured on that city (421 M points), from its memory-mapped map: peak resident memory 2.5 GB
    (2.2 GB anonymous: the index lists and the tiles in flight; 0.6 GB of map pages), in 196 s;
    bucketing in one pass held every point's cell and the map's pages read: 12.2 GB, 210 s."""
    pts = _checked_points(points)  # (a memory-mapped map comes back as a plain view of its mapping)
    source = points if isinstance(points, np.memmap) else pts  # what private mappings are made of
    lo, shape = _grid_in_chunks(source, resolution, d_max, chunk)
    ntx, nty = (int(s + tile_cells - 1) // tile_cells for s in shape[:2])
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    for old in directory.glob("t*_*.*.npy"):  # tiles of another table
        old.unlink(missing_ok=True)
    index = {
        "format": _FORMAT,
        "key": key,
        "origin": lo.tolist(),
        "resolution": resolution,
        "d_max_built": d_max,
        "shape": shape.tolist(),
        "tile_cells": tile_cells,
        "tiles_xy": [ntx, nty],
        "tiles": {},
    }
    grid = dict(origin=lo, resolution=resolution, d_max=d_max, shape=shape, tile_cells=tile_cells, nty=nty)
    per_tile = _bucket_in_chunks(source, grid, int(math.ceil(d_max / resolution)) + 2, ntx, nty, chunk)

    def one(t):
        tx, ty = divmod(t, nty)
        # a mapping of its own per tile: the map's pages it read are let go with it
        brick_index, bricks = _build_tile(private_mapping(source), grid, tx, ty, idx=per_tile[t])
        per_tile[t] = None  # this tile's point list is done with
        name = tile_name(tx, ty)
        return name, write_tile(directory, name, {"index": brick_index, "bricks": bricks})

    with ThreadPoolExecutor(usable_cores(threads), thread_name_prefix="lidarloc-tiles") as pool:
        for done, (name, entry) in enumerate(pool.map(one, range(ntx * nty)), 1):
            index["tiles"][name] = entry
            if progress is not None:
                progress(done / (ntx * nty))
    write_index(directory, index)
    return index


def _grid_in_chunks(pts: np.ndarray, resolution: float, d_max: float, chunk: int) -> tuple[np.ndarray, np.ndarray]:
    """(origin, shape) of the grid :meth:`LookupTable.build` lays over ``pts``
    (:func:`~.lookup.grid_over`), their bounds read ``chunk`` points at a time, checking every
    coordinate is finite."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for s in range(0, len(pts), chunk):
        part = _checked_points(private_mapping(pts)[s : s + chunk])  # a mapping per chunk: its pages go with it
        if not np.isfinite(part).all():
            raise DataError("map points contain NaN or infinite coordinates")
        lo = np.minimum(lo, part.min(axis=0))
        hi = np.maximum(hi, part.max(axis=0))
    return grid_over(lo, hi, resolution, d_max)


def _bucket_in_chunks(pts: np.ndarray, grid: dict, reach: int, ntx: int, nty: int, chunk: int, only=None):
    """Per tile, the ascending indices (int32, or int64 past 2^31 points) of the points within
    ``reach`` cells of it: :func:`bucket_points` ``chunk`` points at a time. ``only``: the list of
    that one tile (t = tx · nty + ty) alone."""
    lo, res, shape, tc = grid["origin"], grid["resolution"], np.asarray(grid["shape"], np.int64), grid["tile_cells"]
    dtype = np.int32 if len(pts) < 2**31 else np.int64
    parts: list[list[np.ndarray]] = [[] for _ in range(ntx * nty)]
    for s in range(0, len(pts), chunk):
        cells = point_cells(_checked_points(private_mapping(pts)[s : s + chunk]), lo, res, shape)
        offsets, flat = bucket_points(cells, tc, reach, ntx, nty)
        for t in np.flatnonzero(np.diff(offsets)) if only is None else [only]:
            parts[t].append(flat[offsets[t] : offsets[t + 1]].astype(dtype) + dtype(s))
    if only is not None:
        return np.concatenate(parts[only]) if parts[only] else np.zeros(0, dtype)
    lists = []
    for t in range(len(parts)):  # one tile's parts joined at a time: the lists are held once, not twice
        got, parts[t] = parts[t], []
        lists.append(np.concatenate(got) if got else np.zeros(0, dtype))
    return lists
