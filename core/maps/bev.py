"""Bird's-eye-view (BEV) grid pyramid of the road-removed map, for the M3RSM matcher.

Paper, "Multi-Resolution Scan Matching": level L0 is a 2D grid at the match resolution d_m whose
cell value is the number of map points in it (or 1/0 occupancy); levels L1, L2, … are 2×2
max-pooling with stride 2, up to a grid of a single-digit number of cells.

Cell values. Raw counts of a 0.2 m voxel map in 1 m cells range from 1 (a lamp post, a kerb)
to hundreds (a 20 m façade stacks ~100 voxels per metre of wall), so with raw counts a pose's
score is dominated by the few scan cells that hit tall walls; occupancy (binary) treats a stray
voxel like a wall. A saturating count ``min(count, c)`` keeps "more evidence is better" for sparse
cells without letting façades dominate, and keeps the branch and bound fast (a low ceiling means
coarse-level bounds are not inflated by a single dense cell). Measured on the KITTI raw drive
0013 (d_m = 1 m, d_θ = 2.5°, whole-map search; 2 cores shared with other jobs, load ≈ 4):

=========  ===================  =================  ================  ===========
value      margin (10 scans)    success (50)       global ms (50)    notes
=========  ===================  =================  ================  ===========
binary     1.44 (min 1.39)      0.86               118
sat4       1.49 (min 1.43)      0.86               167
sat8       1.54 (min 1.46)      0.90               178               default
sat16      –                    0.90               212
sat32      1.64 (min 1.56)      0.92               238
log        1.57 (min 1.52)      0.94               271               log1p(count)
count      1.58 (min 1.41)      0.94               391               raw counts
=========  ===================  =================  ================  ===========

"margin" = best exhaustive score within 2 m / 3° of the truth ÷ best score farther than 5 m or
10° (how clearly the true pose stands out; raw counts have the widest spread across scans);
"success" = RMSE ≤ 1 m of the 2D match (every match on this drive lands in the right basin: the
spread is the lattice quantisation, ±4 % noise at 50 scans); times are medians. ``sat8`` is the
compromise: half of sat32's margin gain over binary at 3/4 of its time; log and raw counts add a
little margin at 1.5–2.2× sat8's time. The margins come from a one-off exhaustive score map
(all 144 angles × all cells); ``lidarloc bench s2m --cell-study`` reproduces the other columns.

Layout: ``levels[l]`` is an array indexed ``[ix, iy]``, in the narrowest type that holds its cells
exactly (:func:`cell_dtype`: uint8 for sat8 and binary, float32 for log); cell (ix, iy) of level l covers
world x ∈ [origin_x + ix·2^l·d_m, origin_x + (ix+1)·2^l·d_m) (same for y). ``origin`` is a
multiple of d_m so that the L0 lattice is the world lattice of step d_m.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..cache import Cached, atomic_write_dir, cache_rebuilt
from ..config import S2MConfig
from ..errors import LidarlocError

#: Default L0 cell value: "count", "binary", "log" (log1p of the count) or "sat<c>" (min(count, c)).
#: S2MConfig.binary_cells = True overrides it with "binary". See the module docstring for the study.
DEFAULT_CELL_VALUE = "sat8"

_PYRAMID_FORMAT = 1
_MAX_TOP_CELLS = 9


def _cell_values(counts: np.ndarray, cell_value: str) -> np.ndarray:
    counts = counts.astype(np.float32)
    if cell_value == "count":
        return counts
    if cell_value == "binary":
        return (counts > 0).astype(np.float32)
    if cell_value == "log":
        return np.log1p(counts).astype(np.float32)
    if cell_value.startswith("sat"):
        try:
            cap = float(cell_value[3:])
        except ValueError:
            cap = -1.0
        if cap > 0:
            return np.minimum(counts, cap).astype(np.float32)
    raise LidarlocError(f"invalid BEV cell value '{cell_value}': expected count, binary, log or sat<c> (c > 0)")


def cell_dtype(level0: np.ndarray) -> type:
    """The narrowest of uint8, uint16 and float32 that holds every value of ``level0`` exactly
    (saturated counts and binary cells: uint8; log cells: float32). Every coarser grid built from
    it holds maxima of its cells, so it fits the same type; sums over cells are taken in float64
    by the matcher, the same whatever the type."""
    values = np.asarray(level0)
    if values.size == 0:
        return np.uint8
    if values.dtype.kind in "ui" and values.min() >= 0 and values.max() <= 65535:
        return np.uint8 if values.max() <= 255 else np.uint16
    values = values.astype(np.float32, copy=False)
    lo, hi = float(values.min()), float(values.max())
    if lo < 0.0 or not np.isfinite(hi) or not np.array_equal(values, np.floor(values)):
        return np.float32
    return np.uint8 if hi <= 255 else np.uint16 if hi <= 65535 else np.float32


def max_pool2(grid: np.ndarray) -> np.ndarray:
    """2×2 max-pooling with stride 2; an odd edge is padded with zeros (cells with no map points)."""
    nx, ny = grid.shape
    padded = np.zeros((nx + (nx & 1), ny + (ny & 1)), dtype=grid.dtype)
    padded[:nx, :ny] = grid
    return np.maximum.reduce([padded[0::2, 0::2], padded[1::2, 0::2], padded[0::2, 1::2], padded[1::2, 1::2]])


@dataclass
class BEVPyramid:
    resolution: float  # d_m, metres per L0 cell
    origin: np.ndarray  # (2,) world x, y of the lower corner of L0 cell (0, 0)
    levels: list  # [L0, L1, …], (nx_l, ny_l) in the narrowest exact type (cell_dtype)
    cell_value: str = DEFAULT_CELL_VALUE
    meta: dict = field(default_factory=dict)
    # What a matcher derives from the levels, built on first use and kept with them (M3RSM's
    # flattened bound grids, by its key); never saved.
    derived: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self):
        # Integer cells (saturated counts, binary, counts) are held in one or two bytes rather than
        # four: the 4 × 4 km city's pyramid is 88 MB in float32, 22 MB in uint8. Every level is a
        # max-pool of L0, so L0's type holds them all.
        if self.levels:
            dtype = cell_dtype(self.levels[0])
            self.levels = [np.ascontiguousarray(lv, dtype=dtype) for lv in self.levels]

    @property
    def shape(self) -> tuple[int, int]:
        return self.levels[0].shape

    @property
    def n_levels(self) -> int:
        return len(self.levels)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of L0 in world metres."""
        nx, ny = self.shape
        x0, y0 = self.origin
        return float(x0), float(y0), float(x0 + nx * self.resolution), float(y0 + ny * self.resolution)

    @classmethod
    def build(
        cls, xy: np.ndarray, resolution: float, binary: bool = False, cell_value: str | None = None
    ) -> BEVPyramid:
        """Pyramid of the map points ``xy`` (N, ≥2), world frame. ``binary`` (S2MConfig.binary_cells)
        forces occupancy; otherwise ``cell_value`` (default :data:`DEFAULT_CELL_VALUE`)."""
        if resolution <= 0:
            raise LidarlocError(f"invalid BEV resolution {resolution}: must be > 0")
        xy = np.asarray(xy, dtype=np.float64)[:, :2]
        if len(xy) == 0:
            raise LidarlocError("cannot build a BEV pyramid from an empty map (no road-removed points)")
        cell_value = "binary" if binary else (cell_value or DEFAULT_CELL_VALUE)
        idx = np.floor(xy / resolution).astype(np.int64)
        lo = idx.min(axis=0)
        idx -= lo
        nx, ny = (idx.max(axis=0) + 1).tolist()
        counts = np.zeros((nx, ny), dtype=np.int64)
        np.add.at(counts, (idx[:, 0], idx[:, 1]), 1)
        levels = [_cell_values(counts, cell_value)]
        while levels[-1].size > _MAX_TOP_CELLS:
            levels.append(max_pool2(levels[-1]))
        origin = lo.astype(np.float64) * resolution
        return cls(
            resolution=float(resolution),
            origin=origin,
            levels=levels,
            cell_value=cell_value,
            meta={"map_points": int(len(xy)), "occupied_cells": int((counts > 0).sum())},
        )

    # ---------------------------------------------------------------------------- persistence
    def save(self, directory: Path) -> None:
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        np.savez(directory / "levels.npz", **{f"L{i}": lv for i, lv in enumerate(self.levels)})
        info = {
            "format": _PYRAMID_FORMAT,
            "resolution": self.resolution,
            "origin": self.origin.tolist(),
            "cell_value": self.cell_value,
            "n_levels": self.n_levels,
            "meta": self.meta,
        }
        (directory / "pyramid.json").write_text(json.dumps(info, indent=2))

    @classmethod
    def load(cls, directory: Path) -> BEVPyramid:
        directory = Path(directory)
        try:
            info = json.loads((directory / "pyramid.json").read_text())
            if info.get("format") != _PYRAMID_FORMAT:
                raise ValueError("format")
            with np.load(directory / "levels.npz") as data:
                levels = [np.ascontiguousarray(data[f"L{i}"]) for i in range(info["n_levels"])]
        except (OSError, ValueError, KeyError) as exc:
            raise LidarlocError(f"{directory}: unreadable BEV pyramid ({exc})") from None
        return cls(
            resolution=float(info["resolution"]),
            origin=np.asarray(info["origin"], dtype=np.float64),
            levels=levels,
            cell_value=info["cell_value"],
            meta=info.get("meta", {}),
        )


