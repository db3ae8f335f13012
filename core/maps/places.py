"""The place index: every place on the map a vehicle could stand, described as a 2D LiDAR would
see the map from there, so that a scan can be looked up instead of searched for.

A whole-map M3RSM search costs about 3.7 CPU-seconds per km² (its branch and bound must expand
every block whose bound beats the optimum, and a city is full of look-alike blocks). The index
turns the first step of a global localization into a look-up whose cost does not grow with the
map's area; the exact search then verifies a handful of places in small windows
(:mod:`lidarloc.core.matching.candidates`).

**Places.** The L0 cells of the BEV pyramid's lattice, every ``stride`` cells, that are open
ground by the map's own word: the map has points there, none in the height band of
:func:`obstacles_and_ground`, and no cell within ``clearance`` stands in the way (a point
``band_low`` to ``band_high`` above the lowest point within ``ground_cells`` cells). Building interiors and back
yards hold no points in a survey and are never places.

**Descriptor: the first hit per sector.** From the place, ``sectors`` rays in world directions
θ_s = (s + ½)·2π/S march over the cells in the way in half-cell steps; a ray's value is the
distance to the first such cell, ``max_range`` where it meets none. A scan is described the
same way from its own cells (levelled, judged by the same rule), in its sensor frame, so a scan
at yaw ψ matches its place's descriptor circularly shifted by ψ·S/2π sectors. The first hit, not
the occupancy of polar bins (Scan Context, ring keys), because a scan sees only the first wall
along a ray while the map holds every wall surveyed from every street: the façades of the next
street behind a block are in the map's polar bins but never in the scan's. Heights, not the
road-removed map: a real map's road removal leaves scattered road points on the lanes.

**Look-up: two passes over every place.** A scan's descriptor is compared with every place's
under every shift (the yaw): first on coarse sectors (the nearest hit of each group of
``coarse_group`` sectors, 24 of 15°: 576 byte comparisons a place), then the best places again
on all sectors, each sector's difference clipped at a few metres so that a parked van or a
passing truck in front of the scan costs a sector, not the place. It reads every place, so its
cost does grow with the map's area, but at ~10⁻³ of the exact search's: a k-d tree over
rotation-invariant keys (sorted ranges, their Fourier magnitudes, range histograms) would not,
and missed the true place among its 200 nearest keys on 12–38 % of the town's scans, where the
two passes missed none (docs/global-localization.md).

The index is built once per map, pyramid resolution and settings and cached beside the pyramid
(``places-*.npz``); on the 16 km² city it holds ~10⁵–10⁶ places in tens of MB.
"""

from __future__ import annotations

import json
import math
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numba as nb
import numpy as np

from ..cache import atomic_write_file, cache_rebuilt
from ..errors import LidarlocError
from .bev import pyramid_cache_name

_FORMAT = 3


@dataclass(frozen=True)
class PlaceSettings:
    """How places are laid and described (metres and counts)."""

    stride: int = 2  # L0 cells between places (2 m at d_m = 1 m)
    clearance: float = 1.5  # m, no cell in the way this close to a place
    sectors: int = 72  # rays (5° each)
    max_range: float = 60.0  # m, a ray's reach (a first hit farther is "none")
    coarse_group: int = 3  # sectors per coarse sector (the first pass compares 24 of 15°)
    range_unit: float = 0.5  # m, ranges are held as whole multiples of this (one byte each)
    min_hits: int = 8  # a place whose rays meet fewer cells than this describes nothing
    # A cell stands in the way where one of its points lies this high above the local ground
    # (the lowest point within ground_cells cells): the band a scanner at head height sees at
    # every range. Below it: kerbs and low verges; above it: tree crowns over the road (on the
    # KITTI drive they hang over every lane, and with every point above 0.5 m in the way no place
    # was left on the road), which a scan's beams (+2° at the most) cannot see nearby.
    band_low: float = 0.7  # m
    band_high: float = 2.2  # m
    ground_cells: int = 3

    def __post_init__(self):
        if self.stride < 1 or self.sectors < 4 or self.sectors % self.coarse_group:
            raise LidarlocError("place index: stride ≥ 1, sectors ≥ 4 and a multiple of coarse_group")
        if not (0 < self.max_range / self.range_unit <= 255):
            raise LidarlocError("place index: max_range / range_unit must lie in (0, 255]")

    def key(self) -> str:
        return (
            f"s{self.stride}-c{self.clearance:g}-n{self.sectors}-g{self.coarse_group}"
            f"-r{self.max_range:g}-u{self.range_unit:g}-h{self.min_hits}-b{self.band_low:g}-{self.band_high:g}-l{self.ground_cells}"
        )


