"""The scan likelihood of the sensor model (paper: Sensor model):

    log p(y | x_i) = −Σ_j min(d_j², d_max²) / σ²,   d_j = L(R_i·X_j + p_i)

for every particle i, with R_i = R(yaw, pitch, roll) (z-y-x Euler, geometry.rotation_zyx) and
L the lookup table. One numba kernel (compiled parallel over particles, and serial for small
passes); each particle's sum runs sequentially in one thread, so the result does not depend on
the thread count.

:func:`log_likelihood` is the plain sum for every particle. The filter uses
:func:`log_likelihood_floored`, which gives the same log-weights wherever they can matter and
is several times faster: a particle whose log-weight (prior + log-likelihood) ends more than
``margin`` (default 800) below the best particle's has a normalised weight below e^−800, which
is exactly 0.0 in float64 (the smallest double is ≈ e^−745). Its sum is stopped as soon as the
partial sum proves that, and its log-weight is set to the floor ``best − margin`` (so it stays
finite, has weight 0.0 now, and can still regain weight on later scans like any other particle).
The decision depends only on exact sums, never on thread timing, so results are deterministic.
The scan is visited in a fixed scrambled order so that a partial sum is a fair sample of the
whole scan (a scan's own order runs laser by laser).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .errors import LidarlocError
from .lookup import BRICK_CELLS, BRICK_MASK, BRICK_SHIFT, MISS_CODE, LookupTable


@nb.njit(inline="always", nogil=True, fastmath=True, cache=True)
def _rotation_zyx(yaw, pitch, roll):
    """Row-major entries of Rz(yaw)·Ry(pitch)·Rx(roll), as geometry.rotation_zyx, for kernels."""
    cy, sy = math.cos(yaw), math.sin(yaw)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cr, sr = math.cos(roll), math.sin(roll)
    return (cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr,
            sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr,
            -sp, cp * sr, cp * cr)


_CHUNK = 64    # scan points per inner block of the likelihood kernel
BRICK_CELL_BITS = BRICK_CELLS.bit_length() - 1    # a slot's cells start at slot << 9


def _make_costs_kernel(parallel: bool):
    """The likelihood kernel, compiled parallel over particles or serial (same code, same sums).

    ``setup`` is a closure cell on purpose: numba's on-disk cache keys a function by its file,
    name and line plus its closure's contents, so the two twins get separate cache entries."""
    setup = (_CHUNK, parallel)

    def costs_until(states, pts, n_points, limit, origin, inv_res, nbx, nby, nbz, slot_of_brick, cells,
                    sq_cost, cost, complete):
        """Σ sq_cost over the first ``n_points`` points of ``pts`` ((3, M) float32, one row per
        axis) per particle, stopping early once the sum exceeds limit[i] (then complete[i] is False
        and cost[i] is the partial sum so far). The table arrays are LookupTable.flat_kernel_args.

        The read is :func:`~lidarloc.core.lookup.lookup_code`'s, restructured for speed. Each block
        of _CHUNK points goes through two loops:

        1. pure arithmetic, no memory reads, which the compiler vectorises (AVX2/AVX-512): the
           transform folded with the grid origin and resolution, in float32 (coordinates are
           ≤ ~10⁴ cells: float32 keeps them to ~10⁻³ cell), the bounds test, and each point's
           brick and cell number — a point outside the grid gets the sentinel brick whose slot
           is the all-miss brick, so no branch remains;
        2. the dependent reads (slot of the brick, code of the cell, cost of the code) and the sum.

        Keeping every read out of loop 1 is what pays: with the slot read inside it, the loop
        stays scalar and the kernel took 91 ms instead of 57 ms (1000 converged particles ×
        12.8k town points, one thread; 99 ms for the previous single-loop kernel).
        The limit is checked once per block, so a particle may read up to _CHUNK − 1 points past it.
        Each particle's sum runs in a fixed order in one thread: thread count never changes it."""
        chunk = setup[0]
        outside = nbx * nby * nbz            # index of the sentinel entry of slot_of_brick
        ir = np.float32(inv_res)
        xs, ys, zs = pts[0], pts[1], pts[2]
        for i in nb.prange(states.shape[0]):
            r00, r01, r02, r10, r11, r12, r20, r21, r22 = _rotation_zyx(states[i, 3], states[i, 4], states[i, 5])
            # rotation scaled to cells, translation relative to the grid origin in cells
            a00, a01, a02 = np.float32(r00) * ir, np.float32(r01) * ir, np.float32(r02) * ir
            a10, a11, a12 = np.float32(r10) * ir, np.float32(r11) * ir, np.float32(r12) * ir
            a20, a21, a22 = np.float32(r20) * ir, np.float32(r21) * ir, np.float32(r22) * ir
            tx = np.float32((states[i, 0] - origin[0]) * inv_res)
            ty = np.float32((states[i, 1] - origin[1]) * inv_res)
            tz = np.float32((states[i, 2] - origin[2]) * inv_res)
            lim = limit[i]
            acc = 0.0
            done = True
            brick_at = np.empty(chunk, np.int32)
            cell_at = np.empty(chunk, np.int32)
            for j0 in range(0, n_points, chunk):
                m = min(n_points, j0 + chunk) - j0
                for q in range(m):
                    px, py, pz = xs[j0 + q], ys[j0 + q], zs[j0 + q]
                    fx = a00 * px + a01 * py + a02 * pz + tx
                    fy = a10 * px + a11 * py + a12 * pz + ty
                    fz = a20 * px + a21 * py + a22 * pz + tz
                    ix, iy, iz = np.int32(fx), np.int32(fy), np.int32(fz)
                    bx, by, bz = ix >> BRICK_SHIFT, iy >> BRICK_SHIFT, iz >> BRICK_SHIFT
                    # fx ≥ 0 rejects (−1, 0), which truncates to 0; bx ≥ 0 rejects ±inf and values
                    # beyond int32, which convert to INT_MIN on x86; NaN fails every comparison
                    inside = ((fx >= 0) & (fy >= 0) & (fz >= 0) & (bx >= 0) & (by >= 0) & (bz >= 0)
                              & (bx < nbx) & (by < nby) & (bz < nbz))
                    brick_at[q] = (bx * nby + by) * nbz + bz if inside else outside
                    cell_at[q] = ((ix & BRICK_MASK) << (2 * BRICK_SHIFT)) | ((iy & BRICK_MASK) << BRICK_SHIFT) | (iz & BRICK_MASK)
                block = 0.0
                for q in range(m):
                    block += sq_cost[cells[(np.int64(slot_of_brick[brick_at[q]]) << BRICK_CELL_BITS) | cell_at[q]]]
                acc += block
                if acc > lim:
                    done = False
                    break
            cost[i] = acc
            complete[i] = done

    return nb.njit(parallel=parallel, nogil=True, fastmath={"nsz", "arcp", "afn"}, cache=True)(costs_until)


