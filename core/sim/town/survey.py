"""A city's prior map, sampled straight from its surfaces at survey density: what a
mobile-mapping product of every street delivers, instead of a simulated mapping drive.

Why not a mapping drive: mapping a town fuses the 1200 scans of one drive (25 s); a city has
hundreds of kilometres of streets, and a drive along all of them would take hours of simulated
scans. Sampling the surfaces gives each 0.2 m voxel its point directly, street by street.

What the survey keeps is what a mapping van driving every street sees (constants below):

- the ground (road, sidewalks, front yards) up to GROUND_REACH beyond the road's edge
  (OPEN_GROUND_REACH across the open ground of the highway's corridor and the parks), on the
  map's voxel grid (one point per voxel column, on the road or the raised lot surface);
- every other surface (walls, fences, trees, poles, parked cars, curbs …) up to OBJECT_REACH
  beyond the road's edge and SURVEY_TOP above the ground, sampled on a grid of 0.9 voxel along
  each triangle's edges;
- only what is in sight: a point counts if the line from it to a scanner SURVEY_HEIGHT above
  the road passes over every opaque object between them (buildings, walls, containers: the
  city's ``cover`` raster) — the line to the nearest road, or for a wall the line halfway
  between that one and the way the wall faces (a passing scanner sees side walls at an
  angle), or straight out of the wall to another street — so back yards, back walls and what
  stands behind a building are missing as they are from a real survey; roofs and other tops
  above the scanner are missing too (seen from below, a surface facing up is not seen), and so
  is what lies below the ground surface (a wall's foot on a slope).

The reaches trade completeness against size: a scan from the road finds 97–99 % of its points
within 40 m on the map (the rest mostly open ground beyond the reach), and the 4 km city's map
is already 412 M points, 60 % of them ground along the streets (docs/city.md).

Each voxel's point is the centroid of the samples in it, as a fused map's is of its returns.
The road-removed copy (the bird's-eye-view map) drops the voxels whose samples lie mostly on
flat surfaces: the same rule as for a fused map (|normal z| > ``map.road_normal_z``) with each
triangle's exact normal instead of one estimated from the points; curbs count as road. The map
lists those upright voxels first, so that the road-removed copy is a slice of it, not a copy.

The work goes block by block (256 m squares, two at a time), so that only two blocks' samples
are held at once; the points are in the city's frame (the frame of every drive through it).
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numba as nb
import numpy as np

from ...maps.voxelhash import hash_slot, voxel_key
from .constants import CELL, CURB
from .districts import HIGHWAY, PARK
from .survey_sight import cells_in_sight, ground_columns, height, sight

GROUND_REACH = 8.0  # m beyond the road's edge: sidewalks, the front of the lots
OPEN_GROUND_REACH = 30.0  # m beyond the road's edge across open ground (the highway's corridor, parks)
OBJECT_REACH = 40.0  # m beyond the road's edge
SURVEY_TOP = 15.0  # m above the ground
SURVEY_HEIGHT = 2.5  # m, the survey scanner above the road
#: m: a surface point this far below the ground at its place is buried (a building's walls go
#: down to its lowest corner's ground: on a slope their foot is under the terrain on the high
#: side). Kept, such points made the street beside a building on a slope look walled in to the
#: place index (a "ground" 0.9 m lower within 3 m), where a scan sees open ground.
BURIED = 0.1
SURVEY_VERSION = 2
BLOCK = 256.0  # m: two blocks in the making take a few hundred MB
COVER_STEP = 0.25  # m per unit of the city's cover raster
_GROUND_PARTS = ("road", "sidewalk_lot")
_FLAT_PARTS = ("curb",)
_FOLIAGE = ("crown", "bush", "hedge")
_CHUNK_SAMPLES = 4_000_000


class CitySurvey:
    """The source of a city's prior map (what a sequence's ``map_source`` is for a drive):
    :func:`lidarloc.core.maps.mapping.build_prior_map` asks it for the map (``delivers_map``)."""

    delivers_map = True

    def __init__(self, town):
        self.town = town
        self.name = f"{town.name}-{town.extent_m:g}m-survey"

    @property
    def map_source(self) -> CitySurvey:
        return self

    def identity(self) -> str:
        from .city import city_identity

        return (
            f"{city_identity(self.town.seed, self.town.extent_m)}|survey=v{SURVEY_VERSION}|ground={GROUND_REACH:g}"
            f"|open={OPEN_GROUND_REACH:g}|objects={OBJECT_REACH:g}|top={SURVEY_TOP:g}|scanner={SURVEY_HEIGHT:g}"
        )

    def cache_key(self) -> str:
        return hashlib.sha1(self.identity().encode()).hexdigest()[:16]

    def prior_map(self, cfg, progress: Callable[[int, int], None] | None = None):
        """The :class:`~lidarloc.core.maps.mapping.PriorMap` at ``cfg.voxel_size`` with its road-removed copy."""
        from ...maps.mapping import PriorMap

        points, bev = survey_points(self.town, cfg.voxel_size, cfg.road_normal_z, progress)
        return PriorMap(points=points, points_bev=bev, voxel_size=cfg.voxel_size, source=self.name)

    def __repr__(self) -> str:
        return f"CitySurvey({self.name!r})"


def survey_points(
    town,
    voxel: float,
    road_normal_z: float,
    progress: Callable[[int, int], None] | None = None,
    region: tuple[float, float, float, float] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 3), road-removed points (M, 3)), float32, one per voxel (see the module);
    ``region`` (x0, y0, x1, y1): only that part of the city."""
    plan, raster = town.plan, town.raster
    if plan is None:
        raise RuntimeError("a city's survey needs its ground plan (a city built here, not a pickled copy)")
    x_lo, y_lo = raster.x0, raster.y0
    x_hi, y_hi = raster.x0 + raster.nx * CELL, raster.y0 + raster.ny * CELL
    if region is not None:
        x_lo, y_lo = max(x_lo, region[0]), max(y_lo, region[1])
        x_hi, y_hi = min(x_hi, region[2]), min(y_hi, region[3])
    blocks = [(x0, y0) for x0 in np.arange(x_lo, x_hi, BLOCK) for y0 in np.arange(y_lo, y_hi, BLOCK)]
    upright, flat = _Rows(), _Rows()

    def one(block):
        x0, y0 = block
        return _block(town, voxel, road_normal_z, x0, y0, min(x0 + BLOCK, x_hi), min(y0 + BLOCK, y_hi))

    # Two blocks at a time: the kernels release the GIL, and both cores are busy. Each block's
    # points are copied into big chunks at once and dropped: hundreds of blocks' arrays kept
    # until the end would leave the heap in pieces that the allocator never returns (a 4 km
    # city's survey peaked 3 GB higher that way).
    with ThreadPoolExecutor(2, thread_name_prefix="lidarloc-survey") as pool:
        pending = {}
        for k, block in enumerate(blocks):
            pending[k] = pool.submit(one, block)
            if k >= 1:
                _take(pending.pop(k - 1).result(), upright, flat, progress, k, len(blocks))
        _take(pending.pop(len(blocks) - 1).result(), upright, flat, progress, len(blocks), len(blocks))
    # One array: the upright voxels first, then the flat ones, so that the road-removed map is a
    # slice of the map (a 4 km city's map takes GBs; its copy would double them).
    n_upright = upright.n
    out = np.empty((n_upright + flat.n, 3), np.float32)
    upright.move_to(out[:n_upright])
    flat.move_to(out[n_upright:])
    return out, out[:n_upright]


