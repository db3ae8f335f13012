"""Multi-resolution scan matching (Olson's M3RSM) of a 2D scan against the BEV pyramid.

Maximises J(θ_r, t) = Σ_j L0(R_z(θ_r)·B_j + t) over discrete angles θ_r (step d_θ) and
translations t on a lattice of step d_m, by best-first branch and bound (paper, "Multi-Resolution
Scan Matching"): a max-heap of nodes (score, θ_r, level l, translation block); a node at level l
stands for the 2^l × 2^l block of lattice translations starting at (kx, ky); popping a node splits
its block into four quadrants at level l − 1; the first time the heap's best bound cannot beat the
best level-0 score found, that score is the global optimum over the whole search space — the
same optimum an exhaustive search finds.

Admissible bounds. Translations are t = anchor + k·d_m (k integer), so a scan point whose L0
cell at k = 0 is c lands in cell c + k: over a block k ∈ [kx, kx + 2^l) it visits exactly the
L0 cells [c + kx, c + kx + 2^l − 1] (per axis). Two bounds use that, both admissible (≥ the L0
score of every translation in the block, checked in tests/test_m3rsm.py):

* dense (levels 1..DENSE_UPTO): S_l[x] = max of L0 over [x, x + 2^l) — the 2^l × 2^l max-pooling
  with stride 1 — so the point contributes S_l[c + kx], the exact max over the cells it visits.
  S_l is S_{l−1} pooled over two cells 2^{l−1} apart, stored with a low-side pad of 2^l − 1 cells.
* strided (coarser levels): the paper's pyramid L_l (2 × 2 max-pooling, stride 2). Blocks at
  level l start at multiples of 2^l (the root tiling is aligned), so with kx = m·2^l the visited
  cells lie in level-l cells (c >> l) + m to ((c + 2^l − 1) >> l) + m: one cell when c is a
  multiple of 2^l, else two adjacent ones ("straddles"); the max over those ≤ 2 × 2 cells
  (precomputed per level) bounds the point. Each point then needs only (c >> l, straddles), so
  points sharing them merge into one weighted entry (Olson's per-level decimation of the query):
  at coarse levels ~1300 scan cells shrink to a few dozen entries.

The dense bound is tighter (a straddling point's strided bound spans up to 2·2^l cells), the
strided one is cheaper where merging pays. Measured on the KITTI raw drive 0013 (11 scans,
d_m = 1 m, d_θ = 2.5°, median, 2 cores shared with other jobs): all-strided 389 ms global /
68 ms local (±25 m, 360°); all-dense 138 / 35 ms; dense up to level 3, strided above 136 / 33 ms
(fewest nodes per unit of work). DENSE_UPTO = 3 is that split; merging wins more on larger maps,
where more coarse levels are searched.

For inspection a search also reports (``MatchResult.candidates``, ``nodes_per_level``) the best
level-0 poses it scored, best first, and the nodes it expanded per level. Keeping them costs one
comparison per leaf scored, and the search's order and result are those of a search that keeps
none, bit for bit (tests/test_m3rsm.py). They are the leaves of the blocks branch and bound did
not prune, often only the four of the last level-1 block: the tighter the bounds, the fewer
runners-up it ever scores.

The heap is an array binary heap inside the numba kernel, so a whole search runs without the
GIL (the particle filter's threads keep running). The alternative, Python's heapq driving a numba
kernel that bounds a node's four children in one call, found the same optima in 70 ms vs 38 ms
(local ±25 m / 360°, median of 10 KITTI scans) and holds the GIL between calls.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field

import numba as nb
import numpy as np

from ..errors import LidarlocError
from ..maps.bev import BEVPyramid

#: Levels 1..DENSE_UPTO use the dense (stride-1 pooled) bound, coarser levels the strided one.
DENSE_UPTO = 3
#: Level-0 poses a search keeps for inspection (MatchResult.candidates), best first.
N_CANDIDATES = 10


@dataclass(frozen=True)
class MatchResult:
    x: float  # world x of the sensor at the optimum (m)
    y: float
    yaw: float  # rad, wrapped to [-π, π)
    score: float  # L0 score of the optimum, Σ_j L0(cell of point j)
    nodes_expanded: int  # heap pops that were split into quadrants
    ms: float  # wall time of the search (including per-angle preparation)
    n_points: int = 0  # scan cells matched (after down-sampling to d_m)
    region: tuple = ()  # (x_min, y_min, x_max, y_max) of the sensor positions searched
    n_angles: int = 0
    # (K, 4) x, y, yaw, score of the best level-0 poses the search scored, best first (at most
    # ``keep_candidates``); the first is the optimum when there is one. Branch and bound scores
    # only the leaves of blocks it did not prune, so the others are the best it *saw*, not the
    # search space's runners-up; the exhaustive search sees them all.
    candidates: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)), compare=False)
    nodes_per_level: tuple = ()  # nodes expanded per pyramid level (index = level); sums to
    # nodes_expanded (the exhaustive search: all at level 0)


# ------------------------------------------------------------------------------------ scan side
def scan_cells(scan_xy: np.ndarray, resolution: float) -> np.ndarray:
    """Down-sample a 2D scan (sensor frame) to one point per occupied d_m cell (the centroid of the
    points in it), so dense near-range returns do not outweigh far structure. Sorted by cell, so
    the result (and every score computed from it) is deterministic."""
    xy = np.asarray(scan_xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] < 2:
        raise LidarlocError(f"scan must be (K, 2) x, y; got shape {xy.shape}")
    xy = xy[:, :2]
    xy = xy[np.isfinite(xy).all(axis=1)]
    if len(xy) == 0:
        return np.zeros((0, 2))
    idx = np.floor(xy / resolution).astype(np.int64)
    _, inverse, counts = np.unique(idx, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    sums = np.zeros((len(counts), 2))
    np.add.at(sums, inverse, xy)
    return sums / counts[:, None]


def angle_lattice(step: float) -> np.ndarray:
    """The paper's discrete angles θ_r = −π + r·d_θ, r = 0 … ⌊2π / d_θ⌋ − 1 (world-fixed)."""
    n = max(1, int(math.floor(2.0 * math.pi / step + 1e-9)))
    return -math.pi + np.arange(n) * step