def pyramid_cache_name(s2m_cfg: S2MConfig, cell_value: str | None = None) -> str:
    value = "binary" if s2m_cfg.binary_cells else (cell_value or DEFAULT_CELL_VALUE)
    return f"bev-d{s2m_cfg.match_resolution:g}-{value}"


def load_or_build_pyramid(
    prior_map, map_cache_dir: Path | None, s2m_cfg: S2MConfig, cell_value: str | None = None
) -> Cached[BEVPyramid]:
    """The BEV pyramid of ``prior_map.points_bev``, cached in a subdirectory of the map's cache
    directory (keyed by resolution and cell value). With ``map_cache_dir=None`` it is built, not
    cached (the result's directory is then None)."""
    directory = None if map_cache_dir is None else Path(map_cache_dir) / pyramid_cache_name(s2m_cfg, cell_value)
    if directory is not None and (directory / "pyramid.json").is_file():
        try:
            return Cached(BEVPyramid.load(directory), directory, True)
        except LidarlocError as exc:  # rebuilt below
            cache_rebuilt(directory, str(exc).split(": ", 1)[-1])
    t0 = time.perf_counter()
    pyramid = BEVPyramid.build(prior_map.points_bev, s2m_cfg.match_resolution, s2m_cfg.binary_cells, cell_value)
    pyramid.meta["build_seconds"] = time.perf_counter() - t0
    if directory is not None:
        try:
            atomic_write_dir(directory, pyramid.save)
        except OSError as exc:
            raise LidarlocError(f"{directory}: cannot write the BEV pyramid cache ({exc.strerror})") from None
    return Cached(pyramid, directory, False)