def _take(result, upright: _Rows, flat: _Rows, progress, k: int, n: int) -> None:
    upright.append(result[0])
    flat.append(result[1])
    if progress is not None:
        progress(k, n)


class _Rows:
    """(n, 3) float32 rows appended block by block into chunks of CHUNK_ROWS (each its own
    allocation, returned to the system when freed)."""

    CHUNK_ROWS = 1 << 25  # 400 MB

    def __init__(self):
        self.chunks: list[np.ndarray] = []
        self.fill = 0
        self.n = 0

    def append(self, rows: np.ndarray) -> None:
        at = 0
        while at < len(rows):
            if not self.chunks or self.fill == len(self.chunks[-1]):
                self.chunks.append(np.empty((self.CHUNK_ROWS, 3), np.float32))
                self.fill = 0
            k = min(len(rows) - at, len(self.chunks[-1]) - self.fill)
            self.chunks[-1][self.fill : self.fill + k] = rows[at : at + k]
            self.fill += k
            at += k
        self.n += len(rows)

    def move_to(self, out: np.ndarray) -> None:
        """Copy every row into ``out`` (n, 3), dropping each chunk once copied."""
        at = 0
        while self.chunks:
            chunk = self.chunks.pop(0)
            k = min(len(chunk), self.n - at)
            out[at : at + k] = chunk[:k]
            at += k


