"""The lookup table's storage: uint8 distance codes in bricks of 8³ cells (see :mod:`.lookup`)."""

import numba as nb
import numpy as np

MISS_CODE = 255  # quantised "≥ d_max_built"
MAX_CODE = 254  # largest code for a stored distance
BRICK = 8  # cells per brick side
BRICK_SHIFT = 3  # log2(BRICK): cell index >> BRICK_SHIFT = brick index
BRICK_MASK = 7  # BRICK − 1: cell index & BRICK_MASK = cell within its brick
BRICK_CELLS = BRICK**3


@nb.njit(nogil=True, cache=True)
def extract_bricks(codes):
    """Split a (8a, 8b, 8c) code block into bricks; keep those holding any stored distance.
    Returns (brick coords within the block (k, 3), brick data (k, 512))."""
    nbx = codes.shape[0] // BRICK
    nby = codes.shape[1] // BRICK
    nbz = codes.shape[2] // BRICK
    keep = np.zeros(nbx * nby * nbz, np.bool_)
    n = 0
    for bx in range(nbx):
        for by in range(nby):
            for bz in range(nbz):
                found = False
                for i in range(BRICK):
                    for j in range(BRICK):
                        for k in range(BRICK):
                            if codes[bx * BRICK + i, by * BRICK + j, bz * BRICK + k] != MISS_CODE:
                                found = True
                                break
                        if found:
                            break
                    if found:
                        break
                if found:
                    keep[(bx * nby + by) * nbz + bz] = True
                    n += 1
    coords = np.empty((n, 3), np.int32)
    data = np.empty((n, BRICK_CELLS), np.uint8)
    m = 0
    for b in range(nbx * nby * nbz):
        if not keep[b]:
            continue
        bz = b % nbz
        by = (b // nbz) % nby
        bx = b // (nbz * nby)
        coords[m, 0] = bx
        coords[m, 1] = by
        coords[m, 2] = bz
        for i in range(BRICK):
            for j in range(BRICK):
                for k in range(BRICK):
                    data[m, (i << 6) | (j << 3) | k] = codes[bx * BRICK + i, by * BRICK + j, bz * BRICK + k]
        m += 1
    return coords, data