# ------------------------------------------------------------------------------------- kernels
@nb.njit(cache=True, nogil=True)
def _ray_profile(occ, ox, oy, cos_s, sin_s, max_steps, step_cells, out):
    """First-hit distance (in cells) of each ray from (ox, oy) (cell units, continuous) over the
    boolean grid ``occ`` [ix, iy]; ``max_steps * step_cells`` where a ray meets nothing or
    leaves the grid."""
    nx, ny = occ.shape
    hits = 0
    for s in range(cos_s.shape[0]):
        d = max_steps * step_cells
        for t in range(1, max_steps + 1):
            r = t * step_cells
            ix = int(math.floor(ox + r * cos_s[s]))
            iy = int(math.floor(oy + r * sin_s[s]))
            if ix < 0 or iy < 0 or ix >= nx or iy >= ny:
                break
            if occ[ix, iy]:
                d = r
                hits += 1
                break
        out[s] = d
    return hits


@nb.njit(cache=True, nogil=True)
def _profiles(occ, px, py, cos_s, sin_s, max_steps, step_cells, out, hits):
    tmp = np.empty(cos_s.shape[0])
    for i in range(px.shape[0]):
        hits[i] = _ray_profile(occ, px[i] + 0.5, py[i] + 0.5, cos_s, sin_s, max_steps, step_cells, tmp)
        for s in range(cos_s.shape[0]):
            out[i, s] = tmp[s]


def _rays(sectors: int) -> tuple[np.ndarray, np.ndarray]:
    theta = (np.arange(sectors) + 0.5) * (2.0 * math.pi / sectors)
    return np.cos(theta), np.sin(theta)


def _steps(max_range: float, resolution: float) -> tuple[int, float]:
    step_cells = 0.5  # half a cell: a ray does not slip between two diagonal cells
    return int(math.ceil(max_range / resolution / step_cells)), step_cells


