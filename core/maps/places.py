"""The place index: every place on the map a vehicle could stand, described as a 2D LiDAR would
see the road-removed map from there, so that a scan can be looked up instead of searched for.

A whole-map M3RSM search costs about 3.7 CPU-seconds per km² (its branch and bound must expand
every block whose bound beats the optimum, and a city is full of look-alike blocks). The index
turns the first step of a global localization into a look-up whose cost does not grow with the
map's area; the exact search then verifies a handful of places in small windows
(:mod:`lidarloc.core.matching.candidates`).

**Places.** The L0 cells of the BEV pyramid, every ``stride`` cells, that are drivable by the
map's own word: the full map has points there (the ground) while the road-removed map has none
within ``clearance`` (nothing stands there). Walls' backs, building interiors and back yards are
empty in both maps and so never places.

**Descriptor: the first hit per sector.** From the place, ``sectors`` rays in world directions
θ_s = (s + ½)·2π/S march over the road-removed L0 grid in half-cell steps; a ray's value is the
distance to the first occupied cell, ``max_range`` where it meets none. A scan is described the
same way from its own BEV (road-removed, levelled), in its sensor frame, so a scan at yaw ψ
matches its place's descriptor circularly shifted by ψ·S/2π sectors. The first hit, not the
occupancy of polar bins (Scan Context, ring keys), because a scan sees only the first wall
along a ray while the map holds every wall surveyed from every street: the façades of the next
street behind a block are in the map's polar bins but never in the scan's. Measured alternatives
and why this one won: docs/global-localization.md.

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

_FORMAT = 1


@dataclass(frozen=True)
class PlaceSettings:
    """How places are laid and described (metres and counts)."""

    stride: int = 2  # L0 cells between places (2 m at d_m = 1 m)
    clearance: float = 1.5  # m, no road-removed map cell this close to a place
    sectors: int = 72  # rays (5° each)
    max_range: float = 60.0  # m, a ray's reach (a first hit farther is "none")
    coarse_group: int = 3  # sectors per coarse sector (the first pass compares 24 of 15°)
    range_unit: float = 0.5  # m, ranges are held as whole multiples of this (one byte each)
    min_hits: int = 8  # a place whose rays meet fewer cells than this describes nothing

    def __post_init__(self):
        if self.stride < 1 or self.sectors < 4 or self.sectors % self.coarse_group:
            raise LidarlocError("place index: stride ≥ 1, sectors ≥ 4 and a multiple of coarse_group")
        if not (0 < self.max_range / self.range_unit <= 255):
            raise LidarlocError("place index: max_range / range_unit must lie in (0, 255]")

    def key(self) -> str:
        return (
            f"s{self.stride}-c{self.clearance:g}-n{self.sectors}-g{self.coarse_group}"
            f"-r{self.max_range:g}-u{self.range_unit:g}-h{self.min_hits}"
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


def describe_scan(bev_xy: np.ndarray, resolution: float, settings: PlaceSettings) -> tuple[np.ndarray, int]:
    """The descriptor (ranges in ``range_unit`` steps, sector s at sensor-frame angle
    (s + ½)·2π/S) of a levelled road-removed scan's x-y (sensor frame), and how many of its rays
    hit."""
    xy = np.asarray(bev_xy, np.float64)[:, :2]
    n = int(math.ceil(settings.max_range / resolution)) + 1
    # the sensor at the centre of cell (n, n): the same half-cell offset as a place
    cells = np.floor(xy / resolution).astype(np.int64) + n
    inside = (cells[:, 0] >= 0) & (cells[:, 1] >= 0) & (cells[:, 0] < 2 * n + 1) & (cells[:, 1] < 2 * n + 1)
    occ = np.zeros((2 * n + 1, 2 * n + 1), np.bool_)
    occ[cells[inside, 0], cells[inside, 1]] = True
    cos_s, sin_s = _rays(settings.sectors)
    steps, step_cells = _steps(settings.max_range, resolution)
    out = np.empty(settings.sectors)
    # the sensor sits at grid coordinate (n, n): cell n's lower corner, as floor(xy / d) + n says
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
    """Cells within ``radius_cells`` of an occupied cell (a disc), by shifted ors."""
    r = int(math.floor(radius_cells))
    out = occ.copy()
    nx, ny = occ.shape
    for dx in range(-r, r + 1):
        for dy in range(-r, r + 1):
            if (dx or dy) and dx * dx + dy * dy <= radius_cells * radius_cells:
                out[max(dx, 0) : nx + min(dx, 0), max(dy, 0) : ny + min(dy, 0)] |= occ[
                    max(-dx, 0) : nx + min(-dx, 0), max(-dy, 0) : ny + min(-dy, 0)
                ]
    return out


def describe_block(
    occ: np.ndarray, ground: np.ndarray, margin: int, resolution: float, settings: PlaceSettings, phase=(0, 0)
) -> tuple[np.ndarray, np.ndarray, int]:
    """Places and descriptors of one block of the grid: ``occ`` (road-removed occupancy) and
    ``ground`` (the full map's occupancy) over the block plus ``margin`` cells on every side;
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
@nb.njit(cache=True, nogil=True)
def _mark_cells(xyz, ox, oy, resolution, out):
    nx, ny = out.shape
    for i in range(xyz.shape[0]):
        ix = int(math.floor((xyz[i, 0] - ox) / resolution))
        iy = int(math.floor((xyz[i, 1] - oy) / resolution))
        if 0 <= ix < nx and 0 <= iy < ny:
            out[ix, iy] = True


def ground_grid(
    points: np.ndarray, origin, shape: tuple[int, int], resolution: float, chunk: int = 1 << 24
) -> np.ndarray:
    """Cells of the L0 lattice (``origin``, ``shape``) holding at least one of the full map's
    ``points`` (a memory-mapped map is read ``chunk`` points at a time)."""
    out = np.zeros(shape, np.bool_)
    for start in range(0, len(points), chunk):
        part = np.ascontiguousarray(points[start : start + chunk, :2], np.float64)
        _mark_cells(part, float(origin[0]), float(origin[1]), float(resolution), out)
    return out


def _padded(read, cx0: int, cy0: int, cx1: int, cy1: int, shape) -> np.ndarray:
    """``read(a0, b0, a1, b1)`` of the part of [cx0, cx1) × [cy0, cy1) inside the grid, placed in a
    block of zeros the requested size."""
    out = np.zeros((cx1 - cx0, cy1 - cy0), np.bool_)
    a0, b0 = max(cx0, 0), max(cy0, 0)
    a1, b1 = min(cx1, shape[0]), min(cy1, shape[1])
    if a1 > a0 and b1 > b0:
        out[a0 - cx0 : a1 - cx0, b0 - cy0 : b1 - cy0] = read(a0, b0, a1, b1)
    return out


def build_place_index(
    read_occupied,
    ground: np.ndarray,
    origin,
    resolution: float,
    settings: PlaceSettings | None = None,
    block: int = 512,
    progress=None,
) -> PlaceIndex:
    """The index of a map whose road-removed L0 occupancy ``read_occupied(cx0, cy0, cx1, cy1)``
    gives block by block (cells inside the grid only), with the full map's occupancy ``ground``
    on the same lattice. Blocks of ``block`` cells are described one after another with a margin
    of the rays' reach, so a city's grid is never held whole beside its tiles."""
    settings = settings or PlaceSettings()
    t0 = time.perf_counter()
    shape = ground.shape
    margin = int(math.ceil(settings.max_range / resolution)) + int(math.ceil(settings.clearance / resolution)) + 2
    xy_parts, prof_parts, empty = [], [], 0
    blocks = [(bx, by) for bx in range(0, shape[0], block) for by in range(0, shape[1], block)]
    for n_done, (bx, by) in enumerate(blocks):
        ex, ey = min(bx + block, shape[0]), min(by + block, shape[1])
        occ = _padded(read_occupied, bx - margin, by - margin, ex + margin, ey + margin, shape)
        gnd = _padded(
            lambda a0, b0, a1, b1: ground[a0:a1, b0:b1], bx - margin, by - margin, ex + margin, ey + margin, shape
        )
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
    """The index of a map held as one :class:`~lidarloc.core.maps.bev.BEVPyramid`."""
    occ = np.asarray(pyramid.levels[0]) > 0
    ground = ground_grid(full_points, pyramid.origin, pyramid.shape, pyramid.resolution)
    return build_place_index(
        lambda a0, b0, a1, b1: occ[a0:a1, b0:b1], ground, pyramid.origin, pyramid.resolution, settings
    )


def index_of_tiles(bev, full_points: np.ndarray, settings: PlaceSettings | None = None, progress=None) -> PlaceIndex:
    """The index of a city held as a :class:`~lidarloc.core.maps.tiled_bev.TiledBEV`: its L0 read
    block by block from the tiles."""
    ground = ground_grid(full_points, bev.origin, bev.shape, bev.resolution)

    def read(a0, b0, a1, b1):
        return np.asarray(bev.window(a0, b0, a1, b1).levels[0]) > 0

    return build_place_index(read, ground, bev.origin, bev.resolution, settings, progress=progress)


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
