"""The prior map: scans fused with their ground-truth poses (the paper's protocol), streamed scan
by scan into a voxel grid, plus the road-removed copy used for the bird's-eye-view matcher.

The voxel grid is an open-addressing hash table in numba (voxel key → sum of points, count), so
building never holds the raw points of more than one scan; each voxel's point is the centroid of
the returns that fell in it.

A prior map can also come from a point-cloud file (:class:`~lidarloc.core.maps.map_source.MapFileSource`,
passed where a sequence is): its points are voxelized with the same accumulator, in the file's
local frame, and ``PriorMap.origin`` keeps that frame's float64 origin. A source may also deliver
its map itself (``delivers_map``: the generated city's survey, sampled from its surfaces, see
:mod:`lidarloc.core.sim.town.survey`); it is cached like any other.
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..cache import Cached, atomic_write_dir, cache_rebuilt, check_points, default_cache_root
from ..config import MapConfig
from ..errors import DataError, LidarlocError
from ..o3d import open3d
from .voxel_grid import VoxelAccumulator

if TYPE_CHECKING:
    from .point_tiles import PointTiles


def range_filter(points: np.ndarray, cfg: MapConfig) -> np.ndarray:
    r2 = np.einsum("ij,ij->i", points[:, :3], points[:, :3])
    return points[(r2 >= cfg.scan_min_range**2) & (r2 <= cfg.scan_max_range**2)]


def flat_surface_mask(
    points: np.ndarray, cfg: MapConfig, progress: Callable[[float], None] | None = None
) -> np.ndarray:
    """True where a point lies on a flat (road-like) surface: |normal_z| > cfg.road_normal_z.

    The paper removes points "with z-coordinate of its normal greater than 0.75"; normals from PCA
    have no consistent sign, so the absolute value is compared.

    ``progress(fraction)``: the normals are estimated strip by strip along x (at most
    ``FLAT_MASK_STRIPS`` strips of at least ``FLAT_MASK_STRIP_M``), each with every point within
    the normal radius beyond its edges, so each point sees exactly the neighbours it would see in
    the whole map, and the fraction done is reported after each strip.
    """
    pts = np.asarray(points[:, :3], dtype=np.float64)
    if progress is None or len(pts) == 0:
        return _flat_mask(pts, cfg)
    x = pts[:, 0]
    lo, hi = float(x.min()), float(x.max())
    n = int(np.clip(np.ceil((hi - lo) / FLAT_MASK_STRIP_M), 1, FLAT_MASK_STRIPS))
    edges = np.linspace(lo, hi, n + 1)
    edges[-1] = np.inf
    halo = cfg.normal_radius * 1.01
    mask = np.zeros(len(pts), dtype=bool)
    for i in range(n):
        core = (x >= edges[i]) & (x < edges[i + 1])
        near = (x >= edges[i] - halo) & (x < edges[i + 1] + halo)
        idx = np.flatnonzero(near)
        mask[core] = _flat_mask(pts[idx], cfg)[core[idx]]
        progress((i + 1) / n)
    return mask


#: Road removal's strips (see :func:`flat_surface_mask`): at most this many, at least this wide (m).
FLAT_MASK_STRIPS = 20
FLAT_MASK_STRIP_M = 20.0


def _flat_mask(pts: np.ndarray, cfg: MapConfig) -> np.ndarray:
    o3d = open3d()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=cfg.normal_radius, max_nn=cfg.normal_max_nn))
    normals = np.asarray(pcd.normals)
    return np.abs(normals[:, 2]) > cfg.road_normal_z


#: A map of more points than this is held on disk in a run on tiles (``pf.lookup_tile_m`` > 0): its
#: files memory-mapped, read near one place through its point tiles (:mod:`.point_tiles`). 20 M
#: points are 240 MB; the 1 km² city has ~26 M, the 4 × 4 km city 421 M. Smaller maps are read
#: whole, as in a run on one table (their S2M then registers against the whole map, as there).
LARGE_MAP_POINTS = 20_000_000


@dataclass
class PriorMap:
    points: np.ndarray  # (N, 3) float32, world frame (= first LiDAR pose)
    points_bev: np.ndarray | None  # (M, 3) float32, flat surfaces removed (for the bird's-eye
    # view); None while road removal is still to be done (see
    # ``load_or_build_map(road_removal=False)``)
    voxel_size: float
    source: str = ""
    # float64 (3,): the map's frame in the frame of the file it came from (file = points + origin);
    # zeros for a map fused from a drive, whose frame is the drive's own
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    # the same points by x-y tile on disk (a map too big to read whole: a city), for what reads
    # the map near one place; their index also knows the bounds (see :meth:`use_tiles`)
    tiles: PointTiles | None = field(default=None, repr=False, compare=False)
    _bounds: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False, compare=False)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        if self._bounds is None:
            self._bounds = (self.points.min(axis=0), self.points.max(axis=0))
        return self._bounds

    def use_tiles(self, tiles: PointTiles) -> None:
        """Read the map near one place from ``tiles`` (its bounds from their index: a
        memory-mapped map is then never read whole)."""
        self.tiles = tiles
        lo, hi = tiles.bounds
        self._bounds = (lo.astype(self.points.dtype), hi.astype(self.points.dtype))

    def save(self, directory: Path) -> None:
        np.save(directory / MAP_FILE, self.points)
        if self.points_bev is not None:
            np.save(directory / BEV_FILE, self.points_bev)

    @property
    def on_disk(self) -> bool:
        """Whether the points stay on disk (memory-mapped: a large map in a tiled run)."""
        return isinstance(self.points, np.memmap)

    @classmethod
    def load(cls, directory: Path, meta: dict, memory_map: bool = False, large: int | None = None) -> PriorMap:
        """The cached map; ``memory_map`` and more than ``large`` points (default
        LARGE_MAP_POINTS): its files mapped, not read (a city's 5 GB), their shape, type and length
        checked here and their values when tiles are cut from them."""
        bev = directory / BEV_FILE
        large = LARGE_MAP_POINTS if large is None else int(large)
        mapped = memory_map and int(meta.get("points") or 0) > large

        def read(path: Path):
            if not mapped:
                return check_points(np.load(path), path.name)
            return check_points(np.load(path, mmap_mode="r"), path.name, values=False)

        return cls(
            points=read(directory / MAP_FILE),
            points_bev=read(bev) if bev.is_file() else None,
            voxel_size=float(meta["map"]["voxel_size"]),
            source=meta.get("source", ""),
            origin=np.asarray(meta.get("origin", (0.0, 0.0, 0.0)), dtype=np.float64),
        )


#: the map's points in a map's cache directory
MAP_FILE = "map_points.npy"
#: the road-removed map's file in a map's cache directory (written after the map itself when
#: road removal is deferred)
BEV_FILE = "map_points_bev.npy"


def build_prior_map(
    seq, cfg: MapConfig, progress: Callable[[int, int], None] | None = None, road_removal: bool = True
) -> PriorMap:
    """Fuse every scan of ``seq`` with its ground-truth pose into a voxel map, then remove flats
    (unless ``road_removal`` is False: then ``points_bev`` is None, see :func:`remove_road`).
    A :class:`~lidarloc.core.maps.map_source.MapFileSource` is voxelized instead (see
    :func:`build_prior_map_from_file`)."""
    if _is_map_file(seq):
        return build_prior_map_from_file(seq, cfg, progress, road_removal)
    if getattr(seq, "delivers_map", False):  # with its road-removed copy, which it knows exactly
        return seq.prior_map(cfg, progress)
    poses = seq.poses
    if poses is None:
        raise DataError(f"{seq.name}: a prior map needs ground-truth poses, and this sequence has none")
    acc = VoxelAccumulator(cfg.voxel_size)
    n = len(seq)

    # Reading (or simulating) scans overlaps with the fusion: a small look-ahead on two threads
    # keeps both cores busy while holding only a few scans in memory.
    lookahead = 4
    with ThreadPoolExecutor(2, thread_name_prefix="lidarloc-map") as pool:
        pending = [pool.submit(seq.scan, i) for i in range(min(lookahead, n))]
        for i in range(n):
            scan = pending.pop(0).result()
            if i + lookahead < n:
                pending.append(pool.submit(seq.scan, i + lookahead))
            acc.add_scan(scan, poses[i], cfg.scan_min_range, cfg.scan_max_range)
            if progress is not None:
                progress(i + 1, n)
    points = acc.points()
    if len(points) == 0:
        raise DataError(f"{seq.name}: the map is empty (no points within range)")
    prior = PriorMap(points=points, points_bev=None, voxel_size=cfg.voxel_size, source=seq.name)
    return remove_road(prior, cfg) if road_removal else prior


def _is_map_file(source) -> bool:
    from .map_source import MapFileSource

    return isinstance(source, MapFileSource)


#: points voxelized per call when a map comes from a file: bounds the float64 copy the
#: accumulator makes and the table growth it reserves for (a whole 50 M-point map at once
#: would reserve a 100 M-slot table, 4 GB)
FILE_CHUNK_POINTS = 1 << 20


def build_prior_map_from_file(
    source, cfg: MapConfig, progress: Callable[[int, int], None] | None = None, road_removal: bool = True
) -> PriorMap:
    """The voxel map of a map file's points (one centroid per occupied ``cfg.voxel_size`` voxel,
    in the file's local frame), then road removal as for a drive. ``progress(i, n)`` counts
    reading and voxelizing together."""
    # reading is ~3/4 of the work, voxelizing the rest: one progress scale for both
    scale = 1000

    def reading(done: int, total: int) -> None:
        if progress is not None:
            progress(int(0.75 * scale * done / max(total, 1)), scale)

    cloud = source.read(progress=reading)
    acc = VoxelAccumulator(cfg.voxel_size)
    n = len(cloud.points)
    for i in range(0, n, FILE_CHUNK_POINTS):
        acc.add(cloud.points[i : i + FILE_CHUNK_POINTS])
        if progress is not None:
            progress(int(scale * (0.75 + 0.25 * min(i + FILE_CHUNK_POINTS, n) / n)), scale)
    origin, name = cloud.origin, source.name
    del cloud  # the file's points: only the voxel map stays
    prior = PriorMap(points=acc.points(), points_bev=None, voxel_size=cfg.voxel_size, source=name, origin=origin)
    return remove_road(prior, cfg) if road_removal else prior


def remove_road(prior: PriorMap, cfg: MapConfig, progress: Callable[[float], None] | None = None) -> PriorMap:
    """``prior`` with its road-removed copy (the points not on a flat surface) filled in."""
    bev = prior.points[~flat_surface_mask(prior.points, cfg, progress)]
    return PriorMap(
        points=prior.points,
        points_bev=bev.astype(np.float32),
        voxel_size=prior.voxel_size,
        source=prior.source,
        origin=prior.origin,
    )


# ------------------------------------------------------------------------------------- cache
def map_cache_dir(seq, cfg: MapConfig, cache_root: Path | None = None) -> Path:
    import hashlib

    params = json.dumps(asdict(cfg), sort_keys=True)
    key = hashlib.sha1(f"{seq.cache_key()}|{params}".encode()).hexdigest()[:16]
    return Path(cache_root or default_cache_root()) / f"map-{key}"


def load_or_build_map(
    seq,
    cfg: MapConfig,
    cache_root: Path | None = None,
    progress: Callable[[int, int], None] | None = None,
    road_removal: bool = True,
    memory_map: bool = False,
) -> Cached[PriorMap]:
    """The prior map of ``seq`` from the cache, or built and cached (in its own directory under
    ``cache_root``, default :func:`~lidarloc.core.cache.default_cache_root`).

    ``memory_map``: a large cached map's files are mapped, not read (see :meth:`PriorMap.load`);
    a large map built here is written, dropped and mapped in the same way.

    ``road_removal=False``: the map may come without its road-removed copy (``points_bev`` is
    None unless a previous build cached it); :func:`load_or_build_road_removed` adds it later.
    The particle filter needs only the map, so a viewer can start playing before the road
    removal (the normals of every map point: ~10 s for the built-in town) is done."""
    directory = map_cache_dir(seq, cfg, cache_root)
    meta_path = directory / "meta.json"
    if meta_path.is_file():
        try:
            meta = json.loads(meta_path.read_text())
            prior = PriorMap.load(directory, meta, memory_map=memory_map)
        except (OSError, ValueError, KeyError, TypeError) as exc:  # rebuilt below
            cache_rebuilt(directory, f"{type(exc).__name__}: {exc}")
        else:
            if prior.points_bev is None and road_removal:
                prior = load_or_build_road_removed(prior, directory, cfg)
            return Cached(prior, directory, True)
    t0 = time.perf_counter()
    prior = build_prior_map(seq, cfg, progress, road_removal=road_removal)
    scans = 0 if _is_map_file(seq) or getattr(seq, "delivers_map", False) else len(seq)
    meta = {
        "source": seq.name,
        "identity": seq.identity(),
        "scans": scans,
        "map": asdict(cfg),
        "points": int(len(prior.points)),
        "points_road_removed": None if prior.points_bev is None else int(len(prior.points_bev)),
        "build_seconds": time.perf_counter() - t0,
    }
    if _is_map_file(seq):
        meta["origin"] = [float(v) for v in prior.origin]  # repr-exact: json keeps every float64 digit

    def write(tmp: Path):
        prior.save(tmp)
        (tmp / "meta.json").write_text(json.dumps(meta, indent=2))

    try:
        atomic_write_dir(directory, write)
    except OSError as exc:
        raise LidarlocError(f"{directory}: cannot write the map cache ({exc.strerror})") from None
    if memory_map and len(prior.points) > LARGE_MAP_POINTS:
        prior = PriorMap.load(directory, meta, memory_map=True)
    return Cached(prior, directory, False)


def load_or_build_road_removed(
    prior: PriorMap, directory: Path, cfg: MapConfig, progress: Callable[[float], None] | None = None
) -> PriorMap:
    """``prior`` with its road-removed copy: from the map's cache ``directory`` if there, else
    computed and added to it (the file appears whole or not at all: written aside, then renamed)."""
    if prior.points_bev is not None:
        return prior
    path = directory / BEV_FILE
    if path.is_file():
        try:
            return PriorMap(
                points=prior.points,
                points_bev=check_points(np.load(path), BEV_FILE),
                voxel_size=prior.voxel_size,
                source=prior.source,
                origin=prior.origin,
            )
        except (OSError, ValueError) as exc:  # computed again below
            cache_rebuilt(path, f"{type(exc).__name__}: {exc}")
    done = remove_road(prior, cfg, progress)
    tmp = directory / f".{BEV_FILE}.{os.getpid()}.{threading.get_ident()}.tmp.npy"
    try:
        np.save(tmp, done.points_bev)
        os.replace(tmp, path)
        meta_path = directory / "meta.json"
        meta = json.loads(meta_path.read_text())
        meta["points_road_removed"] = int(len(done.points_bev))
        tmp_meta = meta_path.with_name(f".meta.{os.getpid()}.{threading.get_ident()}.tmp")
        tmp_meta.write_text(json.dumps(meta, indent=2))
        os.replace(tmp_meta, meta_path)
    except (OSError, ValueError) as exc:
        tmp.unlink(missing_ok=True)
        raise LidarlocError(f"{directory}: cannot add the road-removed map to the cache ({exc})") from None
    return done