def coarse_of(profiles: np.ndarray, group: int) -> np.ndarray:
    """The nearest hit of each group of ``group`` neighbouring sectors."""
    p = np.asarray(profiles)
    return np.ascontiguousarray(p.reshape(p.shape[0], p.shape[1] // group, group).min(axis=2))


def quantize(ranges_m: np.ndarray, settings: PlaceSettings) -> np.ndarray:
    """Ranges in metres as whole ``range_unit`` steps, one byte each."""
    q = np.rint(np.asarray(ranges_m, np.float64) / settings.range_unit)
    return np.clip(q, 0, 255).astype(np.uint8)


@nb.njit(cache=True, nogil=True)
def _mark_lowest(xyz, ox, oy, resolution, zmin):
    nx, ny = zmin.shape
    for i in range(xyz.shape[0]):
        ix = int(math.floor((xyz[i, 0] - ox) / resolution))
        iy = int(math.floor((xyz[i, 1] - oy) / resolution))
        if 0 <= ix < nx and 0 <= iy < ny:
            z = np.float32(xyz[i, 2])
            if z < zmin[ix, iy]:
                zmin[ix, iy] = z


@nb.njit(cache=True, nogil=True)
def _mark_band(xyz, ox, oy, resolution, ground_z, low, high, out):
    nx, ny = out.shape
    for i in range(xyz.shape[0]):
        ix = int(math.floor((xyz[i, 0] - ox) / resolution))
        iy = int(math.floor((xyz[i, 1] - oy) / resolution))
        if 0 <= ix < nx and 0 <= iy < ny:
            h = xyz[i, 2] - ground_z[ix, iy]
            if low <= h <= high:
                out[ix, iy] = True


def _chunks(points, chunk: int):
    for start in range(0, len(points), chunk):
        yield np.ascontiguousarray(points[start : start + chunk, :3], np.float64)


def obstacles_and_ground(
    points, origin, shape, resolution: float, settings: PlaceSettings, chunk: int = 1 << 24
) -> tuple[np.ndarray, np.ndarray]:
    """Which cells of the lattice (``origin``, ``shape``) stand in the way (a point of ``points`` in
    the height band above the local ground: a wall, a trunk, a pole, a truck) and which are open
    ground (points, none in the band). Judged on heights, not on the road-removed map: a real
    map's road removal leaves the road's own points scattered over the lanes (on the KITTI drive
    16–25 of the 25 cells around the vehicle held some). Two passes over ``points`` (a
    memory-mapped map is read ``chunk`` points at a time): the lowest point per cell, then the band."""
    from scipy.ndimage import minimum_filter

    ox, oy, d = float(origin[0]), float(origin[1]), float(resolution)
    zmin = np.full(shape, np.inf, np.float32)
    for part in _chunks(points, chunk):
        _mark_lowest(part, ox, oy, d, zmin)
    ground_z = minimum_filter(zmin, size=2 * settings.ground_cells + 1, mode="constant", cval=np.inf)
    obstacle = np.zeros(shape, np.bool_)
    for part in _chunks(points, chunk):
        _mark_band(part, ox, oy, d, ground_z, float(settings.band_low), float(settings.band_high), obstacle)
    return obstacle, np.isfinite(zmin) & ~obstacle


def describe_scan(points: np.ndarray, resolution: float, settings: PlaceSettings) -> tuple[np.ndarray, int]:
    """The descriptor (ranges in ``range_unit`` steps, sector s at sensor-frame angle
    (s + ½)·2π/S) of a levelled scan (x, y, z in the sensor frame, pitch and roll removed), and how
    many of its rays hit: the scan's cells judged by :func:`obstacles_and_ground` as the map's are."""
    pts = np.asarray(points)[:, :3]
    n = int(math.ceil(settings.max_range / resolution)) + 1
    # the sensor sits at grid coordinate (n, n): cell n's lower corner, as floor(xy / d) + n says
    occ, _ = obstacles_and_ground(pts, (-n * resolution, -n * resolution), (2 * n + 1, 2 * n + 1), resolution, settings)
    cos_s, sin_s = _rays(settings.sectors)
    steps, step_cells = _steps(settings.max_range, resolution)
    out = np.empty(settings.sectors)
    hits = _ray_profile(occ, float(n), float(n), cos_s, sin_s, steps, step_cells, out)
    return quantize(out * resolution, settings), int(hits)


# ------------------------------------------------------------------------------------- the index
@dataclass
class PlaceIndex:
    """Places (world x, y of their cells' centres) and their descriptors."""

    xy: np.ndarray  # (n, 2) float32, world m
    profiles: np.ndarray  # (n, S) uint8, first-hit range per world-fixed sector, range_unit steps
    coarse: np.ndarray  # (n, S / coarse_group) uint8, the nearest hit of each group of sectors
    resolution: float  # m, the L0 cell the places lie on
    settings: PlaceSettings
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.xy)

    @property
    def nbytes(self) -> int:
        return int(self.xy.nbytes + self.profiles.nbytes + self.coarse.nbytes)

    def save(self, path: Path) -> None:
        info = {"format": _FORMAT, "resolution": self.resolution, "settings": self.settings.__dict__, "meta": self.meta}
        blob = np.frombuffer(json.dumps(info).encode(), np.uint8)

        def write(tmp: Path) -> None:
            with open(tmp, "wb") as f:
                np.savez(f, xy=self.xy, profiles=self.profiles, coarse=self.coarse, info=blob)

        atomic_write_file(Path(path), write)

    @classmethod
    def load(cls, path: Path) -> PlaceIndex:
        try:
            with np.load(path) as data:
                info = json.loads(bytes(data["info"]).decode())
                if info.get("format") != _FORMAT:
                    raise ValueError(f"format {info.get('format')}, expected {_FORMAT}")
                index = cls(
                    xy=np.ascontiguousarray(data["xy"]),
                    profiles=np.ascontiguousarray(data["profiles"]),
                    coarse=np.ascontiguousarray(data["coarse"]),
                    resolution=float(info["resolution"]),
                    settings=PlaceSettings(**info["settings"]),
                    meta=info.get("meta", {}),
                )
        except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile) as exc:
            raise LidarlocError(f"{path}: unreadable place index ({exc})") from None
        n, s = len(index.xy), index.settings.sectors
        if index.profiles.shape != (n, s) or index.coarse.shape != (n, s // index.settings.coarse_group):
            raise LidarlocError(f"{path}: unreadable place index (arrays of mismatched shapes)")
        return index


def _dilate(occ: np.ndarray, radius_cells: float) -> np.ndarray:
    """Cells within ``radius_cells`` of an occupied cell (a disc; nothing beyond the block's edge)."""
    from scipy.ndimage import binary_dilation

    r = int(math.floor(radius_cells))
    d = np.arange(-r, r + 1)
    disc = d[:, None] ** 2 + d[None, :] ** 2 <= radius_cells * radius_cells
    return binary_dilation(occ, structure=disc)


def describe_block(
    occ: np.ndarray, ground: np.ndarray, margin: int, resolution: float, settings: PlaceSettings, phase=(0, 0)
) -> tuple[np.ndarray, np.ndarray, int]:
    """Places and descriptors of one block of the grid: ``occ`` (the cells in the way) and
    ``ground`` (open ground) over the block plus ``margin`` cells on every side;
    places only in the block's core, on the lattice ``phase + stride·i`` of the core's cells.
    Returns the places' core cells (n, 2) int64, their descriptors (n, S) in metres and how many
    places had too few hits."""
    near = _dilate(occ, settings.clearance / resolution)
    free = ground & ~near
    core = free[margin : free.shape[0] - margin, margin : free.shape[1] - margin]
    s = settings.stride
    mask = np.zeros_like(core)
    mask[phase[0] :: s, phase[1] :: s] = True
    ci, cj = np.nonzero(core & mask)
    if len(ci) == 0:
        return np.zeros((0, 2), np.int64), np.zeros((0, settings.sectors), np.uint8), 0
    cos_s, sin_s = _rays(settings.sectors)
    steps, step_cells = _steps(settings.max_range, resolution)
    out = np.empty((len(ci), settings.sectors))
    hits = np.empty(len(ci), np.int64)
    _profiles(
        np.ascontiguousarray(occ),
        (ci + margin).astype(np.float64),
        (cj + margin).astype(np.float64),
        cos_s,
        sin_s,
        steps,
        step_cells,
        out,
        hits,
    )
    keep = hits >= settings.min_hits
    return (
        np.column_stack([ci[keep], cj[keep]]).astype(np.int64),
        quantize(out[keep] * resolution, settings),
        int((~keep).sum()),
    )


# ------------------------------------------------------------------------------------- building
def _padded(grid: np.ndarray, cx0: int, cy0: int, cx1: int, cy1: int) -> np.ndarray:
    """The part of ``grid`` over [cx0, cx1) × [cy0, cy1), zeros beyond its edges."""
    out = np.zeros((cx1 - cx0, cy1 - cy0), grid.dtype)
    a0, b0 = max(cx0, 0), max(cy0, 0)
    a1, b1 = min(cx1, grid.shape[0]), min(cy1, grid.shape[1])
    if a1 > a0 and b1 > b0:
        out[a0 - cx0 : a1 - cx0, b0 - cy0 : b1 - cy0] = grid[a0:a1, b0:b1]
    return out


def build_place_index(
    full_points: np.ndarray,
    origin,
    shape: tuple[int, int],
    resolution: float,
    settings: PlaceSettings | None = None,
    block: int = 512,
    progress=None,
) -> PlaceIndex:
    """The index of a map (its ``full_points``, every point, memory-mapped or not) on the lattice
    (``origin``, ``shape``, ``resolution``) of its BEV pyramid: the cells in the way and the open
    ground judged once (:func:`obstacles_and_ground`), then places described block by block."""
    settings = settings or PlaceSettings()
    t0 = time.perf_counter()
    obstacle, ground = obstacles_and_ground(full_points, origin, shape, resolution, settings)
    margin = int(math.ceil(settings.max_range / resolution)) + int(math.ceil(settings.clearance / resolution)) + 2
    xy_parts, prof_parts, empty = [], [], 0
    blocks = [(bx, by) for bx in range(0, shape[0], block) for by in range(0, shape[1], block)]
    for n_done, (bx, by) in enumerate(blocks):
        ex, ey = min(bx + block, shape[0]), min(by + block, shape[1])
        occ = _padded(obstacle, bx - margin, by - margin, ex + margin, ey + margin)
        gnd = _padded(ground, bx - margin, by - margin, ex + margin, ey + margin)
        # the lattice of places is global (multiples of the stride), whatever the block
        phase = ((-bx) % settings.stride, (-by) % settings.stride)
        cells, prof, few = describe_block(occ, gnd, margin, resolution, settings, phase)
        empty += few
        if len(cells):
            xy_parts.append((cells + np.array([bx, by])).astype(np.float64))
            prof_parts.append(prof)
        if progress is not None:
            progress((n_done + 1) / len(blocks))
    cells = np.concatenate(xy_parts) if xy_parts else np.zeros((0, 2))
    profiles = np.concatenate(prof_parts) if prof_parts else np.zeros((0, settings.sectors), np.uint8)
    xy = (np.asarray(origin, np.float64) + (cells + 0.5) * resolution).astype(np.float32)
    return PlaceIndex(
        xy=xy,
        profiles=profiles,
        coarse=coarse_of(profiles, settings.coarse_group),
        resolution=float(resolution),
        settings=settings,
        meta={"build_seconds": time.perf_counter() - t0, "places": int(len(xy)), "too_few_hits": empty},
    )


def index_of_pyramid(pyramid, full_points: np.ndarray, settings: PlaceSettings | None = None) -> PlaceIndex:
    """The index of a map whose BEV is one :class:`~lidarloc.core.maps.bev.BEVPyramid` (its lattice)."""
    return build_place_index(full_points, pyramid.origin, pyramid.shape, pyramid.resolution, settings)


def index_of_tiles(bev, full_points: np.ndarray, settings: PlaceSettings | None = None, progress=None) -> PlaceIndex:
    """The index of a city held as a :class:`~lidarloc.core.maps.tiled_bev.TiledBEV` (its lattice)."""
    return build_place_index(full_points, bev.origin, bev.shape, bev.resolution, settings, progress=progress)


#: L0 cells from which ``s2m.global_search = "auto"`` looks places up rather than searching the whole
#: map (0.25 km² at d_m = 1 m). Below it the exact search is cheap and certain: 0.39 s on the
#: KITTI drive's 0.04 km², where the look-up found the true place among its first eight for 18 of
#: 30 scans and wrong places along the same street passed GICP (docs/global-localization.md).
AUTO_MIN_CELLS = 250_000


def uses_places(s2m_cfg, shape) -> bool:
    """Whether whole-map matches on a BEV lattice of ``shape`` cells go through the place index."""
    mode = s2m_cfg.global_search
    return mode == "candidates" or (mode == "auto" and int(shape[0]) * int(shape[1]) >= AUTO_MIN_CELLS)


def place_index_name(pyramid_name: str, settings: PlaceSettings) -> str:
    """The index's file name beside the map's other tables, keyed by the pyramid it is read from."""
    return f"places-{pyramid_name}-{settings.key()}-v{_FORMAT}.npz"


def places_for_pyramid(
    pyramid, full_points, map_dir: Path | None, s2m_cfg, settings: PlaceSettings | None = None
) -> PlaceIndex:
    """The place index of a map's pyramid, cached in the map's directory ``map_dir`` (None: built,
    not cached)."""
    settings = settings or PlaceSettings()
    path = None if map_dir is None else Path(map_dir) / place_index_name(pyramid_cache_name(s2m_cfg), settings)
    return load_or_build_place_index(lambda: index_of_pyramid(pyramid, full_points, settings), path)[0]


def load_or_build_place_index(build, path: Path | None) -> tuple[PlaceIndex, bool]:
    """The index cached at ``path`` or ``build()`` and cached there (``path`` None: not cached).
    Returns (index, whether it came from the cache)."""
    if path is not None and Path(path).is_file():
        try:
            return PlaceIndex.load(path), True
        except LidarlocError as exc:
            cache_rebuilt(Path(path), str(exc).split(": ", 1)[-1])
    index = build()
    if path is not None:
        try:
            index.save(Path(path))
        except OSError as exc:
            raise LidarlocError(f"{path}: cannot write the place index cache ({exc.strerror})") from None
    return index, False
