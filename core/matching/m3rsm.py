"""Multi-resolution scan matching (Olson's M3RSM) of a 2D scan against the BEV pyramid.

Maximises J(θ_r, t) = Σ_j L0(R_z(θ_r)·B_j + t) over discrete angles θ_r (step d_θ) and
translations t on a lattice of step d_m, by best-first branch and bound (paper, "Multi-Resolution
Scan Matching"): a max-heap of nodes (score, θ_r, level l, translation block); a node at level l
stands for the 2^l × 2^l block of lattice translations starting at (kx, ky); popping a node splits
its block into four quadrants at level l − 1; the first time the heap's best bound cannot beat the
best level-0 score found, that score is the global optimum over the whole search space — the
same optimum an exhaustive search finds.

Admissible bounds. Translations are t = anchor + k·d_m (k integer), so a scan point whose L0
cell at k = 0 is c lands in cell c + k: over a block k ∈ [kx, kx + 2^l) it visits exactly the
L0 cells [c + kx, c + kx + 2^l − 1] (per axis). Two bounds use that, both admissible (≥ the L0
score of every translation in the block, checked in tests/test_m3rsm.py):

* dense (levels 1..DENSE_UPTO): S_l[x] = max of L0 over [x, x + 2^l) — the 2^l × 2^l max-pooling
  with stride 1 — so the point contributes S_l[c + kx], the exact max over the cells it visits.
  S_l is S_{l−1} pooled over two cells 2^{l−1} apart, stored with a low-side pad of 2^l − 1 cells.
* strided (coarser levels): the paper's pyramid L_l (2 × 2 max-pooling, stride 2). Blocks at
  level l start at multiples of 2^l (the root tiling is aligned), so with kx = m·2^l the visited
  cells lie in level-l cells (c >> l) + m to ((c + 2^l − 1) >> l) + m: one cell when c is a
  multiple of 2^l, else two adjacent ones ("straddles"); the max over those ≤ 2 × 2 cells
  (precomputed per level) bounds the point. Each point then needs only (c >> l, straddles), so
  points sharing them merge into one weighted entry (Olson's per-level decimation of the query):
  at coarse levels ~1300 scan cells shrink to a few dozen entries.

The dense bound is tighter (a straddling point's strided bound spans up to 2·2^l cells), the
strided one is cheaper where merging pays. Measured on the KITTI raw drive 0013 (11 scans,
d_m = 1 m, d_θ = 2.5°, median, 2 cores shared with other jobs): all-strided 389 ms global /
68 ms local (±25 m, 360°); all-dense 138 / 35 ms; dense up to level 3, strided above 136 / 33 ms
(fewest nodes per unit of work). DENSE_UPTO = 3 is that split; merging wins more on larger maps,
where more coarse levels are searched.

For inspection a search also reports (``MatchResult.candidates``, ``nodes_per_level``) the best
level-0 poses it scored, best first, and the nodes it expanded per level. Keeping them costs one
comparison per leaf scored, and the search's order and result are those of a search that keeps
none, bit for bit (tests/test_m3rsm.py). They are the leaves of the blocks branch and bound did
not prune, often only the four of the last level-1 block: the tighter the bounds, the fewer
runners-up it ever scores.

The heap is an array binary heap inside the numba kernel, so a whole search runs without the
GIL (the particle filter's threads keep running). The alternative, Python's heapq driving a numba
kernel that bounds a node's four children in one call, found the same optima in 70 ms vs 38 ms
(local ±25 m / 360°, median of 10 KITTI scans) and holds the GIL between calls.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import LidarlocError
from ..maps.bev import BEVPyramid
from .bnb_kernels import (
    _angle_cells,
    _bound_grid,
    _branch_and_bound,
    _exhaustive,
    _sliding_max,
    level_entries,
    score_l0,
)

#: Levels 1..DENSE_UPTO use the dense (stride-1 pooled) bound, coarser levels the strided one.
DENSE_UPTO = 3
#: Level-0 poses a search keeps for inspection (MatchResult.candidates), best first.
N_CANDIDATES = 10


@dataclass(frozen=True)
class MatchResult:
    x: float  # world x of the sensor at the optimum (m)
    y: float
    yaw: float  # rad, wrapped to [-π, π)
    score: float  # L0 score of the optimum, Σ_j L0(cell of point j)
    nodes_expanded: int  # heap pops that were split into quadrants
    ms: float  # wall time of the search (including per-angle preparation)
    n_points: int = 0  # scan cells matched (after down-sampling to d_m)
    region: tuple = ()  # (x_min, y_min, x_max, y_max) of the sensor positions searched
    n_angles: int = 0
    # (K, 4) x, y, yaw, score of the best level-0 poses the search scored, best first (at most
    # ``keep_candidates``); the first is the optimum when there is one. Branch and bound scores
    # only the leaves of blocks it did not prune, so the others are the best it *saw*, not the
    # search space's runners-up; the exhaustive search sees them all.
    candidates: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)), compare=False)
    nodes_per_level: tuple = ()  # nodes expanded per pyramid level (index = level); sums to
    # nodes_expanded (the exhaustive search: all at level 0)


# ------------------------------------------------------------------------------------ scan side
def scan_cells(scan_xy: np.ndarray, resolution: float) -> np.ndarray:
    """Down-sample a 2D scan (sensor frame) to one point per occupied d_m cell (the centroid of the
    points in it), so dense near-range returns do not outweigh far structure. Sorted by cell, so
    the result (and every score computed from it) is deterministic."""
    xy = np.asarray(scan_xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] < 2:
        raise LidarlocError(f"scan must be (K, 2) x, y; got shape {xy.shape}")
    xy = xy[:, :2]
    xy = xy[np.isfinite(xy).all(axis=1)]
    if len(xy) == 0:
        return np.zeros((0, 2))
    idx = np.floor(xy / resolution).astype(np.int64)
    # One integer key a cell, in the (ix, iy) order np.unique(axis=0) would sort the rows in, but
    # counted by bincount over the scan's box of cells instead of sorted (a sensor-frame scan's box
    # is a few ten thousand cells: 0.1–2 ms a call where the row sort took 4–8 ms, and the windows
    # of a match by candidates call this once a window). The sums add the points in the scan's
    # order as np.add.at did: the same cells, bit for bit.
    lo = idx.min(axis=0)
    span = int(idx[:, 1].max() - lo[1]) + 1
    key = (idx[:, 0] - lo[0]) * span + (idx[:, 1] - lo[1])
    n_keys = int(key.max()) + 1
    if n_keys > 8 * len(key) + (1 << 16):  # a sparse box (a scan in world coordinates): sort instead
        _, key, counts = np.unique(key, return_inverse=True, return_counts=True)
        n_keys, occupied = len(counts), slice(None)
    else:
        counts = np.bincount(key, minlength=n_keys)
        occupied = np.flatnonzero(counts)
        counts = counts[occupied]
    sx = np.bincount(key, weights=xy[:, 0], minlength=n_keys)[occupied]
    sy = np.bincount(key, weights=xy[:, 1], minlength=n_keys)[occupied]
    return np.column_stack([sx, sy]) / counts[:, None]


def angle_lattice(step: float) -> np.ndarray:
    """The paper's discrete angles θ_r = −π + r·d_θ, r = 0 … ⌊2π / d_θ⌋ − 1 (world-fixed)."""
    n = max(1, int(math.floor(2.0 * math.pi / step + 1e-9)))
    return -math.pi + np.arange(n) * step