def _angles_window(center: float, window: float, step: float) -> np.ndarray:
    """Lattice angles θ_r within ±window of ``center`` (all of them if window ≥ π); the nearest one
    if the window holds none (window < d_θ / 2)."""
    lattice = angle_lattice(step)
    if window >= math.pi - 1e-12:
        return lattice
    off = np.abs((lattice - center + math.pi) % (2.0 * math.pi) - math.pi)
    inside = lattice[off <= window + 1e-12]
    return inside if len(inside) else lattice[[int(np.argmin(off))]]


# ----------------------------------------------------------------------------- numba kernels
@nb.njit(cache=True, nogil=True)
def _angle_cells(B, cos_a, sin_a, ax, ay, inv_d):
    """L0 cell (relative to the grid origin) of every point under every angle at translation 0.
    ax, ay: anchor minus grid origin (m)."""
    R = cos_a.shape[0]
    K = B.shape[0]
    cx = np.empty((R, K), np.int64)
    cy = np.empty((R, K), np.int64)
    for r in range(R):
        c = cos_a[r]
        s = sin_a[r]
        for j in range(K):
            wx = c * B[j, 0] - s * B[j, 1] + ax
            wy = s * B[j, 0] + c * B[j, 1] + ay
            cx[r, j] = np.int64(np.floor(wx * inv_d))
            cy[r, j] = np.int64(np.floor(wy * inv_d))
    return cx, cy


@nb.njit(cache=True, nogil=True)
def score_l0(L0, cxr, cyr, kx, ky):
    """Exact score at L0 of one angle (cells cxr, cyr at k = 0) shifted by (kx, ky) cells."""
    nx, ny = L0.shape
    s = 0.0
    for j in range(cxr.shape[0]):
        x = cxr[j] + kx
        y = cyr[j] + ky
        if x >= 0 and x < nx and y >= 0 and y < ny:
            s += L0[x, y]
    return s


