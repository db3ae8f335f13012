"""The prior map: scans fused with their ground-truth poses (the paper's protocol), streamed scan
by scan into a voxel grid, plus the road-removed copy used for the bird's-eye-view matcher.

The voxel grid is an open-addressing hash table in numba (voxel key → sum of points, count), so
building never holds the raw points of more than one scan; each voxel's point is the centroid of
the returns that fell in it.
"""

from __future__ import annotations

import json
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numba as nb
import numpy as np

from .cache import Cached, atomic_write_dir, default_cache_root
from .config import MapConfig
from .errors import DataError, LidarlocError
from .o3d import open3d
from .voxelhash import hash_slot, voxel_key

_EMPTY = np.int64(-1)


@nb.njit(cache=True, nogil=True)
def _insert(table_keys, table_sums, table_counts, pts, inv_voxel):
    """Add points to the table; returns the number of newly occupied slots."""
    cap = table_keys.shape[0]
    mask = cap - 1
    added = 0
    for i in range(pts.shape[0]):
        key = voxel_key(pts[i, 0], pts[i, 1], pts[i, 2], inv_voxel)
        h = hash_slot(key, mask)
        while True:
            k = table_keys[h]
            if k == key:
                break
            if k == -1:
                table_keys[h] = key
                added += 1
                break
            h = (h + 1) & mask
        table_sums[h, 0] += pts[i, 0]
        table_sums[h, 1] += pts[i, 1]
        table_sums[h, 2] += pts[i, 2]
        table_counts[h] += 1
    return added


class VoxelAccumulator:
    """Streaming voxel-grid fusion: add point batches, read out one centroid per voxel."""

    def __init__(self, voxel_size: float, capacity: int = 1 << 20):
        self.voxel_size = float(voxel_size)
        self._alloc(capacity)
        self.size = 0

    def _alloc(self, capacity: int):
        self.keys = np.full(capacity, _EMPTY, dtype=np.int64)
        self.sums = np.zeros((capacity, 3), dtype=np.float64)
        self.counts = np.zeros(capacity, dtype=np.int32)

    def add(self, pts: np.ndarray) -> None:
        pts = np.ascontiguousarray(pts[:, :3], dtype=np.float64)
        # keep the load factor ≤ 0.5 even if every point lands in a new voxel
        while (self.size + len(pts)) * 2 > len(self.keys):
            self._grow()
        self.size += _insert(self.keys, self.sums, self.counts, pts, 1.0 / self.voxel_size)

    def _grow(self):
        used = self.keys != _EMPTY
        centroids_sum, counts = self.sums[used], self.counts[used]
        keys_old = self.keys[used]
        self._alloc(len(self.keys) * 2)
        # Re-insert by replaying each voxel's centroid with its weight: exact for the sums.
        _reinsert(self.keys, self.sums, self.counts, keys_old, centroids_sum, counts)

    def points(self) -> np.ndarray:
        used = self.keys != _EMPTY
        return (self.sums[used] / self.counts[used, None]).astype(np.float32)


@nb.njit(cache=True, nogil=True)
def _reinsert(table_keys, table_sums, table_counts, keys, sums, counts):
    mask = table_keys.shape[0] - 1
    for i in range(keys.shape[0]):
        key = keys[i]
        h = hash_slot(key, mask)
        while table_keys[h] != -1:
            h = (h + 1) & mask
        table_keys[h] = key
        table_sums[h, 0] = sums[i, 0]
        table_sums[h, 1] = sums[i, 1]
        table_sums[h, 2] = sums[i, 2]
        table_counts[h] = counts[i]


def range_filter(points: np.ndarray, cfg: MapConfig) -> np.ndarray:
    r2 = np.einsum("ij,ij->i", points[:, :3], points[:, :3])
    return points[(r2 >= cfg.scan_min_range**2) & (r2 <= cfg.scan_max_range**2)]


def flat_surface_mask(points: np.ndarray, cfg: MapConfig) -> np.ndarray:
    """True where a point lies on a flat (road-like) surface: |normal_z| > cfg.road_normal_z.

    The paper removes points "with z-coordinate of its normal greater than 0.75"; normals from PCA
    have no consistent sign, so the absolute value is compared.
    """
    o3d = open3d()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points[:, :3], dtype=np.float64)))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=cfg.normal_radius, max_nn=cfg.normal_max_nn))
    normals = np.asarray(pcd.normals)
    return np.abs(normals[:, 2]) > cfg.road_normal_z


