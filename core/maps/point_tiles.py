"""The map's points cut into square x-y tiles on disk, for what reads the map only near one place of
a map too big to hold: the scan-to-map matcher's GICP target and its ground heights on a city.

A 4 × 4 km city surveyed at 0.2 m is 421 M points (5 GB as float32): the S2M process cannot load
them, nor build a GICP target over all of them, and it needs only the ~150 m around the match.
Here every point goes to the tile under it (tiles of ``POINT_TILE_M`` on a side, one ``.npy``
file each, :mod:`.tile_cache`: written atomically, CRC-checked when first opened, memory-mapped);
:meth:`PointTiles.points_in` reads the tiles meeting a rectangle and keeps the points inside it,
so a read across a tile border sees the points on both sides, as the whole map would.

The build reads the map in chunks (it may be a memory-mapped file larger than memory), checks
every coordinate is finite, and appends each chunk's points to its tiles in the map's order (in a
staging folder of its own, so two processes cutting the same map at once do not mix), so a tile
holds its points in the order the map file has them. The index (written last: a build cut short
leaves no index and is done again) keeps the grid, each tile's point count and the map's bounds,
which a run on a memory-mapped map reads instead of scanning every point.
"""

from __future__ import annotations

import json
import math
import shutil
import tempfile
import threading
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..errors import DataError
from .tile_cache import INDEX, open_or_rebuild, read_index, remember, tile_name, write_index, write_tile
from .voxel_grid import voxel_centroids

POINT_TILE_M = 100.0  # ~0.26 M points (3 MB) of a survey city; a match's 142 m disc reads 9–16 of them
_CHUNK = 1 << 24  # points read at a time while building (192 MB of float32 coordinates)
_FORMAT = 1
_STAGING = "staging-"