def _block(town, voxel, road_normal_z, x0, y0, x1, y1) -> tuple[np.ndarray, np.ndarray]:
    """The voxel points of one block (float32 (n, 3)): those mostly on upright surfaces, and
    those mostly on flat ones. A voxel belongs to the block its index falls in, so that blocks
    never share one."""
    from .constants import TILE

    plan, raster, cover = town.plan, town.raster, town.cover
    ground = plan.ground
    road_i, road_j = plan.road_dir.ii, plan.road_dir.jj
    vx0, vx1 = math.ceil(x0 / voxel - 1e-9), math.ceil(x1 / voxel - 1e-9)
    vy0, vy1 = math.ceil(y0 / voxel - 1e-9), math.ceil(y1 / voxel - 1e-9)
    bounds = np.array([vx0 * voxel, vx1 * voxel, vy0 * voxel, vy1 * voxel])
    voxels = _Voxels(voxel)

    # The ground: which of the block's cells are in sight, then one point per voxel column.
    i0, j0, _ = raster.ij(bounds[0], bounds[2])
    i1, j1, _ = raster.ij(bounds[1] - 1e-6, bounds[3] - 1e-6)
    i0, j0, i1, j1 = int(i0), int(j0), int(i1) + 1, int(j1) + 1
    xs = raster.x0 + (np.arange(i0, i1) + 0.5) * CELL
    ys = raster.y0 + (np.arange(j0, j1) + 0.5) * CELL
    open_ground = np.isin(town.districts.style_at(xs[:, None], ys[None, :]), (HIGHWAY, PARK))
    near = plan.dist_road[i0:i1, j0:j1] <= np.where(open_ground, OPEN_GROUND_REACH, GROUND_REACH)
    seen = np.zeros(near.shape, bool)
    if near.any():
        ci, cj = np.nonzero(near)
        ci, cj = ci + i0, cj + j0
        height = np.where(plan.road[ci, cj], 0.0, CURB)
        seen[near] = cells_in_sight(
            ci,
            cj,
            height,
            plan.road,
            road_i,
            road_j,
            cover,
            COVER_STEP,
            SURVEY_HEIGHT,
            raster.x0,
            raster.y0,
            CELL,
            OPEN_GROUND_REACH,
        ) & (cover[ci, cj] == 0)
    columns = ground_columns(
        vx0,
        vx1,
        vy0,
        vy1,
        voxel,
        seen,
        i0,
        j0,
        plan.road,
        ground.z,
        ground.x0,
        ground.y0,
        ground.spacing,
        raster.x0,
        raster.y0,
        CELL,
        CURB,
    )
    voxels.add(columns, np.ones(len(columns), bool))
    del columns

    # Every other surface, from the triangles whose centroid is in the block or one tile around it.
    index = town.lidar._index
    tiles = (math.floor(x0 / TILE) - 1, math.ceil(x1 / TILE) + 1, math.floor(y0 / TILE) - 1, math.ceil(y1 / TILE) + 1)
    h = 0.9 * voxel
    for part, idx in zip(index.parts, index.triangles_in(*tiles)):
        if part.name in _GROUND_PARTS or not len(idx):
            continue
        corners = part.vertices[part.triangles[idx]][:, :, :2]  # only the triangles reaching into the block
        lo, hi = corners.min(axis=1), corners.max(axis=1)
        idx = idx[(hi[:, 0] >= bounds[0]) & (lo[:, 0] < bounds[1]) & (hi[:, 1] >= bounds[2]) & (lo[:, 1] < bounds[3])]
        del corners, lo, hi
        for chunk, cap in _chunks(part, idx, h):
            tri = part.vertices[part.triangles[chunk]].astype(np.float64)
            normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
            nz = np.abs(normal[:, 2])
            flat = (nz > road_normal_z) | (part.name in _FLAT_PARTS)
            # the horizontal way a wall faces (boxes face outwards); none for foliage's random triangles
            facing = normal[:, :2] / np.maximum(np.linalg.norm(normal[:, :2], axis=1, keepdims=True), 1e-12)
            facing[(nz > 0.7) | (part.name in _FOLIAGE)] = 0.0
            pts, is_flat = _surface_samples(
                tri,
                flat,
                nz > 0.7,
                facing,
                h,
                bounds,
                ground.z,
                ground.x0,
                ground.y0,
                ground.spacing,
                raster.x0,
                raster.y0,
                CELL,
                plan.dist_road,
                plan.road,
                road_i,
                road_j,
                cover,
                COVER_STEP,
                OBJECT_REACH,
                SURVEY_TOP,
                SURVEY_HEIGHT,
                cap,
            )
            voxels.add(pts, is_flat)
    return voxels.result()


