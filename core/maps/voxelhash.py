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
def mix64(z):
    """splitmix64 finaliser of the uint64 ``z``: every output bit depends on every input bit."""
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@nb.njit(cache=True, nogil=True)
def hash_slot(key, mask):
    """The slot of ``key`` in a table of mask + 1 slots: mixed so that the low bits are uniform."""
    return np.int64(mix64(np.uint64(key)) & np.uint64(mask))
