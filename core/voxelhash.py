"""Voxel keys and hash slots shared by the numba open-addressing tables (map fusion, random
voxel down-sampling)."""

import numba as nb
import numpy as np

_OFFSET = 1 << 20  # voxel indices packed as three 21-bit fields (±1M voxels per axis)


@nb.njit(cache=True, nogil=True)
def voxel_key(x, y, z, inv_voxel):
    """The packed int64 key of the voxel holding (x, y, z)."""
    ix = np.int64(np.floor(x * inv_voxel)) + _OFFSET
    iy = np.int64(np.floor(y * inv_voxel)) + _OFFSET
    iz = np.int64(np.floor(z * inv_voxel)) + _OFFSET
    return (ix << 42) | (iy << 21) | iz


@nb.njit(cache=True, nogil=True)
def hash_slot(key, mask):
    """splitmix64 finaliser: mixes all 64 bits so the low bits used as the slot are uniform."""
    z = np.uint64(key)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z = z ^ (z >> np.uint64(31))
    return np.int64(z & np.uint64(mask))
