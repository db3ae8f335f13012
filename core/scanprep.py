"""Scan preparation for the likelihood (paper: Sensor model).

The paper down-samples each scan with a voxel grid that keeps *one randomly chosen point* per
voxel (not the centroid): the kept points are real returns, spread uniformly over the 3D space
the scan covers, so near-range ground does not dominate the sum of distances.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .errors import LidarlocError
from .voxelhash import hash_slot, voxel_key

@nb.njit(nogil=True, cache=True)
def _first_per_voxel(pts, inv_voxel, order, table_bits):
    """Indices of the first point of ``order`` to land in each voxel (open addressing on the
    packed voxel key). Visiting the points in a random order makes that point a uniform pick."""
    cap = 1 << table_bits
    mask = cap - 1
    keys = np.full(cap, -1, np.int64)
    kept = np.empty(pts.shape[0], np.int64)
    n = 0
    for r in range(order.shape[0]):
        i = order[r]
        key = voxel_key(pts[i, 0], pts[i, 1], pts[i, 2], inv_voxel)
        slot = hash_slot(key, mask)
        while True:
            k = keys[slot]
            if k == key:
                break
            if k == -1:
                keys[slot] = key
                kept[n] = i
                n += 1
                break
            slot = (slot + 1) & mask
    return kept[:n]


def voxel_downsample_random(points: np.ndarray, voxel: float, rng_or_seed=0) -> np.ndarray:
    """One random point of ``points`` (N, ≥3) per ``voxel``-sized cube, as float32 (M, 3).

    ``rng_or_seed`` is a ``np.random.Generator`` (advanced by one draw of N numbers) or an
    integer seed; the result is deterministic given it. Kept points are returned in their
    original order.
    """
    voxel = float(voxel)
    if not voxel > 0:
        raise LidarlocError(f"scan voxel size must be > 0, got {voxel}")
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise LidarlocError(f"scan must be (N, ≥3) points; got shape {pts.shape}")
    pts = np.ascontiguousarray(pts[:, :3], dtype=np.float32)
    n = len(pts)
    if n == 0:
        return pts.reshape(0, 3)
    rng = rng_or_seed if isinstance(rng_or_seed, np.random.Generator) else np.random.default_rng(rng_or_seed)
    order = rng.permutation(n)
    bits = max(10, int(2 * n - 1).bit_length())  # load factor ≤ 0.5 even if every point is alone
    kept = _first_per_voxel(pts, 1.0 / voxel, order, bits)
    kept.sort()
    return pts[kept]
