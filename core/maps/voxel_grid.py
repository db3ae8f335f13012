"""Streaming voxel-grid fusion in numba: points added batch by batch to an open-addressing table
of voxel sums, read out as one centroid per voxel (the prior map's fusion, the viewer's and the
verification target's thinning)."""

from __future__ import annotations

import numba as nb
import numpy as np

from .voxelhash import hash_slot, voxel_key

_EMPTY = np.int64(-1)


@nb.njit(cache=True, nogil=True)
def _insert(table_keys, table_acc, pts, inv_voxel):
    """Add points (N, ≥3) to the table; returns the number of newly occupied slots."""
    mask = table_keys.shape[0] - 1
    added = 0
    for i in range(pts.shape[0]):
        added += _add_point(table_keys, table_acc, mask, pts[i, 0], pts[i, 1], pts[i, 2], inv_voxel)
    return added


@nb.njit(cache=True, nogil=True)
def _insert_scan(table_keys, table_acc, scan, R, t, min_r2, max_r2, inv_voxel):
    """Add a sensor-frame scan (N, ≥3) placed at pose (R, t), keeping the returns whose range lies
    in [min_r, max_r] (``range_filter``'s rule). One pass, no temporaries: the map's fusion
    spends its time here, once per scan of the mapping drive."""
    mask = table_keys.shape[0] - 1
    added = 0
    for i in range(scan.shape[0]):
        # the range test in the scan's own precision, as range_filter does it
        r2 = scan[i, 0] * scan[i, 0] + scan[i, 1] * scan[i, 1] + scan[i, 2] * scan[i, 2]
        if r2 < min_r2 or r2 > max_r2:
            continue
        x = np.float64(scan[i, 0])
        y = np.float64(scan[i, 1])
        z = np.float64(scan[i, 2])
        wx = x * R[0, 0] + y * R[0, 1] + z * R[0, 2] + t[0]
        wy = x * R[1, 0] + y * R[1, 1] + z * R[1, 2] + t[1]
        wz = x * R[2, 0] + y * R[2, 1] + z * R[2, 2] + t[2]
        added += _add_point(table_keys, table_acc, mask, wx, wy, wz, inv_voxel)
    return added


@nb.njit(cache=True, nogil=True, inline="always")
def _add_point(table_keys, table_acc, mask, x, y, z, inv_voxel):
    key = voxel_key(x, y, z, inv_voxel)
    h = hash_slot(key, mask)
    added = 0
    while True:
        k = table_keys[h]
        if k == key:
            break
        if k == -1:
            table_keys[h] = key
            added = 1
            break
        h = (h + 1) & mask
    table_acc[h, 0] += x
    table_acc[h, 1] += y
    table_acc[h, 2] += z
    table_acc[h, 3] += 1.0
    return added


class VoxelAccumulator:
    """Streaming voxel-grid fusion: add point batches, read out one centroid per voxel.

    Each slot's sums and count sit in one row (x, y, z sums and the count, float64: exact up to
    2^53 returns) so that adding a point touches one cache line beside its key: the table is far
    larger than the caches, and one miss per point instead of three is most of the fusion's speed."""

    def __init__(self, voxel_size: float, capacity: int = 1 << 20):
        self.voxel_size = float(voxel_size)
        self._alloc(capacity)
        self.size = 0

    def _alloc(self, capacity: int):
        self.keys = np.full(capacity, _EMPTY, dtype=np.int64)
        self.acc = np.zeros((capacity, 4), dtype=np.float64)

    def _reserve(self, n_new: int) -> None:
        # keep the load factor ≤ 0.5 even if every point lands in a new voxel
        while (self.size + n_new) * 2 > len(self.keys):
            self._grow()

    def add(self, pts: np.ndarray) -> None:
        pts = np.ascontiguousarray(pts[:, :3], dtype=np.float64)
        self._reserve(len(pts))
        self.size += _insert(self.keys, self.acc, pts, 1.0 / self.voxel_size)

    def add_scan(self, scan: np.ndarray, pose: np.ndarray, min_range: float, max_range: float) -> None:
        """Add the returns of a sensor-frame scan within [min_range, max_range] m, placed at
        ``pose`` (4×4 world ← sensor): the same points as ``add(range_filter(scan) @ R.T + t)``."""
        scan = np.ascontiguousarray(scan)
        if scan.dtype not in (np.float32, np.float64):
            scan = scan.astype(np.float64)
        pose = np.asarray(pose, dtype=np.float64)
        # squared limits in the scan's precision: numpy compares a float32 array with a Python
        # float in float32
        limit = scan.dtype.type
        self._reserve(len(scan))
        self.size += _insert_scan(
            self.keys,
            self.acc,
            scan,
            np.ascontiguousarray(pose[:3, :3]),
            np.ascontiguousarray(pose[:3, 3]),
            limit(float(min_range) ** 2),
            limit(float(max_range) ** 2),
            1.0 / self.voxel_size,
        )

    def _grow(self):
        used = self.keys != _EMPTY
        keys_old, acc_old = self.keys[used], self.acc[used]
        self._alloc(len(self.keys) * 2)
        # Re-insert each voxel's sums and count as they are: exact.
        _reinsert(self.keys, self.acc, keys_old, acc_old)

    def points(self) -> np.ndarray:
        used = self.keys != _EMPTY
        acc = self.acc[used]
        return (acc[:, :3] / acc[:, 3:4]).astype(np.float32)


CENTROID_CHUNK = 1 << 18  # points added to the hash table at a time


def voxel_centroids(points: np.ndarray, voxel: float, cap: int | None = None) -> np.ndarray | None:
    """One centroid per ``voxel`` (float32, voxels aligned to the origin), the points added a
    chunk at a time so that memory stays at the voxels' hash table (about twice their count) and
    one chunk, however large ``points`` (a memory-mapped city map is never copied whole); None as
    soon as there are more than ``cap`` voxels."""
    acc = VoxelAccumulator(voxel, capacity=1 << 12)
    for s in range(0, len(points), CENTROID_CHUNK):
        acc.add(points[s : s + CENTROID_CHUNK])
        if cap is not None and acc.size > cap:
            return None
    return acc.points()


@nb.njit(cache=True, nogil=True)
def _reinsert(table_keys, table_acc, keys, acc):
    mask = table_keys.shape[0] - 1
    for i in range(keys.shape[0]):
        key = keys[i]
        h = hash_slot(key, mask)
        while table_keys[h] != -1:
            h = (h + 1) & mask
        table_keys[h] = key
        table_acc[h] = acc[i]