@nb.njit(cache=True, nogil=True)
def level_entries(cx, cy, first, top):
    """Per level l = first..top and angle r, the merged entries (X, Y, code, weight): X = c >> l,
    code = straddles_x + 2·straddles_y (straddles: c is not a multiple of 2^l, so the 2^l cells
    from c span two level-l cells), weight = number of points merged.

    Level ``first`` comes from the points; each next level from the previous one's entries:
    X_l = X_{l−1} >> 1 and straddles_l = straddles_{l−1} | (X_{l−1} & 1). Equal entries are merged
    through a scratch grid (slot → entry index). Returns flat arrays and offsets such that level l,
    angle r is [off[l, r], off[l, r + 1])."""
    R, K = cx.shape
    n_lv = top + 1
    counts = np.zeros((n_lv, R), np.int64)
    n_used = max(top - first + 1, 0)
    cap = R * K * n_used + 1
    ex = np.empty(cap, np.int32)
    ey = np.empty(cap, np.int32)
    ec = np.empty(cap, np.int8)
    ew = np.empty(cap, np.float64)
    off = np.zeros((n_lv, R + 1), np.int64)
    if n_used == 0 or K == 0:
        return ex[:0], ey[:0], ec[:0], ew[:0], off
    xmin, xmax, ymin, ymax = cx.min(), cx.max(), cy.min(), cy.max()
    # the scratch is sized for level `first` (the finest used); coarser levels use a prefix of it
    W = (xmax >> first) - (xmin >> first) + 1
    H = (ymax >> first) - (ymin >> first) + 1
    scratch = np.full(W * H * 4, -1, np.int64)
    mask = (np.int64(1) << first) - 1
    # previous level's entries of the angle being processed
    px = np.empty(K, np.int64)
    py = np.empty(K, np.int64)
    pc = np.empty(K, np.int64)
    pw = np.empty(K, np.float64)
    n = 0
    for r in range(R):
        for l in range(first, top + 1):
            x0 = xmin >> l
            y0 = ymin >> l
            Hl = (ymax >> l) - y0 + 1
            start = n
            m = K if l == first else counts[l - 1, r]
            for i in range(m):
                if l == first:
                    c_x = cx[r, i]
                    c_y = cy[r, i]
                    X = c_x >> first
                    Y = c_y >> first
                    code = (1 if (c_x & mask) != 0 else 0) + (2 if (c_y & mask) != 0 else 0)
                    w = 1.0
                else:
                    X = px[i] >> 1
                    Y = py[i] >> 1
                    code = ((pc[i] & 1) | (px[i] & 1)) + 2 * (((pc[i] >> 1) & 1) | (py[i] & 1))
                    w = pw[i]
                slot = ((X - x0) * Hl + (Y - y0)) * 4 + code
                e = scratch[slot]
                if e < 0:
                    scratch[slot] = n
                    ex[n] = X
                    ey[n] = Y
                    ec[n] = code
                    ew[n] = w
                    n += 1
                else:
                    ew[e] += w
            # clear the slots used, and hand this level's entries to the next level
            counts[l, r] = n - start
            for i in range(n - start):
                e = start + i
                scratch[((ex[e] - x0) * Hl + (ey[e] - y0)) * 4 + ec[e]] = -1
                px[i] = ex[e]
                py[i] = ey[e]
                pc[i] = ec[e]
                pw[i] = ew[e]
    # entries were appended angle-major; reorder level-major so each (l, r) slice is contiguous
    pos = 0
    for l in range(first, n_lv):
        off[l, 0] = pos
        for r in range(R):
            pos += counts[l, r]
            off[l, r + 1] = pos
    oxs = np.empty(n, np.int32)
    oys = np.empty(n, np.int32)
    ocs = np.empty(n, np.int8)
    ows = np.empty(n, np.float64)
    src = 0
    for r in range(R):
        for l in range(first, n_lv):
            dst = off[l, r]
            for i in range(counts[l, r]):
                oxs[dst + i] = ex[src + i]
                oys[dst + i] = ey[src + i]
                ocs[dst + i] = ec[src + i]
                ows[dst + i] = ew[src + i]
            src += counts[l, r]
    return oxs, oys, ocs, ows, off


@nb.njit(cache=True, nogil=True)
def bound(G, gnx, gny, goff, l, ex, ey, ec, ew, a, b, mx, my):
    """Upper bound of level l for block (mx·2^l, my·2^l): Σ w · G_l[code][X + mx, Y + my]. The bound
    grid G_l[code] is padded by one cell on the low side (index X + 1), since a straddling entry
    at X = −1 still sees cell 0."""
    nx = gnx[l]
    ny = gny[l]
    plane = (nx + 1) * (ny + 1)
    base = goff[l]
    s = 0.0
    for e in range(a, b):
        X = ex[e] + mx + 1
        Y = ey[e] + my + 1
        if X >= 0 and X <= nx and Y >= 0 and Y <= ny:
            s += ew[e] * G[base + ec[e] * plane + X * (ny + 1) + Y]
    return s


@nb.njit(cache=True, nogil=True)
def bound_dense(S, snx, sny, soff, l, cxr, cyr, kx, ky):
    """Tight bound of level l for block (kx, ky): Σ_j S_l[c_j + k], S_l[x, y] = max of L0 over
    [x, x + 2^l) × [y, y + 2^l), stored with a low-side pad of 2^l − 1 cells."""
    pad = (np.int64(1) << l) - 1
    nx = snx[l]
    ny = sny[l]
    base = soff[l]
    s = 0.0
    for j in range(cxr.shape[0]):
        x = cxr[j] + kx + pad
        y = cyr[j] + ky + pad
        if x >= 0 and x < nx and y >= 0 and y < ny:
            s += S[base + x * ny + y]
    return s