def _angles_window(center: float, window: float, step: float) -> np.ndarray:
    """Lattice angles θ_r within ±window of ``center`` (all of them if window ≥ π); the nearest one
    if the window holds none (window < d_θ / 2)."""
    lattice = angle_lattice(step)
    if window >= math.pi - 1e-12:
        return lattice
    off = np.abs((lattice - center + math.pi) % (2.0 * math.pi) - math.pi)
    inside = lattice[off <= window + 1e-12]
    return inside if len(inside) else lattice[[int(np.argmin(off))]]


# ------------------------------------------------------------------------------- preparation
class _Prepared:
    """The pyramid flattened for the kernels: L0, dense bound grids S_l for levels 1..dense_upto,
    strided bound grids G_l for levels ≥ strided_from (default dense_upto + 1). Only the levels a
    search can use are built: the dense grids grow by 2^l cells per axis per level.

    The grids are stored in the pyramid's type, the narrowest that holds every cell value exactly
    (:func:`~lidarloc.core.maps.bev.cell_dtype`): the saturated counts (the
    default ``sat8``) and binary cells fit in one byte, so the dense grids — three copies of a
    level-0-sized grid — take a quarter of the memory they take in float32 (the 4 × 4 km city:
    200 → 50 MB in the S2M process). The kernels add the cells up in float64 either way: scores,
    bounds, the search's order and its result are the same bit for bit (tests/test_m3rsm.py)."""

    def __init__(self, pyramid: BEVPyramid, dense_upto: int, strided_from: int | None = None):
        n = pyramid.n_levels
        strided_from = dense_upto + 1 if strided_from is None else strided_from
        self.n_levels = n
        level0 = pyramid.levels[0]
        self.dtype = level0.dtype.type  # the pyramid holds its cells in the narrowest exact type
        self.L0 = np.ascontiguousarray(level0)  # the pyramid's own array: no copy
        empty = np.zeros(0, self.dtype)
        grids, gnx, gny = [], [], []
        for l, lv in enumerate(pyramid.levels):
            use = 1 <= l and l >= strided_from
            grid = _bound_grid(np.ascontiguousarray(lv, dtype=np.float32)) if use else None
            grids.append(empty if grid is None else grid.ravel().astype(self.dtype))
            gnx.append(lv.shape[0])
            gny.append(lv.shape[1])
        self.G, self.goff = _flatten(grids, self.dtype)
        self.gnx = np.asarray(gnx, np.int64)
        self.gny = np.asarray(gny, np.int64)
        dense, snx, sny = [empty], [gnx[0]], [gny[0]]
        prev = np.ascontiguousarray(level0, dtype=np.float32)
        for l in range(1, min(dense_upto, n - 1) + 1):
            prev = _sliding_max(prev, l)  # float32, one level at a time: the narrow copy is kept
            dense.append(prev.ravel().astype(self.dtype))
            snx.append(prev.shape[0])
            sny.append(prev.shape[1])
        del prev
        self.S, self.soff = _flatten(dense, self.dtype)
        self.snx = np.asarray(snx, np.int64)
        self.sny = np.asarray(sny, np.int64)