class PointTiles:
    """A map's points by x-y tile in ``directory`` (see the module docstring)."""

    def __init__(self, directory: Path, index: dict, points: np.ndarray | None = None, max_open: int = 32):
        self.directory = Path(directory)
        self.points = points  # the whole map (may be memory-mapped), to cut a damaged tile again
        self.index = index
        self.origin = np.asarray(index["origin"], np.float64)  # (2,) x, y of tile (0, 0)'s corner
        self.tile_m = float(index["tile_m"])
        self.ntx, self.nty = (int(v) for v in index["tiles_xy"])
        self.n_points = int(index["points"])
        lo, hi = index["bounds"]
        self.bounds = (np.asarray(lo, np.float64), np.asarray(hi, np.float64))
        self.max_open = int(max_open)
        self.rebuilt: list[tuple[int, int]] = []  # tiles cut again since opening (damaged files)
        self._open: OrderedDict[str, np.ndarray] = OrderedDict()
        self._lock = threading.Lock()  # the S2M feeder and a warm-up may read at once
        # tiles thinned from these (:meth:`thinned`): their parent and voxel, and those made so far
        self._parent: tuple[PointTiles, float] | None = None
        self.voxel = 0.0  # m, the voxel these tiles were thinned to (0: the map's own points)
        self._thinned: dict[float, PointTiles] = {}

    def tiles_over(self, x0: float, y0: float, x1: float, y1: float) -> list[tuple[int, int]]:
        """The tiles meeting the rectangle [x0, x1] × [y0, y1] (clipped to the grid)."""
        ox, oy = self.origin
        t = self.tile_m
        tx0, tx1 = max(math.floor((x0 - ox) / t), 0), min(math.floor((x1 - ox) / t), self.ntx - 1)
        ty0, ty1 = max(math.floor((y0 - oy) / t), 0), min(math.floor((y1 - oy) / t), self.nty - 1)
        return [(tx, ty) for tx in range(tx0, tx1 + 1) for ty in range(ty0, ty1 + 1)]

    def tile(self, tx: int, ty: int) -> np.ndarray:
        """The (n, 3) float32 points of tile (tx, ty), memory-mapped (empty where the map has none).
        A damaged tile file (its size or CRC, checked when first opened) is cut again from the
        map's points and the user told; without them it is a DataError naming the file."""
        name = tile_name(tx, ty)
        entry = self.index["tiles"].get(name)
        if entry is None:
            return np.zeros((0, 3), np.float32)
        with self._lock:
            if name in self._open:
                self._open.move_to_end(name)
                return self._open[name]
            points = open_or_rebuild(
                self.directory,
                name,
                entry,
                lambda arrays: arrays["points"],
                None if self.points is None and self._parent is None else lambda: self._rebuild(tx, ty),
                "rebuild the map's tables (the map points are needed)",
            )
            return remember(self._open, name, points, self.max_open)

    def _rebuild(self, tx: int, ty: int) -> np.ndarray:
        """Tile (tx, ty) cut again from the whole map (one pass over it, in chunks), or thinned
        again from its parent's tile."""
        if self._parent is not None:
            parent, voxel = self._parent
            return self._keep(tx, ty, _thin(parent.tile(tx, ty), voxel))
        assert self.points is not None
        source = private_mapping(self.points)
        parts = []
        for s in range(0, len(source), _CHUNK):
            chunk = np.asarray(source[s : s + _CHUNK, :3], dtype=np.float32)
            t = _tile_xy(chunk, self.origin, self.tile_m, self.ntx, self.nty)
            parts.append(chunk[(t[:, 0] == tx) & (t[:, 1] == ty)])
        return self._keep(tx, ty, np.concatenate(parts))

    def _keep(self, tx: int, ty: int, points: np.ndarray) -> np.ndarray:
        name = tile_name(tx, ty)
        self.index["tiles"][name] = write_tile(self.directory, name, {"points": points})
        write_index(self.directory, self.index)
        self.rebuilt.append((tx, ty))
        return points

    def points_in(self, x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
        """Every map point with x in [x0, x1] and y in [y0, y1], (n, 3) float32, tile by tile in
        tile order (a copy: the tiles stay on disk)."""
        parts = []
        for tx, ty in self.tiles_over(x0, y0, x1, y1):
            pts = self.tile(tx, ty)
            if not len(pts):
                continue
            x, y = pts[:, 0], pts[:, 1]
            parts.append(np.asarray(pts[(x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)]))
        return np.concatenate(parts) if parts else np.zeros((0, 3), np.float32)

    def points_near(self, x: float, y: float, radius: float) -> np.ndarray:
        """Every map point within ``radius`` of (x, y) in x-y, (n, 3) float32."""
        pts = self.points_in(x - radius, y - radius, x + radius, y + radius)
        return pts[np.hypot(pts[:, 0] - x, pts[:, 1] - y) <= radius]

    def thinned(self, voxel: float) -> PointTiles:
        """These tiles with each tile's points down-sampled to one centroid per ``voxel`` (voxels
        aligned to the origin), cached beside them in ``<directory>-<voxel>m`` and thinned from
        them the first time they are asked for (a few seconds a km²), then opened.

        Why: a GICP target built for one whole-map answer (:mod:`lidarloc.core.matching.gicp`)
        wants the map down-sampled to its voxel near the answer; cutting the raw points there and
        down-sampling them took 80–160 ms of a 460 ms match on the 1 km² city, every answer. The
        tiles' edges lie on the voxel grid where the tile size is a multiple of the voxel (100 m
        and 0.5 m): a voxel then never straddles two tiles, and a tile's centroids are the whole
        map's there."""
        voxel = float(voxel)
        with self._lock:
            known = self._thinned.get(voxel)
        if known is not None:
            return known
        directory = self.directory.with_name(f"{self.directory.name}-{voxel:g}m")
        key = f"{self.index['key']}|thinned|v{voxel:.6g}|f{_FORMAT}"
        index = read_index(directory, key)
        if index is None:
            directory.mkdir(parents=True, exist_ok=True)
            tiles, n = {}, 0
            for name in sorted(self.index["tiles"]):
                tx, ty = (int(v) for v in name[1:].split("_"))
                pts = _thin(self.tile(tx, ty), voxel)
                tiles[name] = write_tile(directory, name, {"points": pts})
                n += len(pts)
            index = {**self.index, "key": key, "points": n, "tiles": tiles}
            write_index(directory, index)
        thin = PointTiles(directory, index, max_open=self.max_open)
        thin._parent = (self, voxel)
        thin.voxel = voxel
        with self._lock:
            return self._thinned.setdefault(voxel, thin)

    @classmethod
    def open(cls, directory: Path, points: np.ndarray | None = None) -> PointTiles:
        """The tiles already cut in ``directory`` (whatever their key: the caller built them for
        this map), DataError if there are none."""
        try:
            index = json.loads((Path(directory) / INDEX).read_text())
        except (OSError, ValueError) as exc:
            raise DataError(f"{directory}: no point tiles ({exc})") from None
        return cls(directory, index, points)

    @classmethod
    def load_or_build(
        cls,
        points: np.ndarray,
        directory: Path,
        key: str,
        tile_m: float = POINT_TILE_M,
        progress: Callable[[float], None] | None = None,
    ) -> PointTiles:
        """The tiles of ``points`` cached in ``directory`` for ``key`` (the map's identity), or cut
        there; a cache made for another key or tile size is cut again (a damaged tile alone, when
        it is read: :meth:`tile`)."""
        directory = Path(directory)
        full_key = f"{key}|points|t{float(tile_m):.6g}|v{_FORMAT}"
        index = read_index(directory, full_key)
        if index is None:
            index = _build(points, directory, full_key, float(tile_m), progress or (lambda f: None))
            write_index(directory, index)
        return cls(directory, index, points)


def private_mapping(points: np.ndarray) -> np.ndarray:
    """A memory-mapped map read through a mapping of its own, dropped when the reader is done with
    it: read through the shared mapping, every page read would stay resident in the process (5 GB
    for a city's map read once). Other arrays as they are."""
    if isinstance(points, np.memmap) and points.filename:
        return np.memmap(points.filename, points.dtype, "r", offset=points.offset, shape=points.shape)
    return points


def _thin(points: np.ndarray, voxel: float) -> np.ndarray:
    """One centroid per ``voxel`` of a tile's points, (n, 3) float32."""
    if not len(points):
        return np.zeros((0, 3), np.float32)
    out = voxel_centroids(np.asarray(points, np.float32), voxel)
    assert out is not None  # no cap
    return out


def _tile_xy(points: np.ndarray, origin: np.ndarray, tile_m: float, ntx: int, nty: int) -> np.ndarray:
    """(n, 2) int64 tile of each point (clamped into the grid)."""
    txy = np.floor((points[:, :2].astype(np.float64) - origin) / tile_m).astype(np.int64)
    np.clip(txy[:, 0], 0, ntx - 1, out=txy[:, 0])
    np.clip(txy[:, 1], 0, nty - 1, out=txy[:, 1])
    return txy


def _build(points: np.ndarray, directory: Path, key: str, tile_m: float, progress) -> dict:
    if not tile_m > 0 or not math.isfinite(tile_m):
        raise DataError(f"point tile size must be > 0 m, got {tile_m}")
    points = private_mapping(points)
    n = len(points)
    if points.ndim != 2 or points.shape[1] < 3 or n == 0:
        raise DataError(f"map points must be a non-empty (N, 3) array; got shape {points.shape}")
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for s in range(0, n, _CHUNK):  # pass 1: bounds, and every coordinate finite
        chunk = np.asarray(points[s : s + _CHUNK, :3], dtype=np.float32)
        if not np.isfinite(chunk).all():
            raise DataError(f"map points {s}…{s + len(chunk) - 1}: non-finite coordinates")
        lo = np.minimum(lo, chunk.min(axis=0))
        hi = np.maximum(hi, chunk.max(axis=0))
        progress(0.3 * (s + len(chunk)) / n)
    origin = np.floor(lo[:2] / tile_m) * tile_m
    ntx, nty = (int(v) for v in np.floor((hi[:2] - origin) / tile_m).astype(np.int64) + 1)
    directory.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=_STAGING, dir=directory))
    try:
        return _cut(points, directory, staging, key, tile_m, origin, ntx, nty, lo, hi, progress)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _cut(points, directory: Path, staging: Path, key: str, tile_m: float, origin, ntx: int, nty: int, lo, hi, progress):
    n = len(points)
    counts = np.zeros(ntx * nty, np.int64)
    for s in range(0, n, _CHUNK):  # pass 2: each chunk's points appended to their tiles, in order
        chunk = np.ascontiguousarray(points[s : s + _CHUNK, :3], dtype=np.float32)
        txy = _tile_xy(chunk, origin, tile_m, ntx, nty)
        t = txy[:, 0] * nty + txy[:, 1]
        order = np.argsort(t, kind="stable")
        t_sorted = t[order]
        starts = np.flatnonzero(np.r_[True, t_sorted[1:] != t_sorted[:-1]])
        ends = np.r_[starts[1:], len(t_sorted)]
        for a, b in zip(starts, ends, strict=True):
            tid = int(t_sorted[a])
            with open(staging / f"{tile_name(tid // nty, tid % nty)}.raw", "ab") as fh:
                fh.write(chunk[order[a:b]].tobytes())
            counts[tid] += b - a
        progress(0.3 + 0.4 * (s + len(chunk)) / n)
    tiles = {}
    filled = np.flatnonzero(counts)
    for i, tid in enumerate(filled):
        name = tile_name(int(tid) // nty, int(tid) % nty)
        raw = staging / f"{name}.raw"
        pts = np.fromfile(raw, np.float32).reshape(-1, 3)
        tiles[name] = write_tile(directory, name, {"points": pts})
        raw.unlink()
        progress(0.7 + 0.3 * (i + 1) / len(filled))
    return {
        "key": key,
        "origin": origin.tolist(),
        "tile_m": tile_m,
        "tiles_xy": [ntx, nty],
        "points": int(n),
        "bounds": [lo.tolist(), hi.tolist()],
        "tiles": tiles,
    }