@nb.njit(cache=True, nogil=True)
def _heap_push(hs, hl, hr, hx, hy, n, s, l, r, x, y):
    """Push into the max-heap (ties: deeper level first, so leaves surface sooner)."""
    if n == hs.shape[0]:
        cap = 2 * n
        hs2 = np.empty(cap, np.float64)
        hl2 = np.empty(cap, np.int32)
        hr2 = np.empty(cap, np.int32)
        hx2 = np.empty(cap, np.int64)
        hy2 = np.empty(cap, np.int64)
        hs2[:n] = hs
        hl2[:n] = hl
        hr2[:n] = hr
        hx2[:n] = hx
        hy2[:n] = hy
        hs, hl, hr, hx, hy = hs2, hl2, hr2, hx2, hy2
    i = n
    while i > 0:
        p = (i - 1) >> 1
        if hs[p] > s or (hs[p] == s and hl[p] <= l):
            break
        hs[i] = hs[p]
        hl[i] = hl[p]
        hr[i] = hr[p]
        hx[i] = hx[p]
        hy[i] = hy[p]
        i = p
    hs[i] = s
    hl[i] = l
    hr[i] = r
    hx[i] = x
    hy[i] = y
    return hs, hl, hr, hx, hy, n + 1


@nb.njit(cache=True, nogil=True)
def _heap_pop(hs, hl, hr, hx, hy, n):
    """Remove the top (read it before calling); returns the new size."""
    n -= 1
    s = hs[n]
    l = hl[n]
    r = hr[n]
    x = hx[n]
    y = hy[n]
    i = 0
    while True:
        c = 2 * i + 1
        if c >= n:
            break
        if c + 1 < n and (hs[c + 1] > hs[c] or (hs[c + 1] == hs[c] and hl[c + 1] < hl[c])):
            c += 1
        if hs[c] < s or (hs[c] == s and hl[c] >= l):
            break
        hs[i] = hs[c]
        hl[i] = hl[c]
        hr[i] = hr[c]
        hx[i] = hx[c]
        hy[i] = hy[c]
        i = c
    if n > 0:
        hs[i] = s
        hl[i] = l
        hr[i] = r
        hx[i] = x
        hy[i] = y
    return n


@nb.njit(cache=True, nogil=True)
def _keep_best(ts, tr, tx, ty, m, s, r, kx, ky):
    """Insert leaf (s, r, kx, ky) into the list ts[:m], best first; an equal score goes after the
    entries already there, so the first of equal scores stays first, as it does for the search's
    own optimum (only a strictly better leaf replaces it). A full list drops its last entry.
    Returns the new length."""
    K = ts.shape[0]
    if m == K:
        if s <= ts[K - 1]:
            return m
        i = K - 1
    else:
        i = m
        m += 1
    while i > 0 and ts[i - 1] < s:
        ts[i] = ts[i - 1]
        tr[i] = tr[i - 1]
        tx[i] = tx[i - 1]
        ty[i] = ty[i - 1]
        i -= 1
    ts[i] = s
    tr[i] = r
    tx[i] = kx
    ty[i] = ky
    return m