def _flatten(arrays: list, dtype=np.float32) -> tuple[np.ndarray, np.ndarray]:
    offsets = np.cumsum([0] + [len(a) for a in arrays[:-1]]).astype(np.int64)
    return np.concatenate(arrays).astype(dtype, copy=False), offsets


_prep_lock = threading.Lock()


def _prepared(pyramid: BEVPyramid, dense_upto: int) -> _Prepared:
    """The kernels' view of ``pyramid`` for one dense/strided split, built once and kept on it."""
    key = ("m3rsm", dense_upto)
    prep = pyramid.derived.get(key)
    if prep is None:
        with _prep_lock:
            prep = pyramid.derived.get(key)
            if prep is None:
                prep = _Prepared(pyramid, dense_upto)
                pyramid.derived[key] = prep
    return prep


def angle_cells(pyramid: BEVPyramid, B: np.ndarray, angles: np.ndarray, anchor) -> tuple[np.ndarray, np.ndarray]:
    ax = float(anchor[0]) - float(pyramid.origin[0])
    ay = float(anchor[1]) - float(pyramid.origin[1])
    return _angle_cells(
        np.ascontiguousarray(B, np.float64), np.cos(angles), np.sin(angles), ax, ay, 1.0 / pyramid.resolution
    )


def _top_level(n_levels: int, width: int, height: int) -> int:
    """Coarsest level worth starting at: one block covers the region, capped by the pyramid."""
    span = max(width, height, 1)
    return int(min(n_levels - 1, max(0, math.ceil(math.log2(span)))))


def _wrap(yaw):
    return (yaw + math.pi) % (2 * math.pi) - math.pi


def _search(
    pyramid, scan_xy, anchor, angles, k_lo, k_hi, beat=-1.0, exhaustive=False, keep: int = N_CANDIDATES
) -> MatchResult:
    if keep < 0:
        raise LidarlocError(f"keep_candidates must be ≥ 0, got {keep}")
    t0 = time.perf_counter()
    B = scan_cells(scan_xy, pyramid.resolution)
    cx, cy = angle_cells(pyramid, B, angles, anchor)
    return search_cells(pyramid, cx, cy, anchor, angles, k_lo, k_hi, beat, exhaustive, keep, t0)