class _Voxels:
    """Voxel centroids of samples and the share of them on flat surfaces: an open-addressing
    table in numba (as :class:`~lidarloc.core.maps.voxel_grid.VoxelAccumulator`, plus a flat count),
    grown with the voxels, a million samples at a time."""

    def __init__(self, voxel: float, capacity: int = 1 << 22):
        self.inv_voxel = 1.0 / voxel
        self.keys = np.full(capacity, -1, np.int64)
        self.acc = np.zeros((capacity, 5), np.float64)  # x, y, z sums, count, flat count
        self.size = 0

    def add(self, pts: np.ndarray, flat: np.ndarray) -> None:
        for k in range(0, len(pts), 1 << 20):
            p, f = (
                np.ascontiguousarray(pts[k : k + (1 << 20)], np.float64),
                np.ascontiguousarray(flat[k : k + (1 << 20)]),
            )
            while (self.size + len(p)) * 2 > len(self.keys):
                used = self.keys != -1
                keys, acc = self.keys[used], self.acc[used]
                self.keys = np.full(2 * len(self.keys), -1, np.int64)
                self.acc = np.zeros((len(self.keys), 5), np.float64)
                _reinsert(self.keys, self.acc, keys, acc)
            self.size += _accumulate(self.keys, self.acc, p, f, self.inv_voxel)

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        """The centroids of the voxels mostly on upright surfaces, and of those mostly on flat ones."""
        acc = self.acc[self.keys != -1]
        self.keys = self.acc = None
        flat = acc[:, 4] > 0.5 * acc[:, 3]
        centroid = (acc[:, :3] / acc[:, 3:4]).astype(np.float32)
        return centroid[~flat], centroid[flat]


@nb.njit(cache=True, nogil=True)
def _accumulate(table_keys, table_acc, pts, flat, inv_voxel):
    mask = table_keys.shape[0] - 1
    added = 0
    for k in range(pts.shape[0]):
        key = voxel_key(pts[k, 0], pts[k, 1], pts[k, 2], inv_voxel)
        h = hash_slot(key, mask)
        while True:
            if table_keys[h] == key:
                break
            if table_keys[h] == -1:
                table_keys[h] = key
                added += 1
                break
            h = (h + 1) & mask
        table_acc[h, 0] += pts[k, 0]
        table_acc[h, 1] += pts[k, 1]
        table_acc[h, 2] += pts[k, 2]
        table_acc[h, 3] += 1.0
        table_acc[h, 4] += 1.0 if flat[k] else 0.0
    return added