@nb.njit(cache=True, nogil=True)
def _branch_and_bound(
    L0,
    G,
    gnx,
    gny,
    goff,
    S,
    snx,
    sny,
    soff,
    dense_upto,
    cx,
    cy,
    ex,
    ey,
    ec,
    ew,
    eoff,
    top,
    kx_lo,
    kx_hi,
    ky_lo,
    ky_hi,
    best_in,
    keep,
):
    """Best-first search over angles r and lattice translations k ∈ [kx_lo, kx_hi] × [ky_lo, ky_hi].
    Returns (best score, r, kx, ky, nodes expanded, nodes expanded per level, the ``keep`` best
    leaves scored as (scores, r, kx, ky, count)). ``best_in`` is a score to beat (−1 for none):
    only strictly better optima are reported (r = −1 if none). Keeping the leaves costs one
    comparison per leaf scored; it changes neither the order of the search nor its result."""
    R = cx.shape[0]
    best = best_in
    best_r = -1
    best_kx = 0
    best_ky = 0
    nodes = 0
    per_level = np.zeros(top + 1, np.int64)
    ts = np.empty(keep, np.float64)
    tr = np.empty(keep, np.int64)
    tx = np.empty(keep, np.int64)
    ty = np.empty(keep, np.int64)
    m = 0
    cap = 1024
    hs = np.empty(cap, np.float64)
    hl = np.empty(cap, np.int32)
    hr = np.empty(cap, np.int32)
    hx = np.empty(cap, np.int64)
    hy = np.empty(cap, np.int64)
    n = 0
    step = np.int64(1) << top
    x_start = (kx_lo >> top) << top  # aligned root tiling (floor to a multiple of 2^top)
    y_start = (ky_lo >> top) << top
    for r in range(R):
        kx = x_start
        while kx <= kx_hi:
            ky = y_start
            while ky <= ky_hi:
                if top == 0:
                    if kx >= kx_lo and ky >= ky_lo:
                        s = score_l0(L0, cx[r], cy[r], kx, ky)
                        if keep > 0 and (m < keep or s > ts[keep - 1]):
                            m = _keep_best(ts, tr, tx, ty, m, s, r, kx, ky)
                        if s > best:
                            best, best_r, best_kx, best_ky = s, r, kx, ky
                else:
                    if top <= dense_upto:
                        s = bound_dense(S, snx, sny, soff, top, cx[r], cy[r], kx, ky)
                    else:
                        s = bound(
                            G, gnx, gny, goff, top, ex, ey, ec, ew, eoff[top, r], eoff[top, r + 1], kx >> top, ky >> top
                        )
                    if s > best:
                        hs, hl, hr, hx, hy, n = _heap_push(hs, hl, hr, hx, hy, n, s, top, r, kx, ky)
                ky += step
            kx += step
    while n > 0:
        s = hs[0]
        l = hl[0]
        r = hr[0]
        kx = hx[0]
        ky = hy[0]
        n = _heap_pop(hs, hl, hr, hx, hy, n)
        if s <= best:
            break  # no block left can hold a better translation than the best leaf found
        nodes += 1
        per_level[l] += 1
        h = l - 1
        half = np.int64(1) << h
        for q in range(4):
            ckx = kx + (q & 1) * half
            cky = ky + (q >> 1) * half
            if ckx > kx_hi or cky > ky_hi or ckx + half - 1 < kx_lo or cky + half - 1 < ky_lo:
                continue  # quadrant entirely outside the search region
            if h == 0:
                cs = score_l0(L0, cx[r], cy[r], ckx, cky)
                if keep > 0 and (m < keep or cs > ts[keep - 1]):
                    m = _keep_best(ts, tr, tx, ty, m, cs, r, ckx, cky)
                if cs > best:
                    best, best_r, best_kx, best_ky = cs, r, ckx, cky
            else:
                if h <= dense_upto:
                    cs = bound_dense(S, snx, sny, soff, h, cx[r], cy[r], ckx, cky)
                else:
                    cs = bound(G, gnx, gny, goff, h, ex, ey, ec, ew, eoff[h, r], eoff[h, r + 1], ckx >> h, cky >> h)
                if cs > best:
                    hs, hl, hr, hx, hy, n = _heap_push(hs, hl, hr, hx, hy, n, cs, h, r, ckx, cky)
    return best, best_r, best_kx, best_ky, nodes, per_level, ts, tr, tx, ty, m


@nb.njit(cache=True, nogil=True)
def _exhaustive(L0, cx, cy, kx_lo, kx_hi, ky_lo, ky_hi, keep):
    """Every angle and lattice translation at L0; first maximum in (r, kx, ky) order. Also the
    ``keep`` best poses as (scores, r, kx, ky, count), as :func:`_branch_and_bound` keeps them."""
    best = -1.0
    best_r = 0
    best_kx = kx_lo
    best_ky = ky_lo
    ts = np.empty(keep, np.float64)
    tr = np.empty(keep, np.int64)
    tx = np.empty(keep, np.int64)
    ty = np.empty(keep, np.int64)
    m = 0
    for r in range(cx.shape[0]):
        for kx in range(kx_lo, kx_hi + 1):
            for ky in range(ky_lo, ky_hi + 1):
                s = score_l0(L0, cx[r], cy[r], kx, ky)
                if keep > 0 and (m < keep or s > ts[keep - 1]):
                    m = _keep_best(ts, tr, tx, ty, m, s, r, kx, ky)
                if s > best:
                    best, best_r, best_kx, best_ky = s, r, kx, ky
    return best, best_r, best_kx, best_ky, ts, tr, tx, ty, m