def search_cells(
    pyramid, cx, cy, anchor, angles, k_lo, k_hi, beat=-1.0, exhaustive=False, keep: int = N_CANDIDATES, t0=None
) -> MatchResult:
    """The search of :func:`match` for scan cells already placed on the pyramid's L0 grid (``cx``,
    ``cy`` per angle at translation 0, as :func:`angle_cells` places them): the tiled global
    search places them once on the city's grid and shifts them by whole cells into each tile."""
    t0 = time.perf_counter() if t0 is None else t0
    dense_upto = DENSE_UPTO
    prep = _prepared(pyramid, dense_upto)
    d = pyramid.resolution
    kx_lo, ky_lo = int(k_lo[0]), int(k_lo[1])
    kx_hi, ky_hi = int(k_hi[0]), int(k_hi[1])
    region = (anchor[0] + kx_lo * d, anchor[1] + ky_lo * d, anchor[0] + kx_hi * d, anchor[1] + ky_hi * d)
    keep = int(keep)
    if exhaustive:
        score, r, kx, ky, ts, tr, tx, ty, m = _exhaustive(prep.L0, cx, cy, kx_lo, kx_hi, ky_lo, ky_hi, keep)
        nodes = (kx_hi - kx_lo + 1) * (ky_hi - ky_lo + 1) * len(angles)
        per_level = (int(nodes),)
    else:
        top = _top_level(prep.n_levels, kx_hi - kx_lo + 1, ky_hi - ky_lo + 1)
        ex, ey, ec, ew, eoff = level_entries(cx, cy, dense_upto + 1, top)
        score, r, kx, ky, nodes, levels, ts, tr, tx, ty, m = _branch_and_bound(
            prep.L0,
            prep.G,
            prep.gnx,
            prep.gny,
            prep.goff,
            prep.S,
            prep.snx,
            prep.sny,
            prep.soff,
            dense_upto,
            cx,
            cy,
            ex,
            ey,
            ec,
            ew,
            eoff,
            top,
            kx_lo,
            kx_hi,
            ky_lo,
            ky_hi,
            float(beat),
            keep,
        )
        per_level = tuple(int(v) for v in levels)
    ms = (time.perf_counter() - t0) * 1e3
    # the same arithmetic as the optimum's pose below, so the first candidate equals it exactly
    candidates = (
        np.column_stack([anchor[0] + tx[:m] * d, anchor[1] + ty[:m] * d, _wrap(angles[tr[:m]]), ts[:m]])
        .astype(np.float64)
        .reshape(-1, 4)
    )
    common = dict(
        nodes_expanded=int(nodes),
        ms=ms,
        n_points=int(cx.shape[1]),
        region=region,
        n_angles=len(angles),
        candidates=candidates,
        nodes_per_level=per_level,
    )
    if r < 0:  # nothing strictly better than `beat`
        return MatchResult(x=math.nan, y=math.nan, yaw=math.nan, score=float(score), **common)
    return MatchResult(
        x=float(anchor[0] + kx * d),
        y=float(anchor[1] + ky * d),
        yaw=float(_wrap(angles[r])),
        score=float(score),
        **common,
    )


