"""The scan's likelihood around a pose: what the particle filter's sensor model says about every
x–y position near the estimate, and about any one particle.

:class:`LikelihoodModel` is the filter's likelihood with the options it runs with now (lookup
table, effective d_max, σ, temperature, unexplained share; :meth:`LikelihoodModel.of` reads them
off a running :class:`~lidarloc.core.localizer.Localizer`), so a view of it shows what the filter
weighs with, not a re-implementation.

Likelihood surface (:meth:`LikelihoodModel.surface`): the log-likelihood of a prepared scan
(sensor frame) for a sensor placed at every cell centre of an x–y grid around a pose (default
±20 m in 0.5 m cells: 81 × 81), keeping the pose's z, pitch and roll and, by default, its yaw.
``yaw_window`` > 0 takes, per cell, the best over yaws at ``yaw_step`` (2°) steps within
±``yaw_window`` of the pose's yaw. The default window when asked for, :data:`YAW_WINDOW`, is ±10°:
wider than a tracking filter's yaw error (a few degrees), narrow enough that the 11 yaws cost
11 single-yaw surfaces, not 180. Every cell's value is the filter's log-likelihood of that pose:
the same cost table (:func:`~lidarloc.core.filter.likelihood.cost_table`) read for the same lookup cell
of every point (the same float32 arithmetic gives the same cell), summed in full: the filter's
early stop only floors weights that are 0.0 anyway, and a surface wants every value. The
temperature "per point" divides by the number of points given, as the filter does for the scan
it weighs (with dynamic-point rejection on, the filter weighs a subset; the surface uses every
point it is given).

Why its own kernel: the cells of one yaw differ only by a translation, so the scan is rotated
once and every point's table coordinates are offset per cell, and each point's 81 reads along a
grid row stay within a few bricks of the table; rows run on separate threads (numba ``prange``;
one thread with ``parallel=False``, as the viewer asks: a filter may be running beside it;
``nogil``: the viewer computes it on a worker thread). Measured on the real drive (~14.8k points
per prepared scan, 2 cores, load ≈ 1): 98 ms for 81 × 81 cells (``lidarloc bench surface``),
against 167 ms through the filter's kernel with the 6561 cells as particles (scan 50; 345 ms on
one thread). Only the order of each cell's sum differs from the filter's (the tests compare both).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numba as nb
import numpy as np

from ..errors import LidarlocError
from ..geometry import as_points
from ..maps.lookup import BRICK_MASK, BRICK_SHIFT, LookupTable
from .likelihood import _rotation_zyx, check_shape, cost_table, effective_temperature, log_likelihood

HALF_WIDTH = 20.0  # m, the grid reaches this far from the pose in x and y
CELL = 0.5  # m, grid cell
YAW_STEP = 2.0 * math.pi / 180.0  # rad, yaw step of the best-over-yaw surface
YAW_WINDOW = 10.0 * math.pi / 180.0  # rad, ± around the pose's yaw when the best over yaw is asked for
MAX_CELLS = 1_000_000  # a grid beyond this is a typing error, not a view


@nb.njit(nogil=True, cache=True)
def _rotated_cells(pts, yaw, pitch, roll, inv_res):
    """(3, M) float32: R·p scaled to table cells, rounded as the filter's kernel rounds it
    (float32 products of the float32 point and the float32 rotation · 1/δ, summed in its order)."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = _rotation_zyx(yaw, pitch, roll)
    ir = np.float32(inv_res)
    a00, a01, a02 = np.float32(r00) * ir, np.float32(r01) * ir, np.float32(r02) * ir
    a10, a11, a12 = np.float32(r10) * ir, np.float32(r11) * ir, np.float32(r12) * ir
    a20, a21, a22 = np.float32(r20) * ir, np.float32(r21) * ir, np.float32(r22) * ir
    out = np.empty((3, pts.shape[1]), np.float32)
    for j in range(pts.shape[1]):
        px, py, pz = pts[0, j], pts[1, j], pts[2, j]
        out[0, j] = a00 * px + a01 * py + a02 * pz
        out[1, j] = a10 * px + a11 * py + a12 * pz
        out[2, j] = a20 * px + a21 * py + a22 * pz
    return out