@nb.njit(cache=True, nogil=True)
def _bound_grid(Ll):
    """For one level, the four (nx+1, ny+1) grids of max over L_l[X..X+fx, Y..Y+fy], fx, fy ∈ {0, 1},
    stored at index (X + 1, Y + 1) for X ∈ [−1, nx − 1]; cells outside L_l count as 0."""
    nx, ny = Ll.shape
    out = np.zeros((4, nx + 1, ny + 1), np.float32)
    for X in range(-1, nx):
        for Y in range(-1, ny):
            for code in range(4):
                fx = code & 1
                fy = code >> 1
                m = np.float32(0.0)
                for ix in range(X, X + fx + 1):
                    for iy in range(Y, Y + fy + 1):
                        if ix >= 0 and ix < nx and iy >= 0 and iy < ny and Ll[ix, iy] > m:
                            m = Ll[ix, iy]
                out[code, X + 1, Y + 1] = m
    return out


@nb.njit(cache=True, nogil=True)
def _sliding_max(prev, l):
    """S_l from S_{l-1}: S_l[x] = max(S_{l−1}[x], S_{l−1}[x + 2^{l−1}]) per axis. Index x of S_l is
    stored at x + 2^l − 1 (S_{l−1} at x + 2^{l−1} − 1)."""
    half = np.int64(1) << (l - 1)
    pad_prev = half - 1
    pad = 2 * half - 1
    px, py = prev.shape
    nx = px + half
    ny = py + half
    out = np.zeros((nx, ny), np.float32)
    for X in range(nx):
        x = X - pad  # world-cell index
        for Y in range(ny):
            y = Y - pad
            m = np.float32(0.0)
            for ddx in range(2):
                xi = x + ddx * half + pad_prev
                if xi < 0 or xi >= px:
                    continue
                for ddy in range(2):
                    yi = y + ddy * half + pad_prev
                    if yi >= 0 and yi < py and prev[xi, yi] > m:
                        m = prev[xi, yi]
            out[X, Y] = m
    return out


# ------------------------------------------------------------------------------- preparation
class _Prepared:
    """The pyramid flattened for the kernels: L0, dense bound grids S_l for levels 1..dense_upto,
    strided bound grids G_l for levels ≥ strided_from (default dense_upto + 1). Only the levels a
    search can use are built: the dense grids grow by 2^l cells per axis per level."""

    def __init__(self, pyramid: BEVPyramid, dense_upto: int, strided_from: int | None = None):
        n = pyramid.n_levels
        strided_from = dense_upto + 1 if strided_from is None else strided_from
        self.n_levels = n
        self.L0 = np.ascontiguousarray(pyramid.levels[0], dtype=np.float32)
        empty = np.zeros(0, np.float32)
        grids, gnx, gny = [], [], []
        for l, lv in enumerate(pyramid.levels):
            use = 1 <= l and l >= strided_from
            grids.append(_bound_grid(np.ascontiguousarray(lv, dtype=np.float32)).ravel() if use else empty)
            gnx.append(lv.shape[0])
            gny.append(lv.shape[1])
        self.G, self.goff = _flatten(grids)
        self.gnx = np.asarray(gnx, np.int64)
        self.gny = np.asarray(gny, np.int64)
        dense, snx, sny = [empty], [gnx[0]], [gny[0]]
        prev = self.L0
        for l in range(1, min(dense_upto, n - 1) + 1):
            prev = _sliding_max(prev, l)
            dense.append(prev.ravel())
            snx.append(prev.shape[0])
            sny.append(prev.shape[1])
        self.S, self.soff = _flatten(dense)
        self.snx = np.asarray(snx, np.int64)
        self.sny = np.asarray(sny, np.int64)


def _flatten(arrays: list) -> tuple[np.ndarray, np.ndarray]:
    offsets = np.cumsum([0] + [len(a) for a in arrays[:-1]]).astype(np.int64)
    return np.concatenate(arrays).astype(np.float32), offsets


_prep_lock = threading.Lock()


def _prepared(pyramid: BEVPyramid, dense_upto: int) -> _Prepared:
    """The kernels' view of ``pyramid`` for one dense/strided split, built once and kept on it."""
    key = ("m3rsm", dense_upto)
    prep = pyramid.derived.get(key)
    if prep is None:
        with _prep_lock:
            prep = pyramid.derived.get(key)
            if prep is None:
                prep = _Prepared(pyramid, dense_upto)
                pyramid.derived[key] = prep
    return prep


def angle_cells(pyramid: BEVPyramid, B: np.ndarray, angles: np.ndarray, anchor) -> tuple[np.ndarray, np.ndarray]:
    ax = float(anchor[0]) - float(pyramid.origin[0])
    ay = float(anchor[1]) - float(pyramid.origin[1])
    return _angle_cells(
        np.ascontiguousarray(B, np.float64), np.cos(angles), np.sin(angles), ax, ay, 1.0 / pyramid.resolution
    )