# ------------------------------------------------------------------------------------ public API
def match(
    pyramid: BEVPyramid,
    scan_xy: np.ndarray,
    center_xy,
    half_extent,
    yaw_center: float = 0.0,
    yaw_window: float = math.pi,
    angle_step: float = 2.5 * math.pi / 180.0,
    min_score: float | None = None,
    keep_candidates: int = N_CANDIDATES,
) -> MatchResult:
    """Local search (paper, "Scan-to-map matching"): translations center ± half_extent on a lattice
    of step d_m anchored at center_xy (the search rectangle's lower bound is center − half_extent,
    so the start position is on it), yaws θ_r = −π + r·d_θ within ± yaw_window of yaw_center (the
    full circle if yaw_window ≥ π).

    The angles are the paper's world-fixed lattice, not anchored at the start yaw: a start pose
    near the truth is then usually off the lattice, and the best lattice pose may or may not score
    above it; anchoring the yaws too would make the start itself a candidate, so a start already
    near the truth could never be beaten — and never refined by GICP.

    ``min_score``: report only an optimum strictly above it (blocks whose bound does not exceed it
    are pruned from the start); if there is none, x, y, yaw are NaN and score = min_score.

    ``keep_candidates``: how many of the best level-0 poses the search scored to report in
    ``MatchResult.candidates`` (0: none); keeping them changes neither the result nor the work."""
    if angle_step <= 0:
        raise LidarlocError(f"angle_step must be > 0, got {angle_step}")
    d = pyramid.resolution
    nx = int(math.floor(float(half_extent[0]) / d + 1e-9))
    ny = int(math.floor(float(half_extent[1]) / d + 1e-9))
    angles = _angles_window(float(yaw_center), float(yaw_window), float(angle_step))
    # The lattice starts at the region's lower corner (the paper's lower bound), so the root blocks
    # are aligned with the region: fewer blocks straddle its edges than with blocks aligned at the
    # centre (e.g. 7 instead of 8 level-3 blocks across ±25 cells). The start position is lattice
    # point (nx, ny).
    anchor = (float(center_xy[0]) - nx * d, float(center_xy[1]) - ny * d)
    beat = -1.0 if min_score is None else float(min_score)
    return _search(pyramid, scan_xy, anchor, angles, (0, 0), (2 * nx, 2 * ny), beat=beat, keep=keep_candidates)


def _global_lattice(pyramid: BEVPyramid):
    """Sensor positions at L0 cell centres over the whole grid."""
    d = pyramid.resolution
    anchor = (float(pyramid.origin[0]) + 0.5 * d, float(pyramid.origin[1]) + 0.5 * d)
    nx, ny = pyramid.shape
    return anchor, (0, 0), (nx - 1, ny - 1)


def match_global(
    pyramid: BEVPyramid,
    scan_xy: np.ndarray,
    angle_step: float = 2.5 * math.pi / 180.0,
    keep_candidates: int = N_CANDIDATES,
) -> MatchResult:
    """Global search: every L0 cell centre of the map as sensor position, θ_r = −π + r·d_θ.
    ``keep_candidates`` as for :func:`match`."""
    if angle_step <= 0:
        raise LidarlocError(f"angle_step must be > 0, got {angle_step}")
    anchor, lo, hi = _global_lattice(pyramid)
    return _search(pyramid, scan_xy, anchor, angle_lattice(angle_step), lo, hi, keep=keep_candidates)


def exhaustive_match(
    pyramid: BEVPyramid,
    scan_xy: np.ndarray,
    center_xy=None,
    half_extent=None,
    yaw_center: float = 0.0,
    yaw_window: float = math.pi,
    angle_step: float = 2.5 * math.pi / 180.0,
    keep_candidates: int = N_CANDIDATES,
) -> MatchResult:
    """Brute force over the same search space as :func:`match` (or :func:`match_global` when
    center_xy is None). For tests; O(angles × translations × points)."""
    d = pyramid.resolution
    if center_xy is None:
        anchor, lo, hi = _global_lattice(pyramid)
        angles = angle_lattice(angle_step)
    else:
        nx = int(math.floor(float(half_extent[0]) / d + 1e-9))
        ny = int(math.floor(float(half_extent[1]) / d + 1e-9))
        anchor = (float(center_xy[0]) - nx * d, float(center_xy[1]) - ny * d)
        lo, hi = (0, 0), (2 * nx, 2 * ny)
        angles = _angles_window(float(yaw_center), float(yaw_window), float(angle_step))
    return _search(pyramid, scan_xy, anchor, angles, lo, hi, exhaustive=True, keep=keep_candidates)


def score_pose(pyramid: BEVPyramid, scan_xy: np.ndarray, x: float, y: float, yaw: float) -> float:
    """L0 score of one pose, computed exactly as the search scores its candidates (same scan
    down-sampling, same cell arithmetic), so it is comparable with MatchResult.score."""
    prep = _prepared(pyramid, DENSE_UPTO)
    B = scan_cells(scan_xy, pyramid.resolution)
    cx, cy = angle_cells(pyramid, B, np.array([float(yaw)]), (float(x), float(y)))
    return float(score_l0(prep.L0, cx[0], cy[0], 0, 0))