def _rows(rot, tx, ty, tz, nbx, nby, nbz, slot_of_brick, cells, costs, out):
    """out[i, k] = −Σ_j costs[code of the table cell of point j with the sensor at (tx[i], ty[k], tz)].

    rot: (3, M) float32 rotated points in table cells (:func:`_rotated_cells`); tx, ty, tz: the
    sensor's position relative to the table's origin in cells, float32, as the filter's kernel
    has them, so the sum rot + t and the cell it falls in are the filter's. A point outside the
    table reads through the sentinel entry of ``slot_of_brick`` (the all-miss brick), as there.

    As in the filter's kernel, each point's row of cells is first turned into brick and cell
    numbers in a loop without memory reads (which the compiler vectorises), then read."""
    m = rot.shape[1]
    ny = ty.shape[0]
    outside = nbx * nby * nbz
    for i in nb.prange(tx.shape[0]):
        acc = np.zeros(ny, np.float64)
        brick_at = np.empty(ny, np.int32)
        cell_at = np.empty(ny, np.int32)
        for j in range(m):
            z = rot[2, j] + tz
            x = rot[0, j] + tx[i]
            iz, ix = np.int32(z), np.int32(x)
            bz, bx = iz >> BRICK_SHIFT, ix >> BRICK_SHIFT
            # as in the filter: z ≥ 0 rejects (−1, 0), which truncates to 0; b ≥ 0 rejects
            # values beyond int32; NaN fails every comparison
            inside_xz = (z >= 0) & (x >= 0) & (bz >= 0) & (bx >= 0) & (bz < nbz) & (bx < nbx)
            base = bx * nby
            cell_xz = ((ix & BRICK_MASK) << (2 * BRICK_SHIFT)) | (iz & BRICK_MASK)
            y0 = rot[1, j]
            for k in range(ny):
                y = y0 + ty[k]
                iy = np.int32(y)
                by = iy >> BRICK_SHIFT
                inside = inside_xz & (y >= 0) & (by >= 0) & (by < nby)
                brick_at[k] = (base + by) * nbz + bz if inside else outside
                cell_at[k] = cell_xz | ((iy & BRICK_MASK) << BRICK_SHIFT)
            for k in range(ny):
                acc[k] += costs[cells[(np.int64(slot_of_brick[brick_at[k]]) << (3 * BRICK_SHIFT)) | cell_at[k]]]
        for k in range(ny):
            out[i, k] = -acc[k]


# Rows on both threads for a surface computed alone (``lidarloc inspect``, the bench); one thread
# where it shares the machine with a running filter (the viewer): a parallel region waits for the
# slower of its threads, and with the filter's kernels, its child processes and a browser on two
# cores one of them was nearly always descheduled (measured while playing: 0.17 s with two
# threads, 0.10 s with one; the sums are the same either way).
_surface_rows = nb.njit(parallel=True, nogil=True, fastmath={"nsz", "arcp"}, cache=True)(_rows)
_surface_rows_serial = nb.njit(nogil=True, fastmath={"nsz", "arcp"}, cache=True)(_rows)


@dataclass(frozen=True)
class Surface:
    """A likelihood surface: ``ll[i, k]`` is the log-likelihood (nats) of the sensor at
    (``xs[i]``, ``ys[k]``), ``yaw[i, k]`` the yaw it was taken at (the best one, over a window)."""

    xs: np.ndarray  # (nx,) cell centres, world x (m)
    ys: np.ndarray  # (ny,) cell centres, world y (m)
    ll: np.ndarray  # (nx, ny) float64 log-likelihood
    yaw: np.ndarray  # (nx, ny) rad
    center: np.ndarray  # (6,) x, y, z, yaw, pitch, roll the grid is centred on
    cell: float  # m
    yaw_window: float  # rad, 0: the centre's yaw only
    n_points: int
    ms: float  # wall time of the computation

    @property
    def argmax(self) -> tuple[int, int]:
        i, k = np.unravel_index(int(np.argmax(self.ll)), self.ll.shape)
        return int(i), int(k)

    @property
    def argmax_xy(self) -> np.ndarray:
        """(x, y) of the best cell."""
        i, k = self.argmax
        return np.array([self.xs[i], self.ys[k]])

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x0, y0, x1, y1) of the grid's outer edges."""
        h = self.cell / 2.0
        return (float(self.xs[0] - h), float(self.ys[0] - h), float(self.xs[-1] + h), float(self.ys[-1] + h))