def _top_level(n_levels: int, width: int, height: int) -> int:
    """Coarsest level worth starting at: one block covers the region, capped by the pyramid."""
    span = max(width, height, 1)
    return int(min(n_levels - 1, max(0, math.ceil(math.log2(span)))))


def _wrap(yaw):
    return (yaw + math.pi) % (2 * math.pi) - math.pi


def _search(
    pyramid, scan_xy, anchor, angles, k_lo, k_hi, beat=-1.0, exhaustive=False, keep: int = N_CANDIDATES
) -> MatchResult:
    if keep < 0:
        raise LidarlocError(f"keep_candidates must be ≥ 0, got {keep}")
    t0 = time.perf_counter()
    B = scan_cells(scan_xy, pyramid.resolution)
    cx, cy = angle_cells(pyramid, B, angles, anchor)
    return search_cells(pyramid, cx, cy, anchor, angles, k_lo, k_hi, beat, exhaustive, keep, t0)


def search_cells(
    pyramid, cx, cy, anchor, angles, k_lo, k_hi, beat=-1.0, exhaustive=False, keep: int = N_CANDIDATES, t0=None
) -> MatchResult:
    """The search of :func:`match` for scan cells already placed on the pyramid's L0 grid (``cx``,
    ``cy`` per angle at translation 0, as :func:`angle_cells` places them): the tiled global
    search places them once on the city's grid and shifts them by whole cells into each tile."""
    t0 = time.perf_counter() if t0 is None else t0
    dense_upto = DENSE_UPTO
    prep = _prepared(pyramid, dense_upto)
    d = pyramid.resolution
    kx_lo, ky_lo = int(k_lo[0]), int(k_lo[1])
    kx_hi, ky_hi = int(k_hi[0]), int(k_hi[1])
    region = (anchor[0] + kx_lo * d, anchor[1] + ky_lo * d, anchor[0] + kx_hi * d, anchor[1] + ky_hi * d)
    keep = int(keep)
    if exhaustive:
        score, r, kx, ky, ts, tr, tx, ty, m = _exhaustive(prep.L0, cx, cy, kx_lo, kx_hi, ky_lo, ky_hi, keep)
        nodes = (kx_hi - kx_lo + 1) * (ky_hi - ky_lo + 1) * len(angles)
        per_level = (int(nodes),)
    else:
        top = _top_level(prep.n_levels, kx_hi - kx_lo + 1, ky_hi - ky_lo + 1)
        ex, ey, ec, ew, eoff = level_entries(cx, cy, dense_upto + 1, top)
        score, r, kx, ky, nodes, levels, ts, tr, tx, ty, m = _branch_and_bound(
            prep.L0,
            prep.G,
            prep.gnx,
            prep.gny,
            prep.goff,
            prep.S,
            prep.snx,
            prep.sny,
            prep.soff,
            dense_upto,
            cx,
            cy,
            ex,
            ey,
            ec,
            ew,
            eoff,
            top,
            kx_lo,
            kx_hi,
            ky_lo,
            ky_hi,
            float(beat),
            keep,
        )
        per_level = tuple(int(v) for v in levels)
    ms = (time.perf_counter() - t0) * 1e3
    # the same arithmetic as the optimum's pose below, so the first candidate equals it exactly
    candidates = (
        np.column_stack([anchor[0] + tx[:m] * d, anchor[1] + ty[:m] * d, _wrap(angles[tr[:m]]), ts[:m]])
        .astype(np.float64)
        .reshape(-1, 4)
    )
    common = dict(
        nodes_expanded=int(nodes),
        ms=ms,
        n_points=int(cx.shape[1]),
        region=region,
        n_angles=len(angles),
        candidates=candidates,
        nodes_per_level=per_level,
    )
    if r < 0:  # nothing strictly better than `beat`
        return MatchResult(x=math.nan, y=math.nan, yaw=math.nan, score=float(score), **common)
    return MatchResult(
        x=float(anchor[0] + kx * d),
        y=float(anchor[1] + ky * d),
        yaw=float(_wrap(angles[r])),
        score=float(score),
        **common,
    )