# Parallel over particles for the full passes; a serial twin (same code, same sums) for the
# small ones — a handful of particles or a 1/32 subsample — where waking a second thread costs
# more than it saves when another block's process holds the other core (measured ~10 ms/scan).
_costs_until = _make_costs_kernel(parallel=True)
_costs_until_serial = _make_costs_kernel(parallel=False)


def scrambled_order(m: int) -> np.ndarray:
    """A fixed permutation of range(m) that spreads consecutive indices over the whole scan
    (golden-ratio stride, coprime with m)."""
    if m <= 2:
        return np.arange(m)
    stride = max(1, int(round(m * 0.6180339887498949)))
    while math.gcd(stride, m) != 1:
        stride += 1
    return (np.arange(m, dtype=np.int64) * stride) % m


def squared_cost_table(lookup: LookupTable, d_max: float, sigma: float) -> np.ndarray:
    """min(d², d_max²)/σ² for each of the 256 distance codes (code 255: a miss, = d_max)."""
    d = np.minimum(np.arange(256, dtype=np.float64) * lookup.step, d_max)
    d[MISS_CODE] = d_max
    return d * d / (sigma * sigma)


def log_likelihood(states: np.ndarray, scan: np.ndarray, lookup: LookupTable, d_max: float,
                   sigma: float) -> np.ndarray:
    """(N,) float64 log-likelihoods of (N, ≥6) particle states for a prepared (M, 3) scan.

    ``d_max`` above the table's built value is capped at it (the table knows nothing beyond).
    """
    d_max, sigma = float(d_max), float(sigma)
    if not d_max > 0:
        raise LidarlocError(f"d_max must be > 0, got {d_max}")
    if not sigma > 0:
        raise LidarlocError(f"sigma must be > 0, got {sigma}")
    st = np.ascontiguousarray(states, dtype=np.float64)
    if st.ndim != 2 or st.shape[1] < 6:
        raise LidarlocError(f"states must be (N, ≥6); got shape {st.shape}")
    pts = np.asarray(scan)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise LidarlocError(f"scan must be (M, ≥3); got shape {pts.shape}")
    n = len(st)
    if n == 0 or len(pts) == 0:
        return np.zeros(n, np.float64)
    pts_by_axis = np.ascontiguousarray(pts[:, :3].T, dtype=np.float32)
    cost_table = squared_cost_table(lookup, min(d_max, lookup.d_max_built), sigma)
    cost = np.empty(n, np.float64)
    complete = np.empty(n, np.bool_)
    # the floored filter's kernel with no limit: the same sums in the same order
    kernel = _costs_until if n > 64 else _costs_until_serial
    kernel(st, pts_by_axis, len(pts), np.full(n, np.inf), *lookup.flat_kernel_args, cost_table, cost, complete)
    return -cost


