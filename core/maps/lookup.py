"""The nearest-distance lookup table L of the sensor model (paper: Sensor model).

For every node of a regular grid of resolution δ over the map's bounding box, L holds the
distance from the node to its nearest map point, kept only where it is below ``d_max``; every
other node, and anything outside the grid, reads as ``d_max``. The likelihood then needs one
table read per scan point instead of a nearest-neighbour search.

The grid is the bounding box grown by the built d_max on every side (a deliberate difference
from the paper's tight box): beyond it every point is ≥ d_max from the map, so reading d_max
there is exact. On the tight box, ground returns a few centimetres below the map's lowest point
(half of them on a flat map) fall outside and read d_max, which measurably pushed a toy filter
1.4 m upwards. The extra cells cost little: only the band within d_max of a point is stored.

Where the nodes are
    Node (i, j, k) is the *centre* of cell [origin + (i, j, k)·δ, origin + (i+1, j+1, k+1)·δ) and a
    query point reads the node of the cell it falls in (the paper's ``floor((x − lb)/δ)``). The
    paper puts the node at the cell corner; the centre halves the worst-case read error, because
    the distance function is 1-Lipschitz: |d(q) − d(node)| ≤ |q − node| ≤ δ·√3/2 (0.22 m at
    δ = 0.25 m) instead of δ·√3.

How it is stored (block-sparse, uint8)
    Distances are quantised to uint8 codes with step d_max_built/254; code 255 means "≥ d_max".
    The rounding error (≤ 1 cm at d_max = 5 m) is small against δ·√3/2. Cells are grouped into
    bricks of 8³ (2 m at δ = 0.25 m); only bricks holding at least one node within d_max are
    allocated (512 bytes each) and a dense int32 array over the brick grid maps a brick to its
    slot in the pool. Slot 0 is a shared all-miss brick, so a read is two dependent loads and
    no branch on "is this brick allocated". A hash map (the paper's choice) would cost ≥ 8 bytes
    of key per stored node and a probe loop per read; the brick grid costs 4 bytes per 512 cells.

    Measured at δ = 0.25 m, d_max = 5 m (``lidarloc bench pf``, 2 shared cores, load 1.3–3):

    - KITTI raw 0013 map (268 × 160 × 35 m, 0.87M points): 34 MB, built in ~3 s.
    - KITTI-05-sized synthetic map (485 × 430 × 42 m, 8.6M points, hilly ground over the whole
      box, so more band than a real drive's map): 482k bricks = 252 MB (a dense uint8 grid of
      the same box would be 725 MB), built in 39 s with a build peak RSS of 1.0 GB (0.29 GB of
      it the process and points before the build), loaded from the cache in 0.07 s.
    - The built-in town's map (403 × 259 × 7 m, 1.5M points): 73 MB, built in 7.6 s.

Changing d_max
    Reads are clamped at the caller's d_max (``min(d, d_max)``), so any d_max ≤ ``d_max_built``
    needs no rebuild. ``load_or_build_lookup`` also reuses a cached table of the same δ built for
    a larger d_max.

``lookup_code`` is a numba ``nogil`` function for use inside other numba kernels (it serves
``LookupTable.query``) and takes the table's origin, inv_res, brick_index and bricks. The likelihood
kernel inlines the same read in a vectorisable form and takes ``LookupTable.flat_kernel_args``.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from pathlib import Path

import numba as nb
import numpy as np

from ..cache import Cached, atomic_write_dir, cache_rebuilt
from ..errors import DataError, LidarlocError
from .bricks import BRICK, BRICK_CELLS, BRICK_MASK, BRICK_SHIFT, MAX_CODE, MISS_CODE  # noqa: F401  (BRICK_* and MISS_CODE: the table's format, read by the kernels)
from .distance_transform import build_bricks

_FORMAT_VERSION = 1


# ----------------------------------------------------------------------------------- reading
@nb.njit(nogil=True, cache=True, fastmath=True, inline="always")
def lookup_code(x, y, z, origin, inv_res, brick_index, bricks):
    """Quantised distance code of the node of the cell holding (x, y, z); MISS_CODE outside.

    Multiply by the table's ``step`` for metres. Bounds are checked against the brick grid:
    cells beyond the box inside the last brick are stored as misses.
    """
    fx = (x - origin[0]) * inv_res
    fy = (y - origin[1]) * inv_res
    fz = (z - origin[2]) * inv_res
    if fx < 0.0 or fy < 0.0 or fz < 0.0:
        return MISS_CODE
    ix = np.int64(fx)
    iy = np.int64(fy)
    iz = np.int64(fz)
    bx = ix >> BRICK_SHIFT
    by = iy >> BRICK_SHIFT
    bz = iz >> BRICK_SHIFT
    if bx >= brick_index.shape[0] or by >= brick_index.shape[1] or bz >= brick_index.shape[2]:
        return MISS_CODE
    slot = brick_index[bx, by, bz]
    cell = ((ix & BRICK_MASK) << 6) | ((iy & BRICK_MASK) << 3) | (iz & BRICK_MASK)
    return np.int64(bricks[slot, cell])


@nb.njit(nogil=True, cache=True, parallel=True, fastmath=True)
def _query(points, origin, inv_res, step, d_max, brick_index, bricks, out):
    for i in nb.prange(points.shape[0]):
        code = lookup_code(
            np.float64(points[i, 0]),
            np.float64(points[i, 1]),
            np.float64(points[i, 2]),
            origin,
            inv_res,
            brick_index,
            bricks,
        )
        out[i] = min(np.float32(code * step), np.float32(d_max))


# ----------------------------------------------------------------------------------- building
def grid_over(lo, hi, resolution: float, d_max: float) -> tuple[np.ndarray, np.ndarray]:
    """(origin, shape) of the table's grid over map points bounded by ``lo`` and ``hi`` (their
    per-axis minimum and maximum). The grid covers the map's bounding box grown by d_max on every
    side: outside that, every point is ≥ d_max from the map, so "outside reads d_max" is exact. (On
    the tight box of the paper, ground returns a few cm below the map's lowest point would read
    d_max.)"""
    lo = np.asarray(lo).astype(np.float64) - d_max
    hi = np.asarray(hi).astype(np.float64) + d_max
    return lo, np.floor((hi - lo) / resolution).astype(np.int64) + 1


class LookupTable:
    """Block-sparse quantised nearest-map-point distances over the map's bounding box."""

    def __init__(
        self, origin, resolution: float, d_max_built: float, shape, brick_index: np.ndarray, bricks: np.ndarray
    ):
        self.origin = np.asarray(origin, dtype=np.float64).reshape(3)
        self.resolution = float(resolution)
        self.d_max_built = float(d_max_built)
        self.shape = tuple(int(s) for s in shape)  # cells per axis
        self.brick_index = np.ascontiguousarray(brick_index, dtype=np.int32)
        self.bricks = np.ascontiguousarray(bricks, dtype=np.uint8)
        self.step = self.d_max_built / MAX_CODE  # metres per code
        self.inv_res = 1.0 / self.resolution
        self._flat_args: tuple | None = None

    # -------------------------------------------------------------------------- properties
    @property
    def nbytes(self) -> int:
        return int(self.brick_index.nbytes + self.bricks.nbytes)

    @property
    def n_bricks(self) -> int:
        """Allocated bricks, not counting the shared all-miss brick in slot 0."""
        return int(self.bricks.shape[0] - 1)

    @property
    def flat_kernel_args(self) -> tuple:
        """(origin, inv_res, nbx, nby, nbz, slot_of_brick, cells) for the likelihood kernel.

        ``slot_of_brick`` is brick_index flattened, plus one extra entry at nbx·nby·nbz holding
        slot 0 (the shared all-miss brick): a point outside the grid reads through that entry, so
        the read has no branch. ``cells`` is the brick pool flattened (slot · 512 + cell). Made
        once per table; the brick shape is int32 so the kernel's index arithmetic stays 32-bit."""
        if self._flat_args is None:
            n_grid = self.brick_index.size
            if n_grid >= 2**31 - 1:
                raise LidarlocError(f"lookup table too large for the likelihood kernel: {n_grid} bricks in its grid")
            slot_of_brick = np.empty(n_grid + 1, np.int32)
            slot_of_brick[:n_grid] = self.brick_index.ravel()
            slot_of_brick[n_grid] = 0
            nbx, nby, nbz = (np.int32(s) for s in self.brick_index.shape)
            self._flat_args = (self.origin, self.inv_res, nbx, nby, nbz, slot_of_brick, self.bricks.reshape(-1))
        return self._flat_args

    def __repr__(self) -> str:
        return (
            f"LookupTable(δ={self.resolution} m, d_max_built={self.d_max_built} m, cells={self.shape}, "
            f"bricks={self.n_bricks}, {self.nbytes / 1e6:.1f} MB)"
        )

    # -------------------------------------------------------------------------- reading
    def capped(self, d_max: float) -> float:
        """The distance cap a read of this table gives for a requested ``d_max``: the request,
        but no more than the table was built for (it holds nothing farther; a larger d_max needs
        a table built for it). The one place this rule is written."""
        return min(float(d_max), self.d_max_built)

    def covers(self, d_max: float) -> bool:
        """Whether reads up to ``d_max`` need no other table (it was built for at least that)."""
        return float(d_max) <= self.d_max_built + 1e-9

    def query(self, points: np.ndarray, d_max: float | None = None) -> np.ndarray:
        """Distances (float32, metres) of (M, ≥3) points to the map, capped at ``d_max``
        (default: the built d_max; larger values are capped at the built one)."""
        cap = self.d_max_built if d_max is None else self.capped(d_max)
        pts = np.ascontiguousarray(np.asarray(points)[:, :3], dtype=np.float64)
        out = np.empty(len(pts), np.float32)
        if len(pts):
            _query(pts, self.origin, self.inv_res, self.step, cap, self.brick_index, self.bricks, out)
        return out

    # -------------------------------------------------------------------------- building
    @classmethod
    def build(
        cls,
        points: np.ndarray,
        resolution: float,
        d_max: float,
        progress: Callable[[float], None] | None = None,
        threads: int | None = None,
    ) -> LookupTable:
        """Build from (N, ≥3) map points. ``progress(fraction)`` is called after each tile."""
        resolution, d_max = float(resolution), float(d_max)
        if not (resolution > 0 and math.isfinite(resolution)):
            raise LidarlocError(f"lookup resolution must be > 0, got {resolution}")
        if not (d_max > 0 and math.isfinite(d_max)):
            raise LidarlocError(f"lookup d_max must be > 0, got {d_max}")
        pts = np.asarray(points)
        if pts.ndim != 2 or pts.shape[1] < 3:
            raise DataError(f"map points must be (N, 3); got shape {pts.shape}")
        # float32 maps (the prior map's type) are used as they are: no 8-byte copy of millions
        # of points; the arithmetic below is done in float64 either way.
        pts = np.ascontiguousarray(pts[:, :3], dtype=pts.dtype if pts.dtype in (np.float32, np.float64) else np.float64)
        if len(pts) == 0:
            raise DataError("cannot build a lookup table from an empty map")
        if not np.isfinite(pts).all():
            raise DataError("map points contain NaN or infinite coordinates")
        lo, shape = grid_over(pts.min(axis=0), pts.max(axis=0), resolution, d_max)
        brick_index, bricks = build_bricks(pts, lo, shape, resolution, d_max, progress, threads)
        return cls(lo, resolution, d_max, shape, brick_index, bricks)

    # -------------------------------------------------------------------------- cache
    def save(self, directory: Path) -> None:
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        np.save(directory / "brick_index.npy", self.brick_index)
        np.save(directory / "bricks.npy", self.bricks)
        meta = {
            "version": _FORMAT_VERSION,
            "origin": self.origin.tolist(),
            "resolution": self.resolution,
            "d_max_built": self.d_max_built,
            "shape": list(self.shape),
            "bricks": self.n_bricks,
            "nbytes": self.nbytes,
        }
        (directory / "lookup.json").write_text(json.dumps(meta, indent=2))

    @classmethod
    def load(cls, directory: Path) -> LookupTable:
        directory = Path(directory)
        try:
            meta = json.loads((directory / "lookup.json").read_text())
            if meta.get("version") != _FORMAT_VERSION:
                raise DataError(f"{directory}: lookup table format {meta.get('version')} (expected {_FORMAT_VERSION})")
            brick_index = np.load(directory / "brick_index.npy")
            bricks = np.load(directory / "bricks.npy")
            table = cls(meta["origin"], meta["resolution"], meta["d_max_built"], meta["shape"], brick_index, bricks)
        except DataError:
            raise
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise DataError(f"{directory}: unreadable lookup table ({type(exc).__name__}: {exc})") from None
        nb_expected = tuple((s + BRICK - 1) // BRICK for s in table.shape)
        if (
            table.brick_index.shape != nb_expected
            or table.bricks.ndim != 2
            or table.bricks.shape[1] != BRICK_CELLS
            or len(table.bricks) == 0
            or (
                table.brick_index.size and (table.brick_index.min() < 0 or table.brick_index.max() >= len(table.bricks))
            )
        ):
            raise DataError(f"{directory}: corrupt lookup table (inconsistent array shapes)")
        return table


def _cache_name(resolution: float, d_max: float) -> str:
    return f"lookup-r{resolution:.6g}-d{d_max:.6g}"


def load_or_build_lookup(
    prior_map, map_cache_dir: Path, resolution: float, d_max: float, progress: Callable[[float], None] | None = None
) -> Cached[LookupTable]:
    """The lookup table of ``prior_map`` from ``map_cache_dir/lookup-r<δ>-d<d_max>``, or built and
    cached there atomically. A cached table of the same δ built for a larger d_max is reused
    (reads clamp at the caller's d_max); the result names the directory it came from."""
    map_cache_dir = Path(map_cache_dir)
    resolution, d_max = float(resolution), float(d_max)
    candidates = [map_cache_dir / _cache_name(resolution, d_max)]
    if map_cache_dir.is_dir():
        others = []
        for entry in map_cache_dir.glob(f"lookup-r{resolution:.6g}-d*"):
            try:
                built = float(entry.name.rsplit("-d", 1)[1])
            except ValueError:
                continue
            if built > d_max and entry.is_dir():
                others.append((built, entry))
        candidates += [entry for _, entry in sorted(others)]
    for directory in candidates:
        if (directory / "lookup.json").is_file():
            try:
                return Cached(LookupTable.load(directory), directory, True)
            except DataError as exc:  # rebuilt below (the exact key is overwritten)
                cache_rebuilt(directory, str(exc).split(": ", 1)[-1])
    t0 = time.perf_counter()
    table = LookupTable.build(prior_map.points, resolution, d_max, progress=progress)
    build_s = time.perf_counter() - t0

    def write(tmp: Path):
        table.save(tmp)
        meta = json.loads((tmp / "lookup.json").read_text())
        meta["build_seconds"] = build_s
        (tmp / "lookup.json").write_text(json.dumps(meta, indent=2))

    try:
        atomic_write_dir(candidates[0], write)
    except OSError as exc:
        raise LidarlocError(f"{candidates[0]}: cannot write the lookup-table cache ({exc.strerror})") from None
    return Cached(table, candidates[0], False)