@dataclass(frozen=True)
class LikelihoodModel:
    """The particle filter's likelihood with one set of options (see the module docstring)."""

    lookup: LookupTable
    d_max: float  # m, the effective cap (≤ the table's built d_max)
    sigma: float  # m
    temperature: float = 1.0  # as PFConfig.temperature (0: per point)
    unexplained_share: float = 0.0

    def __post_init__(self):
        check_shape(self.temperature, self.unexplained_share)
        if not (self.d_max > 0 and self.sigma > 0):
            raise LidarlocError(f"d_max and sigma must be > 0, got {self.d_max}, {self.sigma}")

    @classmethod
    def of(cls, localizer) -> LikelihoodModel:
        """The options a localizer's filter weighs the next scan with."""
        pf = localizer.cfg.pf
        return cls(
            localizer.lookup,
            float(localizer.effective_d_max),
            float(pf.sigma),
            float(pf.temperature),
            float(pf.unexplained_share),
        )

    def costs(self, n_points: int) -> np.ndarray:
        """The 256-entry per-point cost table for a scan of ``n_points`` points."""
        return cost_table(
            self.lookup,
            self.lookup.capped(self.d_max),
            self.sigma,
            effective_temperature(self.temperature, n_points),
            self.unexplained_share,
        )

    def log_likelihood(self, states: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(N,) log-likelihoods of (N, ≥6) states for (M, ≥3) sensor-frame points: the
        filter's kernel, summed in full."""
        return log_likelihood(
            states,
            points,
            self.lookup,
            self.d_max,
            self.sigma,
            temperature=self.temperature,
            unexplained_share=self.unexplained_share,
        )

    def surface(
        self,
        points: np.ndarray,
        center,
        half_width: float = HALF_WIDTH,
        cell: float = CELL,
        yaw_window: float = 0.0,
        yaw_step: float = YAW_STEP,
        parallel: bool = True,
    ) -> Surface:
        """The log-likelihood of ``points`` ((M, ≥3), sensor frame) on an x–y grid around
        ``center`` (x, y, z, yaw, pitch, roll): cells of ``cell`` metres out to ±``half_width``
        (rounded to whole cells, the centre on a cell centre), at the centre's yaw, or the best
        over yaws every ``yaw_step`` within ±``yaw_window``. ``parallel`` False computes it on
        the calling thread alone (same values), for a caller that shares the cores with a
        running filter."""
        c = np.asarray(center, dtype=np.float64).reshape(-1)
        if c.shape[0] < 6 or not np.all(np.isfinite(c[:6])):
            raise LidarlocError("the surface's centre must be 6 finite numbers (x, y, z, yaw, pitch, roll)")
        c = c[:6].copy()
        half_width, cell = float(half_width), float(cell)
        if not (cell > 0 and math.isfinite(cell) and half_width >= 0 and math.isfinite(half_width)):
            raise LidarlocError(f"surface grid: cell must be > 0 and half width ≥ 0 (got {cell}, {half_width})")
        n_half = int(round(half_width / cell))
        n = 2 * n_half + 1
        if n * n > MAX_CELLS:
            raise LidarlocError(f"surface grid of {n} × {n} cells is too large (at most {MAX_CELLS:,} cells)")
        yaw_window, yaw_step = float(yaw_window), float(yaw_step)
        if not (yaw_window >= 0 and yaw_step > 0 and math.isfinite(yaw_window)):
            raise LidarlocError(f"yaw window must be ≥ 0 and yaw step > 0 (got {yaw_window}, {yaw_step})")
        pts = as_points(points)
        pts = np.ascontiguousarray(pts[:, :3].T, dtype=np.float32)  # (3, M), as the filter reads them
        m = pts.shape[1]
        t0 = time.perf_counter()
        offsets = (np.arange(n) - n_half) * cell
        xs, ys = c[0] + offsets, c[1] + offsets
        n_yaw = int(math.floor(yaw_window / yaw_step + 1e-9))
        yaws = c[3] + np.arange(-n_yaw, n_yaw + 1) * yaw_step
        costs = self.costs(m)
        origin, inv_res, nbx, nby, nbz, slot_of_brick, cells = self.lookup.flat_kernel_args
        # the sensor's position in table cells, rounded to float32 as the filter's kernel does
        tx = ((xs - origin[0]) * inv_res).astype(np.float32)
        ty = ((ys - origin[1]) * inv_res).astype(np.float32)
        tz = np.float32((c[2] - origin[2]) * inv_res)
        best = np.full((n, n), -np.inf)
        best_yaw = np.full((n, n), c[3])
        rows = _surface_rows if parallel else _surface_rows_serial
        out = np.empty((n, n))
        for yaw in yaws:
            rot = _rotated_cells(pts, float(yaw), float(c[4]), float(c[5]), float(inv_res))
            # points in table order (z brick, x cell, y): consecutive points then read the same
            # cache lines (real drive: 97 instead of 112 ms; only the order of the sums changes)
            rot = np.ascontiguousarray(rot[:, np.lexsort((rot[1], np.floor(rot[0]), np.floor(rot[2] / 8.0)))])
            rows(rot, tx, ty, tz, nbx, nby, nbz, slot_of_brick, cells, costs, out)
            better = out > best
            best[better] = out[better]
            best_yaw[better] = yaw
        ms = (time.perf_counter() - t0) * 1000.0
        return Surface(
            xs=xs, ys=ys, ll=best, yaw=best_yaw, center=c, cell=cell, yaw_window=n_yaw * yaw_step, n_points=m, ms=ms
        )