FLOOR_MARGIN = 800.0   # > 745: e^−margin is 0.0 in float64


def log_likelihood_floored(states: np.ndarray, scan: np.ndarray, lookup: LookupTable, d_max: float, sigma: float,
                           prior_log_w: np.ndarray, margin: float = FLOOR_MARGIN) -> np.ndarray:
    """Log-likelihoods as :func:`log_likelihood`, except that where prior_log_w + ll would end
    more than ``margin`` below the best particle's, ll is raised to put it exactly at that floor
    (see the module docstring). Returns (N,) float64."""
    d_max, sigma = float(d_max), float(sigma)
    if not (d_max > 0 and sigma > 0):
        raise LidarlocError(f"d_max and sigma must be > 0, got {d_max}, {sigma}")
    st = np.ascontiguousarray(states, dtype=np.float64)
    prior = np.ascontiguousarray(prior_log_w, dtype=np.float64)
    n = len(st)
    pts = np.asarray(scan)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise LidarlocError(f"scan must be (M, ≥3); got shape {pts.shape}")
    m = len(pts)
    if n == 0 or m == 0:
        return np.zeros(n, np.float64)
    pts = np.ascontiguousarray(pts[scrambled_order(m), :3].T, dtype=np.float32)   # (3, m)
    cost_table = squared_cost_table(lookup, min(d_max, lookup.d_max_built), sigma)
    args = (*lookup.flat_kernel_args, cost_table)
    cost = np.empty(n, np.float64)
    complete = np.empty(n, np.bool_)
    no_limit = np.full(n, np.inf)
    # 1. A cheap look at every particle (1/32 of the points) names a few likely-best ones …
    n_sub = max(1, m // 32)
    _costs_until_serial(st, pts, n_sub, no_limit, *args, cost, complete)
    guess = prior - cost * (m / n_sub)
    top = np.argsort(-guess, kind="stable")[: min(4, n)]
    # 2. … whose full sums give a value every particle must come within ``margin`` of …
    top_cost = np.empty(len(top), np.float64)
    top_complete = np.empty(len(top), np.bool_)
    _costs_until_serial(st[top], pts, m, no_limit[: len(top)], *args, top_cost, top_complete)
    bound = float(np.max(prior[top] - top_cost))
    # 3. … so the sum of particle i can stop once prior_i − partial > bound − margin fails.
    limit = prior - bound + margin
    _costs_until(st, pts, m, limit, *args, cost, complete)
    value = np.where(complete, prior - cost, -np.inf)
    floor = float(np.max(value)) - margin
    ll = -cost
    below = ~complete | (value < floor)
    ll[below] = floor - prior[below]
    return ll