def remove_flat(points: np.ndarray, cfg: MapConfig) -> np.ndarray:
    return points[~flat_surface_mask(points, cfg)]


@dataclass
class PriorMap:
    points: np.ndarray        # (N, 3) float32, world frame (= first LiDAR pose)
    points_bev: np.ndarray    # (M, 3) float32, flat surfaces removed (for the bird's-eye view)
    voxel_size: float
    source: str = ""

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.points.min(axis=0), self.points.max(axis=0)

    def save(self, directory: Path) -> None:
        np.save(directory / "map_points.npy", self.points)
        np.save(directory / "map_points_bev.npy", self.points_bev)

    @classmethod
    def load(cls, directory: Path, meta: dict) -> "PriorMap":
        return cls(
            points=np.load(directory / "map_points.npy"),
            points_bev=np.load(directory / "map_points_bev.npy"),
            voxel_size=float(meta["map"]["voxel_size"]),
            source=meta.get("source", ""),
        )


def build_prior_map(seq, cfg: MapConfig, progress: Callable[[int, int], None] | None = None) -> PriorMap:
    """Fuse every scan of ``seq`` with its ground-truth pose into a voxel map, then remove flats."""
    poses = seq.poses
    if poses is None:
        raise DataError(f"{seq.name}: a prior map needs ground-truth poses, and this sequence has none")
    acc = VoxelAccumulator(cfg.voxel_size)
    n = len(seq)

    def load(i):
        pts = range_filter(seq.scan(i), cfg)[:, :3].astype(np.float64)
        T = poses[i]
        return pts @ T[:3, :3].T + T[:3, 3]

    # Reading (or simulating) scans overlaps with the insertion: a small look-ahead on two
    # threads keeps both cores busy while holding only a few scans in memory.
    lookahead = 4
    with ThreadPoolExecutor(2, thread_name_prefix="lidarloc-map") as pool:
        pending = [pool.submit(load, i) for i in range(min(lookahead, n))]
        for i in range(n):
            pts = pending.pop(0).result()
            if i + lookahead < n:
                pending.append(pool.submit(load, i + lookahead))
            acc.add(pts)
            if progress is not None:
                progress(i + 1, n)
    points = acc.points()
    if len(points) == 0:
        raise DataError(f"{seq.name}: the map is empty (no points within range)")
    bev = points[~flat_surface_mask(points, cfg)]
    return PriorMap(points=points, points_bev=bev.astype(np.float32), voxel_size=cfg.voxel_size, source=seq.name)


# ------------------------------------------------------------------------------------- cache
def map_cache_dir(seq, cfg: MapConfig, cache_root: Path | None = None) -> Path:
    import hashlib

    params = json.dumps(asdict(cfg), sort_keys=True)
    key = hashlib.sha1(f"{seq.cache_key()}|{params}".encode()).hexdigest()[:16]
    return Path(cache_root or default_cache_root()) / f"map-{key}"


def load_or_build_map(seq, cfg: MapConfig, cache_root: Path | None = None,
                      progress: Callable[[int, int], None] | None = None) -> Cached[PriorMap]:
    """The prior map of ``seq`` from the cache, or built and cached (in its own directory under
    ``cache_root``, default :func:`~lidarloc.core.cache.default_cache_root`)."""
    directory = map_cache_dir(seq, cfg, cache_root)
    meta_path = directory / "meta.json"
    if meta_path.is_file():
        try:
            meta = json.loads(meta_path.read_text())
            return Cached(PriorMap.load(directory, meta), directory, True)
        except (OSError, ValueError, KeyError):
            pass  # unreadable entry: rebuild it below
    t0 = time.perf_counter()
    prior = build_prior_map(seq, cfg, progress)
    meta = {"source": seq.name, "identity": seq.identity(), "scans": len(seq), "map": asdict(cfg),
            "points": int(len(prior.points)), "points_road_removed": int(len(prior.points_bev)),
            "build_seconds": time.perf_counter() - t0}

    def write(tmp: Path):
        prior.save(tmp)
        (tmp / "meta.json").write_text(json.dumps(meta, indent=2))

    try:
        atomic_write_dir(directory, write)
    except OSError as exc:
        raise LidarlocError(f"{directory}: cannot write the map cache ({exc.strerror})") from None
    return Cached(prior, directory, False)