# ------------------------------------------------------------------------------------ public API
def match(
    pyramid: BEVPyramid,
    scan_xy: np.ndarray,
    center_xy,
    half_extent,
    yaw_center: float = 0.0,
    yaw_window: float = math.pi,
    angle_step: float = 2.5 * math.pi / 180.0,
    min_score: float | None = None,
    keep_candidates: int = N_CANDIDATES,
) -> MatchResult:
    """Local search (paper, "Scan-to-map matching"): translations center ± half_extent on a lattice
    of step d_m anchored at center_xy (the search rectangle's lower bound is center − half_extent,
    so the start position is on it), yaws θ_r = −π + r·d_θ within ± yaw_window of yaw_center (the
    full circle if yaw_window ≥ π).

    The angles are the paper's world-fixed lattice, not anchored at the start yaw: a start pose
    near the truth is then usually off the lattice, and the best lattice pose may or may not score
    above it; anchoring the yaws too would make the start itself a candidate, so a start already
    near the truth could never be beaten — and never refined by GICP.

    ``min_score``: report only an optimum strictly above it (blocks whose bound does not exceed it
    are pruned from the start); if there is none, x, y, yaw are NaN and score = min_score.

    ``keep_candidates``: how many of the best level-0 poses the search scored to report in
    ``MatchResult.candidates`` (0: none); keeping them changes neither the result nor the work."""
    if angle_step <= 0:
        raise LidarlocError(f"angle_step must be > 0, got {angle_step}")
    d = pyramid.resolution
    nx = int(math.floor(float(half_extent[0]) / d + 1e-9))
    ny = int(math.floor(float(half_extent[1]) / d + 1e-9))
    angles = _angles_window(float(yaw_center), float(yaw_window), float(angle_step))
    # The lattice starts at the region's lower corner (the paper's lower bound), so the root blocks
    # are aligned with the region: fewer blocks straddle its edges than with blocks aligned at the
    # centre (e.g. 7 instead of 8 level-3 blocks across ±25 cells). The start position is lattice
    # point (nx, ny).
    anchor = (float(center_xy[0]) - nx * d, float(center_xy[1]) - ny * d)
    beat = -1.0 if min_score is None else float(min_score)
    return _search(pyramid, scan_xy, anchor, angles, (0, 0), (2 * nx, 2 * ny), beat=beat, keep=keep_candidates)


def _global_lattice(pyramid: BEVPyramid):
    """Sensor positions at L0 cell centres over the whole grid."""
    d = pyramid.resolution
    anchor = (float(pyramid.origin[0]) + 0.5 * d, float(pyramid.origin[1]) + 0.5 * d)
    nx, ny = pyramid.shape
    return anchor, (0, 0), (nx - 1, ny - 1)


def match_global(
    pyramid: BEVPyramid,
    scan_xy: np.ndarray,
    angle_step: float = 2.5 * math.pi / 180.0,
    keep_candidates: int = N_CANDIDATES,
) -> MatchResult:
    """Global search: every L0 cell centre of the map as sensor position, θ_r = −π + r·d_θ.
    ``keep_candidates`` as for :func:`match`."""
    if angle_step <= 0:
        raise LidarlocError(f"angle_step must be > 0, got {angle_step}")
    anchor, lo, hi = _global_lattice(pyramid)
    return _search(pyramid, scan_xy, anchor, angle_lattice(angle_step), lo, hi, keep=keep_candidates)


def exhaustive_match(
    pyramid: BEVPyramid,
    scan_xy: np.ndarray,
    center_xy=None,
    half_extent=None,
    yaw_center: float = 0.0,
    yaw_window: float = math.pi,
    angle_step: float = 2.5 * math.pi / 180.0,
    keep_candidates: int = N_CANDIDATES,
) -> MatchResult:
    """Brute force over the same search space as :func:`match` (or :func:`match_global` when
    center_xy is None). For tests; O(angles × translations × points)."""
    d = pyramid.resolution
    if center_xy is None:
        anchor, lo, hi = _global_lattice(pyramid)
        angles = angle_lattice(angle_step)
    else:
        nx = int(math.floor(float(half_extent[0]) / d + 1e-9))
        ny = int(math.floor(float(half_extent[1]) / d + 1e-9))
        anchor = (float(center_xy[0]) - nx * d, float(center_xy[1]) - ny * d)
        lo, hi = (0, 0), (2 * nx, 2 * ny)
        angles = _angles_window(float(yaw_center), float(yaw_window), float(angle_step))
    return _search(pyramid, scan_xy, anchor, angles, lo, hi, exhaustive=True, keep=keep_candidates)


def score_pose(pyramid: BEVPyramid, scan_xy: np.ndarray, x: float, y: float, yaw: float) -> float:
    """L0 score of one pose, computed exactly as the search scores its candidates (same scan
    down-sampling, same cell arithmetic), so it is comparable with MatchResult.score."""
    prep = _prepared(pyramid, DENSE_UPTO)
    B = scan_cells(scan_xy, pyramid.resolution)
    cx, cy = angle_cells(pyramid, B, np.array([float(yaw)]), (float(x), float(y)))
    return float(score_l0(prep.L0, cx[0], cy[0], 0, 0))