@nb.njit(cache=True, nogil=True)
def _reinsert(table_keys, table_acc, keys, acc):
    mask = table_keys.shape[0] - 1
    for k in range(keys.shape[0]):
        h = hash_slot(keys[k], mask)
        while table_keys[h] != -1:
            h = (h + 1) & mask
        table_keys[h] = keys[k]
        table_acc[h] = acc[k]


def _chunks(part, idx: np.ndarray, h: float):
    """``idx`` in runs of at most _CHUNK_SAMPLES grid points, each with its count."""
    tri = part.vertices[part.triangles[idx]]
    n1 = np.maximum(np.ceil(np.linalg.norm(tri[:, 1] - tri[:, 0], axis=1) / h), 1) + 1
    n2 = np.maximum(np.ceil(np.linalg.norm(tri[:, 2] - tri[:, 0], axis=1) / h), 1) + 1
    cum = np.concatenate([[0], np.cumsum(n1 * n2)])
    start = 0
    while start < len(idx):
        end = max(int(np.searchsorted(cum, cum[start] + _CHUNK_SAMPLES, side="right")) - 1, start + 1)
        yield idx[start:end], int(cum[end] - cum[start])
        start = end


@nb.njit(cache=True, nogil=True)
def _surface_samples(
    tri,
    flat,
    up,
    facing,
    h,
    bounds,
    z,
    hx0,
    hy0,
    spacing,
    rx0,
    ry0,
    cell,
    dist_road,
    road,
    road_i,
    road_j,
    cover,
    step,
    reach,
    top,
    scanner,
    cap,
):
    """Points on a grid of spacing ≤ h along each triangle's first two edges that the survey
    keeps (in the block, within reach, below the top, in sight; no tops above the scanner),
    and whether each lies on a flat surface."""
    out = np.empty((cap, 3))
    out_flat = np.empty(cap, np.bool_)
    m = 0
    nx, ny = dist_road.shape
    for t in range(tri.shape[0]):
        ax, ay, az = tri[t, 0, 0], tri[t, 0, 1], tri[t, 0, 2]
        e1x, e1y, e1z = tri[t, 1, 0] - ax, tri[t, 1, 1] - ay, tri[t, 1, 2] - az
        e2x, e2y, e2z = tri[t, 2, 0] - ax, tri[t, 2, 1] - ay, tri[t, 2, 2] - az
        n1 = max(int(math.ceil(math.sqrt(e1x * e1x + e1y * e1y + e1z * e1z) / h)), 1)
        n2 = max(int(math.ceil(math.sqrt(e2x * e2x + e2y * e2y + e2z * e2z) / h)), 1)
        for p in range(n1 + 1):
            u = p / n1
            for q in range(n2 + 1):
                w = q / n2
                if u + w > 1.0 + 1e-9:
                    break
                x, y = ax + u * e1x + w * e2x, ay + u * e1y + w * e2y
                if x < bounds[0] or x >= bounds[1] or y < bounds[2] or y >= bounds[3]:
                    continue
                zz = az + u * e1z + w * e2z
                above = zz - height(x, y, z, hx0, hy0, spacing)
                # below the ground surface (a wall's foot on a slope): no scanner sees it
                if above > top or above < -BURIED or (up[t] and above > scanner):
                    continue
                i = int(math.floor((x - rx0) / cell))
                j = int(math.floor((y - ry0) / cell))
                if i < 0 or i >= nx or j < 0 or j >= ny or dist_road[i, j] > reach:
                    continue
                if not sight(
                    x,
                    y,
                    max(above, 0.0),
                    facing[t, 0],
                    facing[t, 1],
                    road,
                    road_i,
                    road_j,
                    cover,
                    step,
                    scanner,
                    rx0,
                    ry0,
                    cell,
                    reach,
                ):
                    continue
                out[m, 0], out[m, 1], out[m, 2] = x, y, zz
                out_flat[m] = flat[t]
                m += 1
    return out[:m], out_flat[:m]
